"""The model's and the encoder's tables, and the service's calibrated thresholds
(``docs/figures_kit.py`` says how the tables are made)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from figures_kit import ROOT, load, ms, source, table, when

# ---- service -------------------------------------------------------------------------------
BENCH = "reports/service/bench.json"


def service() -> str:
    """The serving benchmark's own summary: each goal, what this run measured, met or not."""
    r = load(BENCH)
    rows = [[s["goal"], s["measured"], s["status"]] for s in r["summary"]]
    parts = "; ".join(f"{k}: {v}" for k, v in r.get("parts_measured", {}).items())
    out = source(BENCH, "make bench (python benchmarks/serving.py)")
    out += "\n" + table(["goal", "measured", "status"], rows)
    if parts:
        out += f"\nParts: {parts}.\n"
    return out


# ---- encoder -------------------------------------------------------------------------------
ENCODER = "reports/service/encoder-narrow.json"
VARIANTS = {
    "c-kernel (served)": "C-kernel path (served where it is the faster), one pass",
    "scan-loop": "portable graph (ONNX `Scan` loops)",
    "no-scan": "the same graph with the scan removed (yardstick)",
    "torch eager": "PyTorch, eager",
}


def encoder() -> str:
    """One encoder pass per variant at B = 1 and 8, and the peer comparison as the product
    runs (the shipped model with its views) beside one pass, interleaved."""
    r = load(ENCODER)
    rows = []
    for key, label in VARIANTS.items():
        v = r["variants"].get(key)
        if v is None:
            continue
        rows.append(
            [
                label,
                ms(v["b1_t1"]["median_ms"]),
                ms(v["b1_t2"]["median_ms"]),
                ms(v["b8_t2_per_scan_ms"]),
            ]
        )
    out = source(ENCODER, "python benchmarks/encoder.py --narrow", when(r))
    out += f"\nMachine: {r['machine'].get('cpu', '?')}, {r['machine']['cores']} cores; "
    out += f"{r['inputs']}; medians.\n\n"
    out += table(
        ["encoder", "B = 1, 1 thread", "B = 1, 2 threads", "B = 8, per scan, 2 threads"], rows
    )
    p = r.get("peer")
    if p:
        out += (
            f"\nAgainst the OverlapTransformer-style peer ({p['peer_params'] / 1e6:.1f} M "
            f"parameters; ours {p['ours_params'] / 1e6:.1f} M), interleaved, 2 threads, "
            "ms a scan:\n\n"
        )
        prow = []
        for b in ("b1", "b8"):
            x = p[b]
            prow.append(
                [
                    f"B = {b[1:]}",
                    ms(x["ours_views_ms_per_scan"]),
                    ms(x["ours_ms_per_scan"]),
                    ms(x["peer_ms_per_scan"]),
                    f"{x['ours_views_over_peer']:.2f}×",
                    f"{x['ours_over_peer']:.2f}×",
                ]
            )
        out += table(
            [
                "batch",
                f"ours as shipped ({p['views']} views)",
                "ours, one pass",
                "peer",
                "shipped ÷ peer",
                "one pass ÷ peer",
            ],
            prow,
        )
    return out


VIEWS = "reports/service/views.json"


def views() -> str:
    """The shipped model's sub-column views against one view, interleaved."""
    r = load(VIEWS)
    rows = [
        [
            x["threads"],
            f"encode, {x['scans_per_call']} a call" if "scans_per_call" in x else x["stage"],
            ms(x["one view"]["median_ms"]),
            ms(x["shipped"]["median_ms"]),
            f"{x['shipped']['median_ms'] / x['one view']['median_ms']:.2f}×",
        ]
        for x in r["rows"]
    ]
    out = source(VIEWS, "python benchmarks/views.py", when(r))
    out += f"\n{r['scans']}, {r['reps']} repetitions, medians a scan.\n\n"
    return out + table(
        ["threads", "what", "one view", f"shipped ({r['views']} views)", "ratio"], rows
    )


LOOP_THRESHOLD = "reports/service/loop_threshold.json"
VERIFY_THRESHOLD = "reports/service/verify_threshold.json"


def calibration() -> str:
    """The service's thresholds as the benchmarks chose them on ``val`` for the shipped model,
    with precision and recall there (old files name them max_distance; the service's names
    are the new ones)."""
    lt, vt = load(LOOP_THRESHOLD), load(VERIFY_THRESHOLD)
    op, opr = lt["operating_points"]["f1max"], lt["operating_points_reranked"]["f1max"]
    dist = op.get("accept_distance", op.get("max_distance"))
    c, g = vt["calibration"]["chosen"], vt["calibration"]["gate"]
    gate = g.get("gate_distance", g.get("max_distance"))
    rows = [
        [
            "verified answers",
            "`verify.min_fitness`, `verify.max_rmse_m`",
            f"{c['min_fitness']}, {c['max_rmse_m']}",
            f"{c['precision']:.3f} ({c['correct']} of {c['accepted']} poses right)",
            f"{c['recall']:.3f}",
        ],
        [
            "… with the descriptor gate",
            "`verify.gate_distance`",
            f"{gate}",
            f"{g['precision']:.3f}",
            f"{g['recall']:.3f} ({g['registered_per_query']:.1f} registered a query)",
        ],
        [
            "unverified, re-ranked (F1max)",
            "`loop_closure.max_score`",
            f"{opr['max_score']:.4f}",
            f"{opr['precision']:.3f}",
            f"{opr['recall']:.3f}",
        ],
        [
            "unverified, descriptor order (F1max)",
            "`loop_closure.accept_distance`",
            f"{dist:.4f}",
            f"{op['precision']:.3f}",
            f"{op['recall']:.3f}",
        ],
    ]
    out = source(VERIFY_THRESHOLD, vt["command"], when(vt))
    out += source(LOOP_THRESHOLD, lt["command"], when(lt))
    out += f"\nModel {lt['model_id']}, on `{Path(lt['sequence']).name}`:\n\n"
    out += table(["answer", "setting", "value", "precision on val", "recall on val"], rows)
    pts = lt["operating_points"]
    stricter = [
        f"precision ≥ {name.split('>=')[1]} at "
        f"{p.get('accept_distance', p.get('max_distance')):.3f} (recall {p['recall']:.2f})"
        for name, p in pts.items()
        if name.startswith("precision") and p is not None
    ]
    if stricter:
        out += "\nStricter descriptor-order points: " + "; ".join(stricter) + ".\n"
    return out


MODEL_TABLES = "reports/model/tables.md"


def model_tables() -> str:
    """The model report's own Markdown (``overlapmamba report`` writes it beside
    report.json), under the command that wrote it."""
    text = (ROOT / MODEL_TABLES).read_text()
    return source(MODEL_TABLES, "overlapmamba report") + "\n" + text


RENDERERS: dict[str, Callable[[], str]] = {
    "model-tables": model_tables,
    "calibration": calibration,
    "service": service,
    "encoder": encoder,
    "views": views,
}
