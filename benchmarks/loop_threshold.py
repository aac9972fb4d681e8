"""Calibrate the service's loop-closure threshold on the validation town (never on test).

Runs the shipped ONNX encoder exactly as the service does (``overlapmamba.service.encoder.Encoder``:
the model's own projection, onnxruntime), scores the loop-closure protocol of
``overlapmamba.core.metrics`` on ``data/synth/val`` and prints the operating points: the top-1
descriptor distance at F1max, and the largest distance whose precision is at least 0.9,
0.95 and 0.99 (a false loop closure corrupts a SLAM map, so robots want high precision).
The service's ``loop_closure.accept_distance`` default is chosen from this table.

The service answers scan queries in two stages (``overlapmamba.core.rerank``: the
``rerank.shortlist`` nearest descriptors re-ranked by d² − weight · aligned yaw-feature
correlation) and calls an unverified loop closure on the top-1's *score*; the same table for
that score (the keyframes' yaw features rounded to float16, as the map stores them) gives
``loop_closure.max_score``.
``--write-calibration`` records both F1max points in the model file, which the service takes
them from. Each scan enters the model as its town's sensor's (its manifest's). Several
``--sequence`` (a model for several sensors: each one's validation town) are scored as one
PR curve, each query searching its own town's past (``overlapmamba.core.metrics.pooled``):
one threshold judged on all of them, as the service applies one to every sensor's scans.
Writes JSON (default reports/service/loop_threshold.json).
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import numpy as np
from bench_kit import (
    ROOT,
    model_record,
    provenance,
    served_input,
    served_rerank,
    served_settings,
    write_calibration,
)
from reports_kit import REPORTS
from rich.console import Console
from rich.table import Table
from tqdm import tqdm

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.metrics import (
    LoopClosureResult,
    evaluate_loop_closure,
    evaluate_retrieval,
    pooled,
)
from overlapmamba.core.overlap import LoopGroundTruth
from overlapmamba.core.rerank import Rerank, two_stage
from overlapmamba.service.encoder import Encoder


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", type=Path, default=ROOT / "models" / "overlapmamba-hdl64.onnx")
    pre, _ = ap.parse_known_args()
    enc = Encoder(pre.model)
    served = served_settings(enc.meta).rerank  # the model file's calibration, else defaults
    ap.add_argument(
        "--sequence",
        type=Path,
        action="append",
        help="a validation town (default data/synth/val); several are scored as one curve, one "
        "threshold for all (a model for several sensors: each town's own)",
    )
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument(
        "--rerank",
        default=f"{served.shortlist},{served.weight:g}",
        help="the second stage, K,WEIGHT or off (default: the service's for --model)",
    )
    ap.add_argument("--out", type=Path, default=REPORTS / "service" / "loop_threshold.json")
    ap.add_argument(
        "--write-calibration",
        action="store_true",
        help="record the F1max points as the model's loop_closure.accept_distance / max_score",
    )
    args = ap.parse_args()
    args.sequence = args.sequence or [ROOT / "data" / "synth" / "val"]
    if args.write_calibration and any(p.name.startswith("test") for p in args.sequence):
        ap.error("calibrate on the validation town, never on a test town")

    rerank = served_rerank(enc.meta, args.rerank)  # its score as the service scores
    t0 = time.perf_counter()
    towns = [score_town(enc, path, args.batch, rerank) for path in args.sequence]
    res = pooled([t[0] for t in towns])
    res16 = pooled([t[1] for t in towns])
    staged = pooled([t[2] for t in towns])
    desc = np.concatenate([t[3] for t in towns])
    spread = np.linalg.norm(desc - desc.mean(0), axis=1)
    names = ", ".join(p.name for p in args.sequence)
    # The protocol's PR thresholds are squared L2 distances (overlapmamba.core.metrics.nearest);
    # the service compares L2 distances: accept_distance = √threshold. A score is thresholded
    # as it is (max_score).
    points = operating_points(res, "accept_distance", np.sqrt)
    points_staged = operating_points(staged, "max_score", lambda t: t)
    table = Table(title=f"loop-closure operating points on {names} ({enc.model_id})")
    for col in ("point", "max L2 distance", "precision", "recall"):
        table.add_column(col, justify="right")
    for col in (f"max score ({rerank.shortlist}, {rerank.weight:g})", "precision", "recall"):
        table.add_column(col, justify="right")
    for name, v in points.items():
        w = points_staged[name]
        cells = []
        for x, key in ((v, "accept_distance"), (w, "max_score")):
            cells += (
                ["not reached", "", ""]
                if x is None
                else [f"{x[key]:.4f}", f"{x['precision']:.3f}", f"{x['recall']:.3f}"]
            )
        table.add_row(name, *cells)
    console = Console(width=120)
    console.print(table)
    console.print(
        f"F1max {res.f1max:.3f}, Recall@1 {res.recall_at_1:.3f}, {res.n_queries} queries, "
        f"{res.n_with_loop} with a loop; two stages: F1max {staged.f1max:.3f}, Recall@1 "
        f"{staged.recall_at_1:.3f}; {time.perf_counter() - t0:.0f} s"
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(
        json.dumps(
            {
                **provenance(),
                **model_record(args.model, enc),
                "sequence": ", ".join(map(str, args.sequence)),
                "towns": [
                    {"sequence": str(p), "summary": t[0].summary(), "reranked": t[2].summary()}
                    for p, t in zip(args.sequence, towns, strict=True)
                ],
                "summary": res.summary(),
                "operating_points": points,
                "rerank": asdict(rerank),
                "summary_reranked": staged.summary(),
                "operating_points_reranked": points_staged,
                "float16": res16.summary(),
                "distance_to_mean": {
                    "median": float(np.median(spread)),
                    "p99": float(np.percentile(spread, 99)),
                },
            },
            indent=2,
        )
        + "\n"
    )
    console.print(
        f"float16-rounded descriptors: F1max {res16.f1max:.3f}, Recall@1 "
        f"{res16.recall_at_1:.3f}; distance to the mean descriptor: median "
        f"{np.median(spread):.4f}, p99 {np.percentile(spread, 99):.4f}"
    )
    console.print(f"wrote {args.out}")
    if args.write_calibration:
        f1, f1_staged = points["f1max"], points_staged["f1max"]
        assert f1 is not None and f1_staged is not None  # the F1max point always exists
        values = {"accept_distance": f1["accept_distance"], "max_score": f1_staged["max_score"]}
        write_calibration(args.model, "loop_closure", values, ", ".join(map(str, args.sequence)))


def score_town(
    enc: Encoder, path: Path, batch: int, rerank: Rerank
) -> tuple[LoopClosureResult, LoopClosureResult, LoopClosureResult, np.ndarray]:
    """One town as the service sees it (its scans as its sensor's): the descriptor's result,
    the float16-rounded descriptor's, the two stages' (the yaw features in float16, as a map
    stores them), and the descriptors."""
    seq = open_sequence(path)
    sensor = served_input(enc, seq.sensor)
    gt = LoopGroundTruth.load(path / "ground_truth" / "loops.npz")
    descs, yaws = [], []
    for start in tqdm(range(0, len(seq), batch), desc=f"encode {seq.name}", unit="batch"):
        pts = [seq.points(i) for i in range(start, min(len(seq), start + batch))]
        d, y = enc.describe(pts, sensor, batch=len(pts))  # mapped, as the service answers
        descs.append(d)
        yaws.append(y)
    desc = np.concatenate(descs)
    yaw16 = np.concatenate(yaws).astype(np.float16)  # what a map stores
    recent = int(gt.params.get("exclude_recent", 100))
    # What a float16 store would hold: does the rounding cost accuracy?
    d16 = desc.astype(np.float16).astype(np.float32)
    d16 /= np.linalg.norm(d16, axis=1, keepdims=True)
    res16 = evaluate_loop_closure(d16, gt.positives(), exclude_recent_frames=recent)
    res = evaluate_loop_closure(desc, gt.positives(), exclude_recent_frames=recent)
    staged = evaluate_retrieval(
        two_stage(desc, yaw16, rerank), len(desc), gt.positives(), exclude_recent_frames=recent
    )
    return res, res16, staged, desc


def operating_points(
    res: LoopClosureResult, key: str, to_service: Callable[[float], float]
) -> dict[str, dict[str, float] | None]:
    """The top-1 threshold at F1max and the loosest one whose precision is at least 0.9,
    0.95 and 0.99 (a false loop closure corrupts a SLAM map: robots want high precision),
    in the service's units (``to_service`` of the protocol's threshold) under ``key``."""
    p, r, t = res.precision, res.recall, res.thresholds
    with np.errstate(invalid="ignore", divide="ignore"):
        f1 = np.where(p + r > 0, 2 * p * r / (p + r), 0.0)

    def point(i: int) -> dict[str, float]:
        return {
            key: float(to_service(t[i])),
            "protocol_threshold": float(t[i]),
            "precision": float(p[i]),
            "recall": float(r[i]),
        }

    points: dict[str, dict[str, float] | None] = {"f1max": point(int(np.argmax(f1)))}
    for target in (0.9, 0.95, 0.99):
        ok = np.flatnonzero((p >= target) & np.isfinite(t))
        points[f"precision>={target}"] = point(int(ok[np.argmax(r[ok])])) if len(ok) else None
    return points


if __name__ == "__main__":
    main()
