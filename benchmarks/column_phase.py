"""Where a one-view scan's columns should start, chosen on the validation town (never on test).

A file with aligned columns (``overlapmamba export --column-phase aligned``,
``overlapmamba.core.views``) starts each scan's columns at a direction taken from the scan
itself, so a turn rolls the image by whole columns. Any turn-equivariant direction does
that; they differ in how the columns of two scans of one place from different poses line up.
This benchmark describes ``data/synth/val`` and its second session ``val-s1`` with the
model's weights at one view, its columns started four ways: at the sensor's azimuth (no
alignment), and at the direction of the bearings' first, second and fourth circular moment
(``scan_offset(..., harmonic=k)``; k = 1 is the mean bearing, which aligned files use), and
scores each as ``benchmarks/rerank.py`` scores a second stage: loop closure on ``val``
(F1max and Recall@1, all / same / reverse direction) and AR@1 across sessions, the
descriptor alone and two stages (``--rerank``), ranked by the mean of those seven numbers.

An aligned image is made by turning the scan by its offset before the plain projection (a
turn by a fraction of a column shifts every column coordinate by that fraction), and its
yaw features are shifted back as the service does (``Encoder.encode(images, offsets)``).

    python benchmarks/column_phase.py [--model models/overlapmamba-hdl64.onnx]

Writes JSON (default reports/model/column-phase-val.json). ≈ 20 min on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from collections.abc import Iterator
from itertools import islice
from pathlib import Path

import numpy as np
from bench_kit import ROOT, provenance, refuse_aligned
from reports_kit import REPORTS
from rich.console import Console
from rich.table import Table

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.datasets.base import Sequence
from overlapmamba.core.rerank import OFF, Rerank
from overlapmamba.core.views import scan_offset
from overlapmamba.service.encoder import Encoder
from overlapmamba.train.evaluate import SUBSETS, loop_closure, sequence_loops
from overlapmamba.train.modelfile import with_views
from overlapmamba.train.realscans import turned_points
from overlapmamba.train.sessions import check_sessions, descriptor_recall, town_positions

HARMONICS = (1, 2, 4)


def describe(enc: Encoder, seq: Sequence, harmonic: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Every scan of ``seq`` at one view, its columns at the sensor's azimuth (``harmonic``
    None) or started at the direction of its bearings' ``harmonic``-th moment."""
    p = enc.meta.profile

    def scans() -> Iterator[tuple[np.ndarray, float]]:
        for i in range(len(seq)):
            xyz = seq.points(i).xyz[:, :3]
            if harmonic is None:
                yield enc.project(xyz), 0.0
                continue
            depth = np.linalg.norm(xyz, axis=1)
            kept = xyz[(depth > p.min_range) & (depth < p.max_range)]
            offset = scan_offset(
                kept[:, 0], kept[:, 1], np.linalg.norm(kept, axis=1), p.width, harmonic
            )
            # the sensor turned by `offset` columns: every column coordinate grows by it
            yield enc.project(turned_points(xyz, offset * 360.0 / p.width)), offset

    descs, yaws = [], []
    it = scans()
    while batch := list(islice(it, 8)):  # 8 scans a call, as evaluation describes them
        d, y = enc.encode(np.stack([b[0] for b in batch]), np.array([b[1] for b in batch]))
        descs.append(d)
        yaws.append(y)
    return np.concatenate(descs), np.concatenate(yaws)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", type=Path, default=ROOT / "models" / "overlapmamba-hdl64.onnx")
    ap.add_argument("--val", type=Path, default=ROOT / "data" / "synth" / "val")
    ap.add_argument("--second-session", type=Path, default=ROOT / "data" / "synth" / "val-s1")
    ap.add_argument("--rerank", default="20,0.2", help="the second stage: SHORTLIST,WEIGHT")
    ap.add_argument("--out", type=Path, default=REPORTS / "model" / "column-phase-val.json")
    args = ap.parse_args()
    if args.val.name.startswith("test") or args.second_session.name.startswith("test"):
        ap.error("choose on the validation town, never on a test town")
    refuse_aligned(args.model, "its rows start from the sensor's columns")
    k, w = args.rerank.split(",")
    second_stage = Rerank(int(k), float(w))

    t0 = time.perf_counter()
    val, second = open_sequence(args.val), open_sequence(args.second_session)
    check_sessions(val, second)
    gt = sequence_loops(val)
    pos, pos_q = town_positions(val), town_positions(second)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        one = Path(tmp) / "one-view.onnx"
        with_views(args.model, one, 1)
        enc = Encoder(one, intra_op_threads=2)
        for harmonic in (None, *HARMONICS):
            desc, yaw = describe(enc, val, harmonic)
            desc_q, yaw_q = describe(enc, second, harmonic)
            row: dict = {"columns": "sensor" if harmonic is None else f"harmonic {harmonic}"}
            for stage, p in (("descriptor", OFF), ("two_stages", second_stage)):
                res = loop_closure(desc, gt, yaw, p)
                xs = descriptor_recall(desc, pos, desc_q, pos_q, yaw=(yaw, yaw_q), rerank=p)
                scores = {
                    f"{s}_{m}": getattr(res[s], a)
                    for s in SUBSETS
                    for m, a in (("f1max", "f1max"), ("recall@1", "recall_at_1"))
                }
                scores["cross_session_ar@1"] = xs["ar@1"]
                row[stage] = {**scores, "mean": float(np.mean(list(scores.values())))}
            row["mean_of_both"] = (row["descriptor"]["mean"] + row["two_stages"]["mean"]) / 2
            rows.append(row)
    aligned = [r for r in rows if r["columns"] != "sensor"]
    best = max(aligned, key=lambda r: r["mean_of_both"])

    table = Table(title=f"where the columns start, on {val.name} and {second.name}")
    cols = ["columns", "stage", *(f"{s} F1 / R@1" for s in SUBSETS), "AR@1 across", "mean"]
    for col in cols:
        table.add_column(col, justify="right")
    for r in rows:
        for stage in ("descriptor", "two_stages"):
            x = r[stage]
            table.add_row(
                r["columns"],
                stage,
                *(f"{x[f'{s}_f1max']:.3f} / {x[f'{s}_recall@1']:.3f}" for s in SUBSETS),
                f"{x['cross_session_ar@1']:.3f}",
                f"{x['mean']:.4f}",
            )
    console = Console(width=150)
    console.print(table)
    console.print(f"best aligned: {best['columns']}; {time.perf_counter() - t0:.0f} s")
    record = {
        **provenance(),
        "model": str(args.model),
        "val": str(args.val),
        "second_session": str(args.second_session),
        "rerank": args.rerank,
        "rows": rows,
        "best_aligned": best["columns"],
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(record, indent=2) + "\n")
    console.print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
