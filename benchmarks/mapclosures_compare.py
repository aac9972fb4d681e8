"""MapClosures (PRBonn, ``map-closures`` on the package index) on one of our towns, scored
against our ground truth, beside our verified loop closures.

MapClosures is not a dependency of this project: install it in its own environment
(``python -m venv /tmp/mc && /tmp/mc/bin/pip install map-closures``) and pass its
``map_closure_pipeline`` with ``--exe``. It runs with the authors' defaults and the generic
loader on the town's ``velodyne/`` folder (its KITTI loader applies the real sensor's 0.22°
scan correction, which distorts synthetic scans). Its own ``--eval`` needs a ready-made
ground-truth file; its closures are scored against ours here instead:

- MapClosures matches *local maps* (kiss-icp odometry, a new map every ``max_range`` metres,
  100 m by default) and reports a closure when the query map is complete. The maps' scan
  ranges are rebuilt from its odometry (``kiss_poses_kitti.txt``) by the same rule.
- A revisiting scan (one with a ground-truth loop, overlap > 0.3) is **covered** when its
  local map has a closure to an earlier map holding one of its true loops.
- **Pose error**: the closure's pose T_query map←reference map (the convention of its own
  visualiser, which draws the reference map at ``query pose @ alignment``) against the
  ground truth P_query start⁻¹ · P_reference start.
- **Latency**: for each covered scan, the scans between it and the end of its local map
  (when the closure is reported), in seconds at the town's 10 Hz.

``--ours`` adds our figures for the same town from a ``benchmarks/verify_threshold.py``
JSON. Prints a table and writes JSON.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np
from reports_kit import REPORTS, write_report
from rich.console import Console
from rich.table import Table

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.overlap import LoopGroundTruth
from overlapmamba.core.poses import pose_error

ROOT = Path(__file__).resolve().parents[1]


def local_maps(odom: np.ndarray, max_range: float) -> list[tuple[int, int]]:
    """MapClosures' local maps as [start, end] scan indices (end inclusive): a map closes at
    the first scan farther than ``max_range`` from its start, or at the last scan; the next
    map starts at that scan."""
    maps, start = [], 0
    for i in range(len(odom)):
        if np.linalg.norm(odom[i][:3, 3] - odom[start][:3, 3]) > max_range or i == len(odom) - 1:
            maps.append((start, i))
            start = i
    return maps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--town", type=Path, default=ROOT / "data" / "synth" / "test")
    ap.add_argument("--exe", type=Path, help="map_closure_pipeline (omit to score --results)")
    ap.add_argument("--results", type=Path, default=ROOT / "bench-results" / "mapclosures")
    ap.add_argument("--ours", type=Path, help="verify_threshold.py JSON for the same town")
    ap.add_argument("--json", type=Path, default=REPORTS / "service" / "mapclosures.json")
    args = ap.parse_args()
    console = Console()
    run_s = None
    if args.exe is not None:
        args.results.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        subprocess.run(
            [str(args.exe), str((args.town / "velodyne").resolve()), str(args.results.resolve())],
            check=True,
            cwd=args.results,
        )
        run_s = time.perf_counter() - t0
    out = max(args.results.rglob("map_closures.txt"), key=lambda p: p.stat().st_mtime)
    rows = np.loadtxt(out, ndmin=2)
    odom12 = np.loadtxt(out.parent / "kiss_poses_kitti.txt")
    odom = np.tile(np.eye(4), (len(odom12), 1, 1))
    odom[:, :3, :] = odom12.reshape(-1, 3, 4)
    config = out.parent / "config.yml"
    max_range = 100.0
    if config.is_file():
        import yaml

        cfg = yaml.safe_load(config.read_text())
        max_range = float(cfg.get("kiss_icp", cfg).get("data", {}).get("max_range", max_range))
    maps = local_maps(odom, max_range)
    seq = open_sequence(args.town)
    gt = LoopGroundTruth.load(args.town / "ground_truth" / "loops.npz")
    positives = gt.positives()
    revisits = np.flatnonzero(gt.has_loop())
    covered: set[int] = set()
    latency = []
    t_err, yaw_err = [], []
    for r in rows:
        ref, query = int(r[0]), int(r[1])
        T = r[2:18].reshape(4, 4)
        (rs, re), (qs, qe) = maps[ref], maps[query]
        truth = np.linalg.inv(seq.poses[qs]) @ seq.poses[rs]
        t, y = pose_error(T, truth)
        t_err.append(t)
        yaw_err.append(y)
        for i in range(qs, qe + 1):
            if i not in covered and any(rs <= j <= re for j in positives[i]):
                covered.add(i)
                latency.append((qe - i) / 10.0)
    report: dict[str, Any] = {
        "town": str(args.town),
        "scans": len(seq),
        "revisiting_scans": len(revisits),
        "local_maps": len(maps),
        "max_range_m": max_range,
        "closures": len(t_err),
        "covered_revisits": len(covered),
        "pose_error_m": [float(x) for x in sorted(t_err)],
        "yaw_error_deg": [float(x) for x in sorted(yaw_err)],
        "report_delay_s": {
            "median": float(np.median(latency)) if latency else None,
            "max": float(np.max(latency)) if latency else None,
        },
        "run_s": run_s,
    }
    table = Table(title=f"loop closures on {args.town.name} ({len(revisits)} revisiting scans)")
    for c in ("method", "revisits covered", "pose error m", "yaw error °", "reported"):
        table.add_column(c, justify="right")
    table.add_row(
        "MapClosures (defaults)",
        f"{len(covered)} ({len(covered) / max(1, len(revisits)):.0%})",
        f"{min(t_err):.2f}–{max(t_err):.2f}" if t_err else "—",
        f"{min(yaw_err):.2f}–{max(yaw_err):.2f}" if yaw_err else "—",
        f"up to {max(latency):.1f} s late" if latency else "—",
    )
    if args.ours is not None:
        ours = json.loads(args.ours.read_text())
        row = next(t for t in ours["towns"] if Path(t["town"]).name == args.town.name)
        v = row.get("verified_stop_at_first", row["verified"])  # as the service answers
        report["ours"] = row
        table.add_row(
            "ours (verified, per scan)",
            f"{v['correct']} closures; recall {v['recall']:.0%}",
            f"median {v['translation_error_m']['median']:.3f}",
            f"median {v['yaw_error_deg']['median']:.3f}",
            "at the query",
        )
    console.print(table)
    write_report(args.json, report)
    console.print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
