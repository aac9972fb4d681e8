"""Choose the second stage's shortlist size and weight on the validation town (never on test).

The service re-ranks the K nearest descriptors of a scan query by d² − WEIGHT · aligned
yaw-feature correlation (``overlapmamba.core.rerank``). This grid scores every (K, WEIGHT) with the
shipped encoder on ``data/synth/val`` (loop closure: F1max and Recall@1, all / same / reverse
direction) and ``data/synth/val-s1`` queried against ``val`` (AR@1 across sessions), and
ranks them by the mean of those seven numbers. ``overlapmamba.core.rerank.Rerank``'s defaults (the
service's ``rerank`` settings and ``overlapmamba eval --rerank``) are the winner for the
shipped model; ``--write-calibration`` records the winner in the model file, which the
service takes it from. ``--score network`` measures d² between the network's own descriptors
inside a mixed first stage instead of between the vectors the shortlist is ranked by
(``overlapmamba.core.yaw_spectrum.score_part``); the calibration records the score it was
chosen with (``rerank.score``).

    python benchmarks/rerank.py [--model models/overlapmamba-hdl64.onnx]

Writes JSON (default reports/model/rerank.json). ≈ 2 min on 2 cores once the range images
are cached (``make data`` makes val; ``overlapmamba gen-data data/synth/val-s1 --preset
val-s1`` the second session).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from bench_kit import ROOT, provenance, write_calibration
from reports_kit import REPORTS
from rich.console import Console
from rich.table import Table

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.rerank import OFF, Rerank, with_score
from overlapmamba.core.yaw_spectrum import SCORES
from overlapmamba.train.checkpoint import load_model
from overlapmamba.train.evaluate import SUBSETS, describe_sequence, loop_closure, sequence_loops
from overlapmamba.train.modelfile import read_metadata
from overlapmamba.train.sessions import check_sessions, descriptor_recall, town_positions

KS = (5, 10, 20)
WEIGHTS = (0.02, 0.05, 0.1, 0.2, 0.5)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", type=Path, default=ROOT / "models" / "overlapmamba-hdl64.onnx")
    ap.add_argument("--val", type=Path, default=ROOT / "data" / "synth" / "val")
    ap.add_argument("--second-session", type=Path, default=ROOT / "data" / "synth" / "val-s1")
    ap.add_argument("--out", type=Path, default=REPORTS / "model" / "rerank.json")
    ap.add_argument(
        "--write-calibration",
        action="store_true",
        help="record the winner as the model's rerank.shortlist / rerank.weight",
    )
    ap.add_argument(
        "--score",
        choices=SCORES,
        default="stage",
        help="the score's d²: between the vectors the shortlist is ranked by (stage), or "
        "between the network's own descriptors inside a mixed first stage (network); "
        "--write-calibration records it as rerank.score",
    )
    args = ap.parse_args()
    if args.write_calibration and args.val.name.startswith("test"):
        ap.error("calibrate on the validation town, never on a test town")

    t0 = time.perf_counter()
    val, second = open_sequence(args.val), open_sequence(args.second_session)
    mapped = sorted({val.sensor, second.sensor} & set(read_metadata(args.model).sensor_maps))
    if mapped:  # one second stage serves every sensor: chosen on the model's own, unmapped
        ap.error(
            f"{args.model} carries a sensor map for {mapped[0]}, the towns' sensor; the file's "
            "second stage is chosen on the model's own sensor, whose descriptors no map "
            "moves: choose on a town of the model's own sensor"
        )
    check_sessions(val, second)
    model, profile, _ = load_model(args.model)
    part = None
    if args.score == "network":
        meta = read_metadata(args.model)
        try:
            part = with_score(Rerank(), args.score, meta).part
        except ValueError as e:
            ap.error(f"{args.model}: {e}")
        if part is None:
            ap.error(
                f"{args.model}'s first stage {meta.first_stage!r} is the network's descriptor: "
                "scoring by it is --score stage"
            )
    gt = sequence_loops(val, profile)
    desc, yaw = describe_sequence(model, val, profile)
    desc_q, yaw_q = describe_sequence(model, second, profile)
    pos, pos_q = town_positions(val), town_positions(second)

    rows = []
    for p in [OFF] + [Rerank(k, w, part) for k in KS for w in WEIGHTS]:
        res = loop_closure(desc, gt, yaw, p)
        xs = descriptor_recall(desc, pos, desc_q, pos_q, yaw=(yaw, yaw_q), rerank=p)
        row: dict = {"shortlist": p.shortlist, "weight": p.weight}
        for sub in SUBSETS:
            row[f"{sub}_f1max"] = res[sub].f1max
            row[f"{sub}_recall@1"] = res[sub].recall_at_1
        row["cross_session_ar@1"] = xs["ar@1"]
        scores = [v for key, v in row.items() if key not in ("shortlist", "weight")]
        row["mean"] = float(np.mean(scores))
        rows.append(row)
    best = max(rows[1:], key=lambda r: r["mean"])

    table = Table(title=f"second stage on {val.name} and {second.name} ({args.model.name})")
    cols = ["K", "weight", *(f"{s} F1 / R@1" for s in SUBSETS), "AR@1 across", "mean"]
    for col in cols:
        table.add_column(col, justify="right")
    for r in rows:
        mark = " ←" if r is best else ""
        table.add_row(
            "off" if r["shortlist"] == 1 else str(r["shortlist"]),
            f"{r['weight']:g}",
            *(f"{r[f'{s}_f1max']:.3f} / {r[f'{s}_recall@1']:.3f}" for s in SUBSETS),
            f"{r['cross_session_ar@1']:.3f}",
            f"{r['mean']:.4f}{mark}",
        )
    console = Console(width=140)
    console.print(table)
    console.print(
        f"best: K {best['shortlist']}, weight {best['weight']:g}; {time.perf_counter() - t0:.0f} s"
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    record = {
        **provenance(),
        "model": str(args.model),
        "val": str(args.val),
        "second_session": str(args.second_session),
        "score": args.score,
        "grid": rows,
        "best": {"shortlist": best["shortlist"], "weight": best["weight"]},
    }
    args.out.write_text(json.dumps(record, indent=2) + "\n")
    console.print(f"wrote {args.out}")
    if args.write_calibration:
        values = {"shortlist": best["shortlist"], "weight": best["weight"], "score": args.score}
        write_calibration(args.model, "rerank", values, f"{args.val} and {args.second_session}")


if __name__ == "__main__":
    main()
