"""Every catalogue sensor (``benchmarks/sensors.py``) for several model files on the same
drives: the default file beside its twins, and beside the every-sensor option."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from figures_kit import ROOT, load, source, table, when

DEFAULT = "reports/model/sensors.json"
# the default file and its twins: the same weights, other views
TWIN_RUNS = (
    ("three views (the default file)", DEFAULT),
    ("one view, aligned columns", "reports/model/sensors-one-view.json"),
    ("three views met at the tokens", "reports/model/sensors-tokens.json"),
)
# the default file and the every-sensor option (models/overlapmamba-any-sensor.onnx)
OPTION_RUNS = (
    ("the default file (HDL-64E, three views)", DEFAULT),
    ("every sensor, one view (the option)", "reports/model/sensors-any-sensor.json"),
)
# the every-sensor option's first stages, the same network and aligned columns, each file with
# its own calibration: mixed:0.5:8:none (runs/any-sensor-aligned), spectrum:32:sqrt (the option
# as shipped on 2026-12-01, runs/any-sensor-option-spectrum-32) and the option now
FIRST_STAGE_RUNS = (
    ("`mixed:0.5:8:none`", "reports/model/sensors-any-sensor-aligned.json"),
    ("`spectrum:32:sqrt`", "reports/model/sensors-any-sensor-spectrum-32.json"),
    ("`mixed:0.75:32:sqrt` (the option)", "reports/model/sensors-any-sensor.json"),
)
# the default file, its one-view twin and the one-pass file (the one-view twin with the yaw
# features' spectrum in its first stage: models/overlapmamba-hdl64-one-pass.onnx)
ONE_PASS_RUNS = (
    ("three views (the default file)", DEFAULT),
    ("one view, aligned columns (the twin)", "reports/model/sensors-one-view.json"),
    ("one pass, the spectrum in the first stage", "reports/model/sensors-one-pass.json"),
)
# the every-sensor recipe's network at epoch 10 (the option's first file) and continued to
# epoch 16 (the option's now), each with its first stage as chosen on cal-x00, as served with
# the service's defaults
MORE_RUNS = (
    (
        "epoch 10 (`bev-span-thin-cpu-e10-still`)",
        "reports/model/sensors-bev-span-thin-cpu-e10-still.json",
    ),
    (
        "epoch 16 (`bev-span-thin-cpu-more-e16-still`)",
        "reports/model/sensors-bev-span-thin-cpu-more-e16-still.json",
    ),
)


def _fr(m: dict) -> str:
    return f"{m['f1max']:.3f} / {m['recall@1']:.3f}"


def sensors_table(runs: tuple[tuple[str, str], ...]) -> str:
    """The sensors benchmark of each file on the same drives, town by town and pair by pair,
    a row per file."""
    loaded = [(label, path, load(path)) for label, path in runs]
    out = "".join(
        source(path, r.get("command", "python benchmarks/sensors.py"), when(r))
        for _, path, r in loaded
    )
    towns = [{Path(x["town"]).name: x for x in r["same_sensor"]} for _, _, r in loaded]
    common = [t for t in towns[0] if all(t in other for other in towns[1:])]
    same = all(tw[t]["scan_context"] == towns[0][t]["scan_context"] for tw in towns for t in common)
    margins = [r.get("verify", {}).get("ambiguity_margin") for *_, r in loaded]
    out += (
        "\nSame sensor, F1max / Recall@1 (all revisits); verified precision / recall at each "
        "file's own thresholds ("
        + "; ".join(
            f"{label}: ambiguity margin {m:g}"
            if m is not None
            else f"{label}: without an ambiguity margin (measured before the check)"
            for (label, *_), m in zip(loaded, margins, strict=True)
        )
        + "). Scan Context "
        + (
            "scored the same in every run on every town: the same drives."
            if same
            else "scored differently between the runs: not the same drives."
        )
        + "\n\n"
    )
    rows = []
    for t in common:
        for k, (label, _, _) in enumerate(loaded):
            x = towns[k][t]
            v = x["verified"]  # None: measured with --no-verify
            rows.append(
                [
                    f"{x['sensor']} ({x['mount']})" if k == 0 else "",
                    label,
                    _fr(x["descriptor"]),
                    _fr(x["two_stage"]),
                    _fr(x["scan_context"]) if k == 0 else "",
                    f"{v['precision']:.3f} / {v['recall']:.3f}" if v else "not registered",
                ]
            )
    head = ["sensor (mounting)", "file", "descriptor alone", "two stages (service)"]
    out += table([*head, "Scan Context", "verified precision / recall"], rows)
    out += "\nAcross sensors, AR@1 (a hit within 5 m):\n\n"
    pairs = [
        {(p["query_sensor"], p["map_sensor"]): p for p in r["across_sensors"]} for *_, r in loaded
    ]
    rows = []
    for key in pairs[0]:
        if not all(key in other for other in pairs[1:]):
            continue
        for k, (label, _, _) in enumerate(loaded):
            p = pairs[k][key]
            rows.append(
                [
                    f"{key[0]} against {key[1]}" if k == 0 else "",
                    label,
                    f"{p['descriptor']['ar@1']:.3f}",
                    f"{p['two_stage']['ar@1']:.3f}",
                    f"{p['scan_context']['ar@1']:.3f}" if k == 0 else "",
                ]
            )
    head = ["queries against map", "file", "descriptor alone", "two stages (service)"]
    return out + table([*head, "Scan Context"], rows)


def real_rows(runs: tuple[tuple[str, str], ...]) -> str:
    """Each file on the real scans of the same benchmark: KITTI 00 odd frames, turned, against
    the even ones, whole and thinned; nuScenes odd → even; the lowest cosine under turns."""
    out, rows, counts = "", [], ""
    for label, path in runs:
        r = load(path)
        kitti, nus = r.get("real_thinned"), r.get("real_hdl32")
        if not kitti or not nus:
            continue
        out += source(path, r.get("command", "python benchmarks/sensors.py"), when(r))
        ret = kitti["retrieval_odd_to_even"]
        cells = [label, f"{ret['recall@1']:.3f} / {ret['reranked']['recall@1']:.3f}"]
        for beams in ("32", "16"):
            t = kitti["thinned"][beams]["declared"]
            cells.append(
                f"{t['recall@1']:.3f} / {t['reranked']['recall@1']:.3f}; "
                f"{t['cosine_to_full']['median']:.3f}"
            )
        n = nus["retrieval_odd_to_even"]
        cells.append(f"{n['recall@1']:.3f} / {n['reranked']['recall@1']:.3f}")
        counts = f"{ret['queries']} KITTI 00 queries against {ret['database']} scans, " + (
            f"{n['queries']} of nuScenes against {n['database']}"
        )
        turns = (kitti["yaw_invariance"]["cosine_min"], nus["yaw_invariance"]["cosine_min"])
        cells.append(" / ".join(f"{c:.5f}" for c in turns))
        rows.append(cells)
    head = ["file", "KITTI 00 R@1 (descriptor / two stages)", "32 rings declared; median cosine"]
    head += ["16 rings declared; median cosine", "nuScenes HDL-32E R@1", "turn: lowest cosine"]
    out += (
        "\nReal scans (KITTI 00 odd frames, turned at random, against the even ones, a hit "
        "within 3 m; thinned queries keep every second or fourth ring, declared as the sensor "
        "they now are; nuScenes odd → even within 6 m; the lowest cosine of a scan to its turned "
        f"copy, KITTI 00 / nuScenes; {counts}):\n\n"
    )
    return out + table(head, rows)


VERIFY_ACROSS = "reports/service/verify-across-any-sensor.json"
VERIFY_ACROSS_PLAIN = "reports/service/verify-across-any-sensor-no-view.json"


def _margin_since(model: str, measured: dict[str, Any]) -> str:
    """Where the file now carries an ambiguity margin the run was measured without: said, as
    the check only refuses closures (recall as served can only be lower)."""
    from overlapmamba.service.calibration import read_model_metadata

    now = read_model_metadata(ROOT / model).calibration.get("verify")
    margin = now.values.get("ambiguity_margin") if now is not None else None
    if margin is None or measured.get("ambiguity_margin") is not None:
        return ""
    return (
        f", measured before the file carried its ambiguity margin ({margin:g}): the check "
        "only refuses closures, so recall as served can only be lower"
    )


def verify_across(path: str = VERIFY_ACROSS, plain_path: str | None = VERIFY_ACROSS_PLAIN) -> str:
    """Verified closures across sensors on the sensor test town, pair by pair: precision /
    recall at the file's thresholds, scored within the keyframe sensor's field of view (as
    the service does), and over all the query's points where that run (``plain_path``) is
    there."""
    from figures_pairs import NAMES

    r = load(path)
    out = source(path, r["command"], when(r))
    plain = load(plain_path) if plain_path and (ROOT / plain_path).is_file() else None
    if plain is not None and plain_path is not None:
        if plain["model_id"] != r["model_id"]:
            raise ValueError(f"{path} and {plain_path} measured different files")
        out += source(plain_path, plain["command"], when(plain))
    v = r["verify"]
    out += (
        f"\nTest (the sensor test town), every {r['every']}nd query of each second drive "
        f"against each first drive's keyframes; the file's thresholds (fitness ≥ "
        f"{v['min_fitness']:g}, rmse ≤ {v['max_rmse_m']:g} m, descriptor gate "
        f"{v['gate_distance']}"
        + (
            f", ambiguity margin {v['ambiguity_margin']:g}"
            if v.get("ambiguity_margin") is not None
            else ""
        )
        + "); a closure is right within 1 m and 2°; precision / recall"
        + (", then the same scored over all the query's points" if plain else "")
        + (
            " (measured before the ambiguity margin)"
            if plain and plain["verify"].get("ambiguity_margin") != v.get("ambiguity_margin")
            else ""
        )
        + _margin_since(r["model"], v)
        + ":\n\n"
    )
    cells = {(p["queries_sensor"], p["map_sensor"]): p["verified"] for p in r["test"]["pairs"]}
    old = (
        {(p["queries_sensor"], p["map_sensor"]): p["verified"] for p in plain["test"]["pairs"]}
        if plain
        else {}
    )

    def cell(key: tuple[str, str]) -> str:
        x = cells[key]
        text = f"{x['precision']:.3f} / {x['recall']:.3f}"
        if key in old and key[0] != key[1]:
            text += f" ({old[key]['precision']:.3f} / {old[key]['recall']:.3f})"
        return text

    sensors = list(dict.fromkeys(q for q, _ in cells))
    grid = [[NAMES[q], *(cell((q, m)) for m in sensors)] for q in sensors]
    out += table(["queries ↓ map →", *(NAMES[m] for m in sensors)], grid)
    rows = []
    for name, x in r["test"]["summary"].items():
        rows.append(
            [
                "across sensors (20 pairs)" if name == "across" else "same sensor (5 pairs)",
                f"{x['precision']:.3f} ({x['correct']} of {x['accepted']})",
                f"{x['precision_lowest']:.3f}",
                f"{x['recall_mean']:.3f} / {x['recall_lowest']:.3f}",
            ]
        )
    head = ["pairs", "precision", "lowest pair's precision", "recall: mean / lowest pair"]
    return out + "\n" + table(head, rows)


TURN_FLOOR = "reports/model/turn-floor-any-sensor.json"


def turn_floor(path: str = TURN_FLOOR) -> str:
    """Each file's lowest cosine under random continuous turns of every real scan, over many
    draws (``benchmarks/turn_floor.py``): the lowest of all, the median draw's, and how many
    draws fell below the issue's bar."""
    r = load(path)
    out = source(path, r["command"], when(r))
    sets = list(r["models"][0]["sets"])
    out += (
        f"\nThe lowest cosine between a real scan's descriptor and its turned copy's, as the "
        f"service describes them (each file's own views, input and first stage), every scan "
        f"of each set, {r['seeds']} draws of random continuous turns: the lowest over all "
        f"draws / the median draw's lowest, and how many draws fell below the issue's bar "
        f"({r['bar']}):\n\n"
    )
    rows = []
    for m in r["models"]:
        cells = [f"`{m['model']}` (`{m['model_id']}`, {m['views']} view{'s' * (m['views'] > 1)})"]
        for name in sets:
            x = m["sets"][name]
            if "skipped" in x:
                cells.append("not measured")
                continue
            cells.append(
                f"{x['cosine_min']:.5f} / {x['cosine_min_median']:.5f}; "
                f"{x['draws_below_bar']} of {len(x['cosine_min_per_seed'])}"
            )
        rows.append(cells)
    head = ["file", *(f"{n} ({r['models'][0]['sets'][n].get('scans', '?')} scans)" for n in sets)]
    return out + table(head, rows)


RENDERERS: dict[str, Callable[[], str]] = {
    "sensors-twins": lambda: sensors_table(TWIN_RUNS),
    "sensors-any-sensor": lambda: sensors_table(OPTION_RUNS),
    "sensors-one-pass": lambda: sensors_table(ONE_PASS_RUNS),
    "real-hdl64-one-pass": lambda: real_rows(ONE_PASS_RUNS),
    "sensors-more": lambda: sensors_table(MORE_RUNS),
    "sensors-first-stage": lambda: sensors_table(FIRST_STAGE_RUNS),
    "real-first-stage": lambda: real_rows(FIRST_STAGE_RUNS),
    "real-any-sensor": lambda: real_rows(OPTION_RUNS),
    "verify-across-any-sensor": lambda: verify_across(),
    "verify-across": lambda: verify_across("reports/service/verify-across.json", None),
    "turn-floor-any-sensor": lambda: turn_floor(),
    "turn-floor-one-pass": lambda: turn_floor("reports/model/turn-floor-one-pass.json"),
}
