"""Synthetic LiDAR throughput: scans/s on a full-size town, and overlap ground truth pairs/s.

Builds the default 6×6-node town (the train preset's size), plans a drive, and simulates
``--frames`` KITTI HDL-64E scans with 1 and with 2 worker processes, writing real files as
``overlapmamba gen-data`` does. Then times the overlap ground truth for the same scans.
Prints a table and writes JSON (default reports/synthetic/simulator.json).

Goal: ≥ 10 scans/s on 2 cores at ≈120k points per scan, so that a 4,000-scan
sequence simulates in about 7 minutes or less.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path

from reports_kit import REPORTS, write_report

from overlapmamba.synth.config import GenConfig
from overlapmamba.synth.generate import build_scene, simulate_scans, write_layout
from overlapmamba.synth.truth import compute_ground_truth

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=240)
    ap.add_argument("--seed", type=int, default=1001, help="default: the train preset's town")
    ap.add_argument("--json", type=Path, default=REPORTS / "synthetic" / "simulator.json")
    args = ap.parse_args()

    cfg = GenConfig(seed=args.seed, frames=args.frames, gt_radius=30.0)
    t = time.perf_counter()
    world, drive, dyn = build_scene(cfg)
    t_world = time.perf_counter() - t

    rows = []
    tmp = Path(tempfile.mkdtemp(prefix="simbench-"))
    try:
        for workers in (1, 2):
            out = tmp / f"w{workers}"
            t = time.perf_counter()
            counts = simulate_scans(out, world, drive, dyn, cfg, workers, progress=False)
            dt = time.perf_counter() - t
            rows.append(
                {
                    "what": "simulate",
                    "workers": workers,
                    "frames": cfg.frames,
                    "seconds": dt,
                    "scans_per_s": cfg.frames / dt,
                    "points_per_scan": float(counts.mean()),
                    "minutes_per_4000_scans": 4000 / (cfg.frames / dt) / 60,
                }
            )
        out = tmp / "w2"
        write_layout(out, drive)  # ground truth reads the poses beside the scans
        t = time.perf_counter()
        table, _ = compute_ground_truth(out, cfg, workers=2, progress=False)
        dt = time.perf_counter() - t
        pairs = len(table["query"])
        rows.append(
            {
                "what": "overlap ground truth",
                "workers": 2,
                "frames": cfg.frames,
                "seconds": dt,
                "pairs": pairs,
                "pairs_per_s": pairs / dt,
                "pairs_per_frame": pairs / cfg.frames,
                "minutes_per_4000_scans": 4000 * pairs / cfg.frames / (pairs / dt) / 60,
            }
        )
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    print(
        f"Town: {len(world.static)} triangles, {world.street_length / 1000:.1f} km of street; "
        f"town, drive and traffic built in {t_world:.2f} s; "
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores\n"
    )
    print(
        f"| {'what':<22} | workers | frames | seconds | rate | points/scan | min per 4000 scans |"
    )
    print(f"|{'-' * 24}|---------|--------|---------|------|-------------|--------------------|")
    for r in rows:
        rate = (
            f"{r['scans_per_s']:.1f} scans/s"
            if "scans_per_s" in r
            else f"{r['pairs_per_s']:.0f} pairs/s"
        )
        pts = f"{r['points_per_scan']:.0f}" if "points_per_scan" in r else "—"
        print(
            f"| {r['what']:<22} | {r['workers']} | {r['frames']} | {r['seconds']:.1f} | {rate} | "
            f"{pts} | {r['minutes_per_4000_scans']:.1f} |"
        )
    sim2 = next(r for r in rows if r["what"] == "simulate" and r["workers"] == 2)
    ok = sim2["scans_per_s"] >= 10.0
    print(
        f"\ngoal ≥ 10 scans/s on 2 cores: {'met' if ok else 'NOT met'} ({sim2['scans_per_s']:.1f})"
    )
    write_report(
        args.json,
        {
            "benchmark": "simulator",
            "town": {
                "triangles": len(world.static),
                "street_km": world.street_length / 1000,
                "build_s": t_world,
            },
            "rows": rows,
            "goal_scans_per_s_2_cores": 10.0,
            "goal_met": ok,
        },
    )
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
