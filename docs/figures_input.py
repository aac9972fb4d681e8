"""Tables on what the network reads of its input and what that means across sensors, each
rendered from the JSON a command wrote (``docs/render.py`` pastes them; nothing here types a
measured number)."""

from __future__ import annotations

import json
import shlex
from collections.abc import Callable
from pathlib import Path
from typing import Any

from figures_kit import ROOT, f3, load, source, table, when

RECEPTIVE_ROWS = "reports/model/receptive-rows.json"
BACKBONE_ROWS = "reports/model/backbone-rows.jsonl"
COMMON_BEAMS = "reports/model/common-beams.json"
COMMON_RUNS = ("reports/model/common-towns.json", "reports/model/common-towns-slow.json")
STRUCTURE_RUN = "reports/model/structure-towns.json"
STRUCTURE_GPU = tuple(
    f"reports/model/{n}.json"
    for n in ("structure-long", "structure-many", "structure-many-renders")
)
STRUCTURE_BEAMS = "reports/model/structure-beams.json"
SENSORS = "reports/model/sensors.json"
STRUCTURE_REAL = {
    "reports/model/structure-real-kitti.json": "KITTI 00, frames 0–100",
    "reports/model/structure-real-nuscenes.json": "nuScenes scene-0061",
}


def receptive_rows() -> str:
    """Which rows of the range image reach each model file's descriptor, and how many of each
    catalogue sensor's beams those rows show."""
    r = load(RECEPTIVE_ROWS)
    out = source(RECEPTIVE_ROWS, r["command"], when(r))
    files = []
    for m in r["models"]:
        lo, hi = m["elevation_deg_reaching_descriptor"]
        rows = ", ".join(f"{a}–{b}" for a, b in m["descriptor_rows"])
        files.append(
            [
                f"`{m['model']}` ({m['views']} views)",
                f"{m['rows_reaching_descriptor']} of {m['rows']}: rows {rows}",
                f"{lo:+.1f}° … {hi:+.1f}°",
                f"{m['smallest_change_of_a_row_reaching_it']:.1e}",
                f"{m['largest_change_of_a_row_not_reaching_it']:.1e}",
            ]
        )
    head = [
        "file",
        "rows that reach the descriptor",
        "their elevations",
        "least change a read row makes",
        "most change another row makes",
    ]
    out += f"\nKITTI 00 scan {r['scan'].split('/')[-1]}, one row emptied at a time.\n\n"
    out += table(head, files)
    shipped = r["models"][0]
    sensors = [
        [name, s["beams"], s["beams_in_image"], s["beams_reaching_descriptor"]]
        for name, s in shipped["sensors"].items()
    ]
    out += f"\nBeams of each sensor in `{shipped['model']}`'s image (elevation mode):\n\n"
    return out + table(["sensor", "beams", "in the image", "in the rows read"], sensors)


def _backbone_runs() -> list[dict[str, Any]]:
    lines = (ROOT / BACKBONE_ROWS).read_text().splitlines()
    return [json.loads(line) for line in lines if line.strip()]


def backbone_rows() -> str:
    """The reference backbone against all-rows at one budget, two seeds each, on tiny-val."""
    runs = _backbone_runs()
    first = runs[0]
    words = shlex.split(first["command"])
    command = shlex.join([*words[:2], "NAME", "SPEC", *words[4:]])  # each line: its own
    out = source(BACKBONE_ROWS, command, when(first))
    spec = first["spec"]["train"]
    out += (
        f"\nThe narrow network, {len(first['epochs']) - 1} epochs of {spec['epoch_scans']} scans "
        "(batches of 16) on the `tiny` town, validated on `tiny-val`; epoch 0 is the untrained "
        "network (the towns: `gen-data DIR --preset tiny`, `--preset tiny-val`). F1max / "
        "Recall@1 (all revisits), F1max on reverse revisits.\n\n"
    )
    rows = []
    for run in runs:
        best = max(run["epochs"], key=lambda e: e["f1max"])
        last = run["epochs"][-1]
        rows.append(
            [
                run["name"],
                " · ".join(f3(e["f1max"]) for e in run["epochs"]),
                f"{f3(best['f1max'])} / {f3(best['recall@1'])} (epoch {best['epoch']})",
                f3(last["f1max_reverse"]),
            ]
        )
    head = ["run", "F1max per epoch", "best F1max / R@1", "reverse F1max, last epoch"]
    return out + table(head, rows)


def common_beams() -> str:
    """AR@1 across sensors, as the service projects today against the common beams."""
    r = load(COMMON_BEAMS)
    c = r["common"]
    out = source(COMMON_BEAMS, r["command"], when(r))
    out += (
        f"\nThe shipped weights ({r['views']} views, `{r['model_id']}`), the descriptor alone; "
        f"common beams: each sensor's beams nearest the elevations of `{c['elevations_of']}`, "
        f"within {c['tolerance_deg']:g}°. AR@1 / AR@5 (a hit within 5 m).\n"
    )
    splits = (("val", "val: calibration town `cal-x00` (chosen here)"), ("test", "test"))
    for split, title in splits:
        rows = [
            [
                p["queries"],
                p["map"],
                f"{f3(p['elevation']['ar@1'])} / {f3(p['elevation']['ar@5'])}",
                f"{f3(p['common']['ar@1'])} / {f3(p['common']['ar@5'])}",
            ]
            for p in r[split]
        ]
        out += f"\n{title}:\n\n"
        out += table(["queries", "map", "as served today", "common beams"], rows)
    return out


def epoch_rows(
    runs: list[dict[str, Any]], label: Callable[[dict[str, Any]], str]
) -> tuple[list[str], list[list[str]]]:
    """The epochs of ``runs`` as table rows, each run's first cell ``label(run)``."""
    names = list(runs[0]["epochs"][0]["val_sensors"])
    rows = []
    for r in runs:
        for e in r["epochs"]:
            spread, real = e["health"]["spread"], e["real_cosine_min"]
            rows.append(
                [
                    label(r),
                    str(e["epoch"]),
                    f3(e["score"]),
                    f"{f3(e['val']['all']['f1max'])} / {f3(e['val']['all']['recall@1'])}",
                    *[f3(e["val_sensors"][n]["cross"]["f1max"]) for n in names],
                    "—" if spread is None else f"{spread:.3f}",
                    "—" if e["collapsing"] is None else ("yes" if e["collapsing"] else "no"),
                    "—" if real is None else f"{real:.5f}",
                ]
            )
    head = ["epoch", "score", "val F1max / R@1", *[f"{n} across" for n in names]]
    return [*head, "spread", "collapsing", "real min cosine"], rows


EPOCH_COLUMNS = (
    "F1max of the validation drive (`val-kitti-hdl64`) and of each rendering's scans against "
    "it (across sensors); the spread and the collapse flag from the health numbers; the "
    "minimum cosine of real KITTI scans under a continuous turn (one view).\n\n"
)


def planned(r: dict[str, Any], label: str) -> str:
    return (
        f"- `{r['run']}` ({label}): {r['epochs_run']} of {r['epochs_planned']} planned "
        f"epochs ran; it keeps epoch {r['best']['epoch']}\n"
    )


def common_run() -> str:
    """The ``common-towns`` runs' epochs (both rates): validation, across sensors, health."""
    runs = [load(path) for path in COMMON_RUNS]
    out = "".join(source(p, r["command"], when(r)) for p, r in zip(COMMON_RUNS, runs, strict=True))
    out += "\nEpoch 0 is the shipped weights on common beams. " + EPOCH_COLUMNS
    out += "".join(planned(r, f"rate {r['train_config']['lr']:g}") for r in runs)
    head, rows = epoch_rows(runs, lambda r: f"{r['train_config']['lr']:g}")
    return out + "\n" + table(["rate", *head], rows)


def structure_run() -> str:
    """The ``structure-towns`` run's epochs, from scratch: validation, across sensors, health."""
    r = load(STRUCTURE_RUN)
    out = source(STRUCTURE_RUN, r["command"], when(r))
    out += "\nEpoch 0 is the untrained network. " + EPOCH_COLUMNS
    out += planned(r, f"seed {r['train_config']['seed']}")
    head, rows = epoch_rows([r], lambda r: f"{r['train_config']['seed']:g}")
    return out + "\n" + table(["seed", *head], rows)


_GPU_DATA = {
    "structure-long": "train-b and train-x00 … x03",
    "structure-many": "train-b and train-x00 … x11",
    "structure-many-renders": "train-b, train-x00 … x11 and train-b's three renderings",
    "bev-long": "the bev input, all-rows backbone; train-b and train-x00 … x03",
    "structure-all-rows-long": "the structure input, all-rows backbone; train-b and "
    "train-x00 … x03",
}


def structure_gpu() -> str:
    """The structure recipe's three runs on a lent GPU: five towns, thirteen, and thirteen
    with train-b's renderings by three other sensors."""
    return gpu_runs(STRUCTURE_GPU)


_COUNT = {2: "two", 3: "three", 4: "four"}


def gpu_runs(paths: tuple[str, ...]) -> str:
    runs = [load(path) for path in paths]
    out = "".join(source(p, r["command"], when(r)) for p, r in zip(paths, runs, strict=True))
    where = runs[0]["trained_on"]
    m, towns = where.get("device") or where["machine"], where["towns"]
    same = sum(bool(t.get("byte_identical")) for t in towns if "byte_identical" in t)
    carried = sum("byte_identical" in t for t in towns)
    out += (
        f"\nThe {_COUNT[len(runs)]} ran side by side on one lent {m['gpu']} ({m['cpus']} "
        f"cores, torch {m['torch']}; `python benchmarks/lent_gpu.py`), on the {len(towns)} "
        f"towns and renderings simulated again there in {where['prepare_s']:.0f} s ({same} of the "
        f"{carried} whose tables went from here byte-identical to this machine's scans; the "
        "tables carried, their loop tables' fingerprints renewed). No real scans went along, so "
        "the real-scan column is empty. Epoch 0 is the untrained network. " + EPOCH_COLUMNS
    )
    out += "".join(planned(r, _GPU_DATA[r["run"].split("/")[-1]]) for r in runs)
    head, rows = epoch_rows(runs, lambda r: f"`{r['run'].split('/')[-1]}`")
    return out + "\n" + table(["run", *head], rows)


def structure_real() -> str:
    """The best structure network on real scans: one view under random continuous turns,
    odd→even retrieval, KITTI queries thinned to fewer rings."""
    return real_scans(STRUCTURE_REAL)


def real_scans(paths: dict[str, str], views: str = "one view") -> str:
    reports = {path: load(path) for path in paths}
    out = "".join(source(p, r["command"], when(r)) for p, r in reports.items())
    rows = []
    for path, r in reports.items():
        y, q = r["yaw_invariance"], r["retrieval_odd_to_even"]
        rows.append(
            [
                paths[path],
                f"{r['sensor']} ({r['scans']} scans)",
                f"{y['cosine_min']:.5f}",
                f"{y['turned_over_one_metre_step']:.3f}",
                f"{f3(q['recall@1'])} / {f3(q['scan_context']['recall@1'])}",
            ]
        )
    head = [
        "scans",
        "sensor",
        f"min cosine, random turns ({views})",
        "turned copy / 1 m step (squared distance)",
        "odd→even R@1 / Scan Context's",
    ]
    out += "\n" + table(head, rows)
    thin = next(iter(reports.values()))["thinned"]
    lines = [
        f"- {b} rings (declared): Recall@1 {f3(t['declared']['recall@1'])}"
        + (
            f" (two stages {f3(t['declared']['reranked']['recall@1'])})"
            if "reranked" in t["declared"]
            else ""
        )
        + ", cosine to the whole "
        f"scan median {t['declared']['cosine_to_full']['median']:.4f} / min "
        f"{t['declared']['cosine_to_full']['min']:.4f}"
        for b, t in thin.items()
    ]
    return out + "\nKITTI queries thinned against whole scans:\n\n" + "\n".join(lines) + "\n"


def structure_beams() -> str:
    """The best structure network across sensors on the sensor test town, beside the shipped
    weights (as served, and on common beams) and Scan Context on the same pairs."""
    return beams_table([STRUCTURE_BEAMS])


def _run_of(report: dict[str, Any]) -> str:
    """The run a ``common_beams.py`` report measured: its ``--model``'s folder."""
    args = shlex.split(report["command"])
    return Path(args[args.index("--model") + 1]).parent.name


def beams_table(paths: list[str]) -> str:
    nets, shipped, sensors = [load(p) for p in paths], load(COMMON_BEAMS), load(SENSORS)
    done = [*zip(paths, nets, strict=True), (COMMON_BEAMS, shipped), (SENSORS, sensors)]
    out = "".join(source(p, x["command"], when(x)) for p, x in done)
    sc = {
        (a["query_sensor"], a["map_sensor"]): a["scan_context"] for a in sensors["across_sensors"]
    }
    named = ", ".join(
        f"`{r['model_id']}` ({_run_of(r)}: {r['views']} view a scan, input `{r['sensor_input']}`)"
        for r in nets
    )
    out += (
        f"\n{named}: the descriptor alone, against the shipped weights as served (elevation) "
        "and on common beams, and Scan Context on the same test pairs (`benchmarks/sensors.py`: "
        "the same presets, simulated by that command). A second drive by the first sensor "
        "queried against the first drive's map by the second; AR@1 / AR@5, a hit within 5 m.\n"
    )
    for split in ("test", "val"):
        ship = {(p["queries"], p["map"]): p for p in shipped[split]}
        by_net = [{(p["queries"], p["map"]): p[r["sensor_input"]] for p in r[split]} for r in nets]
        rows = []
        for key in by_net[0]:
            other = ship.get(key, {})
            row = [*key, *(f"{f3(n[key]['ar@1'])} / {f3(n[key]['ar@5'])}" for n in by_net)]
            for mode in ("elevation", "common"):
                row.append(f3(other[mode]["ar@1"]) if mode in other else "—")
            if split == "test":
                row.append(f3(sc[key]["ar@1"]) if key in sc else "—")
            rows.append(row)
        head = [
            "queries",
            "map",
            *(f"`{_run_of(r)}` ({r['sensor_input']})" for r in nets),
            "shipped, as served",
            "shipped, common beams",
        ]
        if split == "test":
            head.append("Scan Context")
            out += "\ntest (the sensor test town):\n\n"
        else:
            out += "\nval (calibration town `cal-x00`):\n\n"
        out += table(head, rows)
    return out


LERP_INPUT = "reports/model/lerp-input-{split}.json"


def lerp_input(split: str) -> str:
    """``elevation`` against ``elevation-lerp`` on one split's renderings and thinned scans:
    own map, the car's map, cosine to the car, and the pick by the mean."""
    rel = LERP_INPUT.format(split=split)
    r = load(rel)
    rows = []
    for x in r["rows"]:
        a, b = x["elevation"], x["elevation-lerp"]
        rows.append(
            [
                f"`{x['rendering']}`",
                *(
                    f"{f3(a[f'{k}_f1max'])} / {f3(a[f'{k}_recall@1'])} → "
                    f"{f3(b[f'{k}_f1max'])} / {f3(b[f'{k}_recall@1'])}"
                    for k in ("own", "car")
                ),
                f"{f3(a['cosine_to_car'])} → {f3(b['cosine_to_car'])}",
            ]
        )
    m = r["mean"]
    out = source(rel, r["command"], when(r))
    out += (
        f"\n`{Path(r['model']).name}`, {r['views']} view a scan, the descriptor alone, "
        f"`elevation` → `elevation-lerp`. The car's map: `{r['car']}`. Mean of the four "
        f"(F1max and R@1, own map and the car's) over the rows: {m['elevation']:.3f} → "
        f"{m['elevation-lerp']:.3f}, the higher: **{r['pick']}**.\n\n"
    )
    head = ["rendering", "own map: F1max / R@1", "the car's map: F1max / R@1", "cosine to car"]
    return out + table(head, rows)


LERP_REAL = {
    "reports/model/lerp-real-kitti.json": "KITTI 00, frames 0–100",
    "reports/model/lerp-real-nuscenes.json": "nuScenes scene-0061",
}


def lerp_real() -> str:
    """The shipped weights with the ``elevation-lerp`` input on real scans (its thinned
    KITTI queries are where the input differs from the shipped file's)."""
    return real_scans(LERP_REAL, "three views")


PROJECTION = "reports/service/projection.json"


def lerp_cost() -> str:
    """What the service's projection of one scan costs by each input, other sensors' scans
    (``benchmarks/projection.py``'s ``service_input`` rows)."""
    r = load(PROJECTION)
    rows = [
        [x["profile"], f"`{x['input']}`", f"{x['median_ms']:.1f}", f"{x['p90_ms']:.1f}"]
        for x in r["results"]
        if x["function"].startswith("service_input")
    ]
    n = r["results"][0]["points"]
    out = source(PROJECTION, r["command"], when(r))
    out += f"\nOne scan of {n:,} points ({r['source']}) projected as the service does, by sensor "
    out += "and input (the shipped file's views), ms:\n\n"
    return out + table(["scan's sensor", "input", "median", "p90"], rows)


RENDERERS = {
    "lerp-cost": lerp_cost,
    "lerp-input-val": lambda: lerp_input("val"),
    "lerp-input-test": lambda: lerp_input("test"),
    "lerp-real": lerp_real,
    "receptive-rows": receptive_rows,
    "backbone-rows": backbone_rows,
    "common-beams": common_beams,
    "common-run": common_run,
    "structure-run": structure_run,
    "structure-gpu": structure_gpu,
    "structure-real": structure_real,
    "structure-beams": structure_beams,
}
