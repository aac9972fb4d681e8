"""Overlap tables: pairs a second, the shipped code against the definition written plainly.

A training town's table holds the overlap of every pair of scans closer than 30 m (158,622
pairs for train-b's 2,000 scans), and computing it costs more than simulating the scans.
This generates a small town of the train presets' kind (``--frames`` HDL-64E scans, in a
temporary folder), takes its candidate pairs as ``gen-data`` does, and computes them in one
process two ways, alternating chunks of whole queries so that both meet the same machine:

- ``plain``: the definition as written (float64 ``transform_points``, ``pixel_coordinates``,
  the nearest point of each pixel by ``np.minimum.at``), one reference at a time: the code
  the tables were made with up to generator 1.6;
- ``shipped``: :func:`overlapmamba.core.overlap.pair_overlaps` (float32 points as (3, N)
  rows, one (3, 3) @ (3, N) product a pair, :func:`overlapmamba.core.projection.pixel_index`).

It reports pairs a second each, their ratio, and how far the two tables are apart (largest
difference, share of pairs that differ at all, pairs on the other side of the 0.3 positive
threshold). Writes reports/synthetic/overlap_tables.json.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
from reports_kit import REPORTS, write_report

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.overlap import candidate_pairs, pair_overlaps
from overlapmamba.core.poses import relative_transform, transform_points
from overlapmamba.core.projection import pixel_coordinates, project
from overlapmamba.core.sensors import SensorProfile, get_profile
from overlapmamba.synth.config import GenConfig
from overlapmamba.synth.generate import build_scene, simulate_scans, write_layout


def plain_overlaps(seq, pairs: np.ndarray, profile: SensorProfile) -> np.ndarray:
    """The overlap of each (query, reference) pair as the module docstring defines it."""
    H, W = profile.height, profile.width
    out = np.zeros(len(pairs), np.float32)
    for q in np.unique(pairs[:, 0]):
        rows = np.flatnonzero(pairs[:, 0] == q)
        image = project(seq.points(int(q)).xyz, profile)
        valid = image != np.float32(profile.empty_value)
        rel = relative_transform(seq.poses[q], seq.poses[pairs[rows, 1]])
        for k, t in zip(rows, rel, strict=True):
            xyz = transform_points(seq.points(int(pairs[k, 1])).xyz, t)
            pc = pixel_coordinates(xyz, profile)
            slab = np.full(H * W, np.inf, np.float32)
            np.minimum.at(slab, pc.row.astype(np.int64) * W + pc.col, pc.depth)
            hit = np.isfinite(slab) & valid.ravel() & (np.abs(slab - image.ravel()) < 1.0)
            out[k] = hit.sum() / max(int(valid.sum()), 1)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--seed", type=int, default=1101, help="default: train-b's town")
    ap.add_argument("--queries-per-chunk", type=int, default=20)
    ap.add_argument("--json", type=Path, default=REPORTS / "synthetic" / "overlap_tables.json")
    args = ap.parse_args()

    cfg = GenConfig(seed=args.seed, frames=args.frames, gt_radius=30.0, split="train")
    profile = get_profile(cfg.sensor)
    tmp = Path(tempfile.mkdtemp(prefix="overlap-tables-"))
    try:
        world, drive, dyn = build_scene(cfg)
        simulate_scans(tmp, world, drive, dyn, cfg, workers=2, progress=False)
        write_layout(tmp, drive)
        seq = open_sequence(tmp, kind="kitti", sensor=cfg.sensor)
        for i in range(len(seq)):
            seq.points(i)  # both ways read the scans from the page cache
        pairs = candidate_pairs(seq.positions(), radius=cfg.gt_radius, min_gap=1)
        pairs = pairs[np.argsort(pairs[:, 0], kind="stable")]
        queries = np.unique(pairs[:, 0])
        groups = np.array_split(queries, max(1, len(queries) // args.queries_per_chunk))
        plain = np.zeros(len(pairs), np.float32)
        shipped = np.zeros(len(pairs), np.float32)
        seconds = {"plain": 0.0, "shipped": 0.0}
        for n, group in enumerate(groups):
            rows = np.flatnonzero(np.isin(pairs[:, 0], group))
            ways = [("plain", plain), ("shipped", shipped)]
            for name, table in ways if n % 2 == 0 else ways[::-1]:
                t = time.perf_counter()
                if name == "plain":
                    table[rows] = plain_overlaps(seq, pairs[rows], profile)
                else:
                    table[rows] = pair_overlaps(seq, pairs[rows], profile, progress=False)[0]
                seconds[name] += time.perf_counter() - t
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    diff = np.abs(shipped - plain)
    rate = {k: len(pairs) / v for k, v in seconds.items()}
    record = {
        "benchmark": "overlap_tables",
        "town": {"seed": cfg.seed, "frames": cfg.frames, "sensor": cfg.sensor, "radius_m": 30.0},
        "pairs": len(pairs),
        "processes": 1,
        "seconds": seconds,
        "pairs_per_s": rate,
        "speedup": rate["shipped"] / rate["plain"],
        "agreement": {
            "max_abs_difference": float(diff.max()),
            "mean_abs_difference": float(diff.mean()),
            "share_of_pairs_that_differ": float((diff > 0).mean()),
            "pairs_across_0_3": int(((shipped > 0.3) != (plain > 0.3)).sum()),
        },
    }
    print(
        f"{len(pairs)} pairs of {cfg.frames} scans, one process: plain {rate['plain']:.0f} "
        f"pairs/s, shipped {rate['shipped']:.0f} pairs/s ({record['speedup']:.2f}×); "
        f"largest difference {diff.max():.2e}, {100 * (diff > 0).mean():.1f} % of pairs differ, "
        f"{record['agreement']['pairs_across_0_3']} across 0.3"
    )
    write_report(args.json, record)
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
