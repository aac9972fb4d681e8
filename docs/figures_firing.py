"""Where a scan's firings fall (``benchmarks/firing_phase.py``): each HDL-64E town rendered
with the head's firings locked to the same azimuths every turn and drifting from turn to turn,
and each model file's loop closure on both: the ``firing-phase`` block of docs/results.md;
the one-view twin's network trained on drifting firings: ``drift-pilot`` in docs/training.md."""

from __future__ import annotations

from figures_kit import load, source, table, when
from figures_phase import pilot_runs

FIRING = "reports/model/firing-phase.json"
DRIFT_RUNS = tuple(
    f"reports/model/{run}.json"
    for run in ("drift-pilot", "drift-pilot-control", "drift-pilot-s1", "drift-pilot-control-s1")
)
STAGE_LABEL = {
    "descriptor": "descriptor alone",
    "two_stages": "two stages",
    "scan_context": "",
}


def _cell(by_phase: dict, stage: str) -> str:
    a, b = (by_phase[p][stage]["all"] for p in ("locked", "drifting"))
    return f"{a['f1max']:.3f} / {a['recall@1']:.3f} → {b['f1max']:.3f} / {b['recall@1']:.3f}"


def firing_phase() -> str:
    """Per file and stage, every town's F1max / Recall@1 over all revisits, locked →
    drifting, and the test towns' mean F1max and its change."""
    r = load(FIRING)
    towns = list(r["towns"])
    out = source(FIRING, "python benchmarks/firing_phase.py", when(r))
    out += (
        "\nLoop closure over all revisits, F1max / Recall@1, the head's firings locked → "
        f"drifting (the second stage: `--rerank {r['rerank']}`). `val` is the selection "
        "town; the last column is the test towns' mean F1max, locked → drifting (change).\n\n"
    )
    rows = []
    summary = r["summary"]
    for name, by_town in r["rows"].items():
        stages = [s for s in STAGE_LABEL if s in by_town[towns[0]]["locked"]]
        for i, stage in enumerate(stages):
            s = summary[name][stage]
            change = round(s["drifting_minus_locked"], 3) or 0.0  # never "-0.000"
            mean = f"{s['locked']:.3f} → {s['drifting']:.3f} ({change:+.3f})"
            cells = [_cell(by_town[t], stage) for t in towns]
            rows.append([name if i == 0 else "", STAGE_LABEL[stage], *cells, mean])
    head = ["file", "stage", *(f"`{t}`" for t in towns), "test towns' mean F1max"]
    return out + table(head, rows)


def drift_pilot() -> str:
    """The one-view twin's network continued on train-b with drifting firings and on train-b
    as it is, both validated on val-drift: every epoch by direction, health, real turns."""
    return pilot_runs(DRIFT_RUNS, "val-drift")


RENDERERS = {"firing-phase": firing_phase, "drift-pilot": drift_pilot}
