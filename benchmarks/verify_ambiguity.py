"""How ambiguous a verified closure's registration is: the same pair registered from the other
quarter turns.

A verified closure is a registration whose fitness clears ``verify.min_fitness``. Where a place
looks like another one turned by a quarter (a crossing of a grid town, seen by a sensor whose
range ends at the crossing), a registration can fit the wrong place about as well as a right
closure fits the right one, and fitness alone cannot tell them apart. This measures, for each
closure the service would accept at a file's own thresholds without the margin
(``verify_threshold.run_town`` and ``closure_kit.closure``: the service's order and call), the
best fitness of the same pair registered again from the seed yaw + 90°, 180° and 270° whose
pose turns more than ``TURN_APART_DEG`` from the accepted one (the service's
``overlapmamba.service.verify.rival_fitness``), and the margin between the two, for right
closures (pose within 1 m and 2°) and wrong ones. The service refuses a closure whose margin
is below ``verify.ambiguity_margin``; its cost in right closures is the table's ``kept`` column.

It also checks the screen the service's check relies on (:func:`screen`): each turn of
every candidate that passes the served fitness is registered in full, and counted when it
ends with a fitness above the share of its points that were within GICP's reach at its
seed pose (the service does not register a turn whose share is below the fit that would
refuse); and how many turns the screen registers at the file's margin.

Nothing is chosen here: ``verify_threshold.py --calibrate`` chooses the margin on validation
towns; the test towns are reported beside them to show the failure it addresses.

    python benchmarks/verify_ambiguity.py --model models/overlapmamba-hdl64-one-pass.onnx \\
        --town data/synth/val --town data/synth/val-os0-128 --town data/synth/val-vlp16 \\
        --town data/synth/val-xt32 --town data/synth/test-os0-128 \\
        --out reports/service/verify-ambiguity-one-pass.json

≈ 3 min a 2,000-scan town on 2 cores (three more registrations for each candidate that passes
the fitness threshold).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np
from bench_kit import ROOT, model_record, served_rerank, served_settings
from closure_kit import closure
from reports_kit import REPORTS, write_report
from rich.console import Console
from rich.table import Table
from verify_threshold import run_town

from overlapmamba.core.poses import POSE_RIGHT
from overlapmamba.service.encoder import Encoder
from overlapmamba.service.verify import QUARTER_TURNS, TURN_APART_DEG

MARGINS = (0.02, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4)


def summary(rows: list[tuple[bool, float, float]]) -> dict[str, Any]:
    """(right, fitness, best alternative fitness) of each accepted closure → counts, margin
    percentiles of right and wrong closures, and what each margin of ``MARGINS`` keeps."""
    a = np.array(rows, dtype=np.float64).reshape(-1, 3)
    right = a[:, 0] == 1
    margin = a[:, 1] - a[:, 2]

    def spread(m: np.ndarray) -> dict[str, float] | None:
        if not len(m):
            return None
        return {f"p{q}": float(np.percentile(m, q)) for q in (1, 5, 50)} | {"max": float(m.max())}

    return {
        "accepted": len(a),
        "wrong": int((~right).sum()),
        "margin_right": spread(margin[right]),
        "margin_wrong": spread(margin[~right]),
        "fitness_right_median": float(np.median(a[right, 1])) if right.any() else None,
        "fitness_wrong_median": float(np.median(a[~right, 1])) if (~right).any() else None,
        "kept": [
            {
                "margin": t,
                "right": int((right & (margin >= t)).sum()),
                "wrong": int((~right & (margin >= t)).sum()),
            }
            for t in MARGINS
        ],
    }


def alternatives(r: dict[str, Any], v: Any) -> list[tuple[bool, float, float]]:
    """Each closure of one town that the served thresholds accept without the margin
    (``run_town(..., rivals_from=v.min_fitness)``): whether it is right, its fitness, and the
    best fitness of the other turns."""
    out = []
    for q in r["queries"]:
        best, _ = closure(q, v.min_fitness, v.max_rmse_m, v.gate_distance, v.stop_at_first)
        if best is None:
            continue
        right = best["t_err"] <= POSE_RIGHT[0] and best["yaw_err"] <= POSE_RIGHT[1]
        out.append((bool(right), float(best["fitness"]), float(best["rival"])))
    return out


def screen(r: dict[str, Any], margin: float | None) -> dict[str, Any]:
    """How the service's screen (``overlapmamba.service.verify.rival_fitness``) fares on one
    town's turned registrations: every candidate that passed the served fitness carries each
    turn registered in full, with the share of its points within GICP's reach at the seed
    (``turns``: reach, fitness, whether it counts as a rival). ``above_reach``: turns that
    ended with a fitness above that share (what the screen assumes does not happen);
    ``registered``: turns the screen registers at ``margin`` (a seed within reach of the fit
    that would refuse); ``changed``: candidates whose check the screen decides otherwise
    than registering every turn would (a turn left out that would have refused)."""
    turns, changed, checked = [], 0, 0
    for q in r["queries"]:
        for c in q["candidates"]:
            if "turns" not in c:
                continue
            checked += 1
            turns += [(c["fitness"], reach, fit) for reach, fit, _ in c["turns"]]
            if margin is not None:
                need = c["fitness"] - margin
                counted = [(reach, fit) for reach, fit, counts in c["turns"] if counts]
                every = any(fit >= need for _, fit in counted)
                screened = any(min(fit, reach) >= need for reach, fit in counted)
                changed += every != screened
    a = np.array(turns, dtype=np.float64).reshape(-1, 3)
    excess = a[:, 2] - a[:, 1]
    return {
        "turns": len(a),
        "above_reach": int((excess > 0).sum()),
        "largest_excess": float(excess.max()) if len(a) else None,
        "registered": None if margin is None else int((a[:, 1] >= a[:, 0] - margin).sum()),
        "checked": checked,
        "changed": None if margin is None else changed,
        "margin": margin,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, default=ROOT / "models" / "overlapmamba-hdl64.onnx")
    ap.add_argument("--town", type=Path, action="append", required=True)
    ap.add_argument("--out", type=Path, default=REPORTS / "service" / "verify-ambiguity.json")
    args = ap.parse_args()
    enc = Encoder(args.model)
    served = served_settings(enc.meta)
    v, rerank = served.verify, served_rerank(enc.meta)
    record = v.model_copy(update={"min_fitness": 0.0, "max_rmse_m": 1e9})  # every verdict kept
    towns = {}
    for town in args.town:
        r = run_town(enc, town, v.candidates, record, rerank, rivals_from=v.min_fitness)
        towns[town.name] = summary(alternatives(r, v)) | {"screen": screen(r, v.ambiguity_margin)}
    report = {
        **model_record(args.model, enc),
        "verify": v.model_dump(),
        "turns_deg": list(QUARTER_TURNS),
        "turn_apart_deg": TURN_APART_DEG,
        "towns": towns,
    }
    write_report(args.out, report)
    table = Table(title=f"ambiguity of accepted closures ({enc.model_id})")
    cols = ("town", "accepted", "wrong", "margin right p1 / p5", "margin wrong p50")
    for col in (*cols, "turns above reach", "turns the screen registers", "checks changed"):
        table.add_column(col, justify="right")
    for t in MARGINS:
        table.add_column(f"≥ {t:g} keeps right / wrong", justify="right")
    for name, s in towns.items():
        mr, mw = s["margin_right"] or {}, s["margin_wrong"] or {}
        table.add_row(
            name,
            str(s["accepted"]),
            str(s["wrong"]),
            f"{mr.get('p1', float('nan')):.3f} / {mr.get('p5', float('nan')):.3f}",
            f"{mw['p50']:.3f}" if mw else "—",
            f"{s['screen']['above_reach']} of {s['screen']['turns']}",
            f"{s['screen']['registered']} of {s['screen']['turns']}",
            f"{s['screen']['changed']} of {s['screen']['checked']}",
            *(f"{k['right']} / {k['wrong']}" for k in s["kept"]),
        )
    Console(width=200).print(table)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
