"""Where a one-view scan's columns start (aligned columns, ``overlapmamba.core.views``): the
choice of direction on ``val``, how far apart the synthetic revisits' column grids are, and
the one-view twin's network trained on aligned images against the same training in the
sensor's columns."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from figures_kit import f3, load, source, table, when

COLUMN_PHASE = "reports/model/column-phase-val.json"


def column_phase() -> str:
    """Where a one-view scan's columns start, scored on val and its second session: the
    sensor's azimuth and the bearings' moments, each stage, and the pick."""
    r = load(COLUMN_PHASE)
    subsets = ("all", "same", "reverse")
    rows = []
    for x in r["rows"]:
        for stage, label in (("descriptor", "descriptor alone"), ("two_stages", "two stages")):
            v = x[stage]
            rows.append(
                [
                    x["columns"],
                    label,
                    *(f"{v[f'{s}_f1max']:.3f} / {v[f'{s}_recall@1']:.3f}" for s in subsets),
                    f"{v['cross_session_ar@1']:.3f}",
                    f"{v['mean']:.4f}",
                ]
            )
    out = source(COLUMN_PHASE, r["command"], when(r))
    out += (
        f"\n`{Path(r['val']).name}` (loop closure, F1max / Recall@1) and "
        f"`{Path(r['second_session']).name}` against it (AR@1 across sessions); second stage "
        f"{r['rerank']}; the aligned pick by the mean of both stages' means: "
        f"**{r['best_aligned']}**.\n\n"
    )
    head = ["columns", "stage", "all", "same direction", "reverse", "AR@1 across", "mean"]
    return out + table(head, rows)


REVISIT_PHASE = "reports/synthetic/revisit-phase.json"


def revisit_phase() -> str:
    """Each town's revisits: heading off 0°/180° and the remainder in columns."""
    r = load(REVISIT_PHASE)
    u = r["uniform"]
    out = source(REVISIT_PHASE, r["command"], when(r))
    out += (
        f"\nEach scan with an earlier one within {r['radius_m']:g} m (outside the "
        f"{r['exclude_frames']}-frame exclusion) and its nearest such scan: how far their "
        f"headings are from 0° or 180°, and the remainder of their difference in columns "
        f"({r['width']} a turn), folded to [0, ½]. A uniform remainder has median "
        f"{u['column_remainder_median']:g} and puts {u['within_tenth_of_a_column']:g} of the "
        "pairs within a tenth of a column.\n\n"
    )
    rows = [
        [
            f"`{name}`",
            str(x["revisits"]),
            f"{x['reverse_share']:.2f}",
            f"{x['heading_off_median_deg']:.2f}°",
            f3(x["column_remainder_median"]),
            f3(x["within_tenth_of_a_column"]),
        ]
        for name, x in r["towns"].items()
    ]
    head = ["town", "revisits", "reverse share", "heading off 0°/180°, median"]
    head += ["remainder, median (columns)", "within 0.1 column"]
    return out + table(head, rows)


ALIGNED_RUNS = (
    "reports/model/aligned-pilot.json",
    "reports/model/aligned-pilot-control.json",
)


def aligned_pilot() -> str:
    """The one-view twin's network trained on aligned images and the same training in the
    sensor's columns: every epoch's validation by direction, health and real turns."""
    return pilot_runs(ALIGNED_RUNS, "val")


def pilot_runs(paths: tuple[str, ...], val: str) -> str:
    """Continuations of the one-view twin's network side by side (``run_summary.py``
    reports): every epoch's validation on ``val`` by direction, health and real turns."""
    runs = [load(p) for p in paths]
    out = "".join(source(p, r["command"], when(r)) for p, r in zip(paths, runs, strict=True))
    out += (
        "\nEpoch 0 is the start (the shipped weights) in the run's columns. Loop closure of "
        f"`{val}`, the descriptor alone (F1max / Recall@1); the spread from the health "
        "numbers; the minimum cosine of real KITTI scans under a continuous turn, in the "
        "run's columns.\n\n"
    )
    for r in runs:
        phase = r["model_config"].get("column_phase", "sensor")
        out += (
            f"- `{r['run']}` (columns: {phase}, seed {r['train_config']['seed']}): "
            f"{r['epochs_run']} of {r['epochs_planned']} planned epochs ran; it keeps epoch "
            f"{r['best']['epoch']}\n"
        )
    rows = []
    for r in runs:
        for e in r["epochs"]:
            v, spread, real = e["val"], e["health"]["spread"], e["real_cosine_min"]
            rows.append(
                [
                    f"`{r['run'].split('/')[-1]}`",
                    str(e["epoch"]),
                    *(f"{f3(v[s]['f1max'])} / {f3(v[s]['recall@1'])}" for s in SUBSETS),
                    "—" if spread is None else f"{spread:.3f}",
                    "—" if real is None else f"{real:.5f}",
                ]
            )
    head = ["run", "epoch", "all", "same direction", "reverse", "spread", "real min cosine"]
    return out + "\n" + table(head, rows)


SUBSETS = ("all", "same", "reverse")

# (file, report, the command that wrote it: report.json records none)
HEADLINES = (
    (
        "three views (the default file)",
        "reports/model/two-stage/report.json",
        "overlapmamba report --runs EMPTY --out reports/model/two-stage",
    ),
    (
        "one view, aligned columns (the twin)",
        "reports/model/two-stage-one-view/report.json",
        "overlapmamba report --runs EMPTY --model models/overlapmamba-hdl64-one-view.onnx "
        "--out reports/model/two-stage-one-view",
    ),
)
SHIPPED_ROW = "OverlapMamba narrow, mined hard negatives (shipped)"


def headline_one_view() -> str:
    """The README's headline for the default file and for its one-view twin, by the same
    command: the test towns (mean), across sessions, real KITTI 00 retrieval and turns."""
    reports = [(name, load(path)) for name, path, _ in HEADLINES]
    out = "".join(source(path, command) for _, path, command in HEADLINES)
    rows = []
    for name, r in reports:
        t1, xs, real = r["table1"], r["cross_session"], r["real"]["kitti00"]
        got = real["retrieval_odd_to_even"]
        for stage, key, kitti in (
            ("descriptor alone", SHIPPED_ROW, got["recall@1"]),
            ("two stages", SHIPPED_ROW + " + yaw re-rank", got["reranked"]["recall@1"]),
        ):
            m = t1[key]
            rows.append(
                [
                    name,
                    stage,
                    *(f"{f3(m[s]['f1max'])} / {f3(m[s]['recall@1'])}" for s in SUBSETS),
                    f3(xs[key]["ar@1"]),
                    f3(kitti),
                    f"{real['yaw_invariance']['cosine_min']:.5f}",
                ]
            )
    sc = reports[0][1]["table1"]["Scan Context"]
    sc_x = reports[0][1]["cross_session"]["Scan Context"]
    sc_real = reports[0][1]["real"]["kitti00"]["retrieval_odd_to_even"]["scan_context"]
    rows.insert(
        0,
        [
            "Scan Context",
            "",
            *(f"{f3(sc[s]['f1max'])} / {f3(sc[s]['recall@1'])}" for s in SUBSETS),
            f3(sc_x["ar@1"]),
            f3(sc_real["recall@1"]),
            "—",
        ],
    )
    out += (
        "\nThe test towns' mean (F1max / Recall@1), the second drive through `test` against "
        "the first (AR@1), real KITTI 00 odd frames, turned, against the even ones "
        "(Recall@1) and the minimum cosine of a real KITTI scan to its turned copies.\n\n"
    )
    head = ["file", "stage", "all", "same direction", "reverse", "across sessions AR@1"]
    head += ["real KITTI 00 Recall@1", "real turn min cosine"]
    return out + table(head, rows)


# the sensors baseline (benchmarks/sensors.py) of the default file and of its twins
SENSOR_RUNS = (
    ("three views (the default file)", "reports/model/sensors.json"),
    ("one view, aligned columns", "reports/model/sensors-one-view.json"),
    ("three views met at the tokens", "reports/model/sensors-tokens.json"),
)


def _fr(m: dict) -> str:
    return f"{m['f1max']:.3f} / {m['recall@1']:.3f}"


def sensors_twins() -> str:
    """The sensors baseline for the default file and for its twins on the same drives, town
    by town and pair by pair, a row per file."""
    runs = [(label, path, load(path)) for label, path in SENSOR_RUNS]
    out = "".join(
        source(path, r.get("command", "python benchmarks/sensors.py"), when(r))
        for _, path, r in runs
    )
    towns = [{Path(x["town"]).name: x for x in r["same_sensor"]} for _, _, r in runs]
    common = [t for t in towns[0] if all(t in other for other in towns[1:])]
    same = all(tw[t]["scan_context"] == towns[0][t]["scan_context"] for tw in towns for t in common)
    out += (
        "\nSame sensor, F1max / Recall@1 (all revisits); verified precision / recall at each "
        "file's own thresholds. Scan Context "
        + (
            "scored the same in every run on every town: the same drives."
            if same
            else "scored differently between the runs: not the same drives."
        )
        + "\n\n"
    )
    rows = []
    for t in common:
        for k, (label, _, _) in enumerate(runs):
            x = towns[k][t]
            v = x["verified"]
            rows.append(
                [
                    f"{x['sensor']} ({x['mount']})" if k == 0 else "",
                    label,
                    _fr(x["descriptor"]),
                    _fr(x["two_stage"]),
                    _fr(x["scan_context"]) if k == 0 else "",
                    f"{v['precision']:.3f} / {v['recall']:.3f}",
                ]
            )
    head = ["sensor (mounting)", "file", "descriptor alone", "two stages (service)"]
    out += table([*head, "Scan Context", "verified precision / recall"], rows)
    out += "\nAcross sensors, AR@1 (a hit within 5 m):\n\n"
    pairs = [
        {(p["query_sensor"], p["map_sensor"]): p for p in r["across_sensors"]} for *_, r in runs
    ]
    rows = []
    for key in pairs[0]:
        if not all(key in other for other in pairs[1:]):
            continue
        for k, (label, _, _) in enumerate(runs):
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


RENDERERS: dict[str, Callable[[], str]] = {
    "column-phase": column_phase,
    "revisit-phase": revisit_phase,
    "aligned-pilot": aligned_pilot,
    "sensors-twins": sensors_twins,
    "headline-one-view": headline_one_view,
}
