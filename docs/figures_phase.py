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
    (
        "one view, aligned columns, spectrum in the first stage (the one-pass file)",
        "reports/model/two-stage-one-pass/report.json",
        "overlapmamba report --runs EMPTY --model models/overlapmamba-hdl64-one-pass.onnx "
        "--out reports/model/two-stage-one-pass",
    ),
    (
        "the one-pass file's first stage reduced to 256 floats (its 256-float twin)",
        "reports/model/two-stage-one-pass-256/report.json",
        "overlapmamba report --runs EMPTY --model models/overlapmamba-hdl64-one-pass-256.onnx "
        "--out reports/model/two-stage-one-pass-256",
    ),
)
REDUCE_STAGE = "reports/model/reduce-stage.json"


def reduce_stage() -> str:
    """A first stage reduced by its principal directions, on the validation town's second
    drive, which the fit did not see: as it is, projected uncentred (the export's way) and
    centred."""
    r = load(REDUCE_STAGE)
    out = source(REDUCE_STAGE, r["command"], when(r))
    out += (
        f"\n`{r['model']}` (`{r['model_id']}`), its first stage `{r['stage']}`; the "
        f"directions fitted on `{r['fit']}`, every figure on `{r['held_out']}`, which the fit "
        "did not see: F1max / Recall@1 within that drive (all revisits and the reverse ones), "
        f"the vector alone, and its AR@1 queried against `{r['fit']}`.\n\n"
    )
    rows = []
    for row in r["rows"]:
        d = row["drive"]
        how = {None: "", False: "uncentred (the export's)", True: "centred"}[row["centred"]]
        kept = f"{row['variance_kept']:.3f}" if "variance_kept" in row else ""
        rows.append(
            [
                row["vector"],
                str(row["floats"]),
                how,
                kept,
                *(f"{f3(d[s]['f1max'])} / {f3(d[s]['recall@1'])}" for s in ("all", "reverse")),
                f3(row["sessions_ar@1"]),
            ]
        )
    head = ["vector", "floats", "projected", "variance kept", "all", "reverse", "AR@1"]
    return out + table(head, rows)


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


RENDERERS: dict[str, Callable[[], str]] = {
    "column-phase": column_phase,
    "revisit-phase": revisit_phase,
    "aligned-pilot": aligned_pilot,
    "headline-one-view": headline_one_view,
    "reduce-stage": reduce_stage,
}
