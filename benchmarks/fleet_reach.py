"""How far a fleet's robots get along their drive decides the closures' recall it reports.

The same server (a fresh one each run, the default settings) and the same 8 robots on the
held-out drive ``data/synth/test``; only how many scans a second each robot asks for
changes. In a fixed minute, robots that ask for fewer scans cover shorter stretches of the
drive: which loops they meet changes, and so does the recall, though every closure is
judged the same way. With a fixed number of scans a robot (``simulate(scans=…)``, the
fleet simulator's ``--scans``, what ``make e2e`` asks since 2026-12-02) the slow fleet
covers the stretches the fast one did and its recall comes back.

Rows: each ``--rate`` for ``--duration`` seconds, then the slowest rate with ``--scans``
scans a robot (bounded at 10 minutes). Throughput, scans a robot, precision and recall of
the accepted closures (ground truth: the drive's loop radius).

    python benchmarks/fleet_reach.py [--model models/overlapmamba-any-sensor.onnx]
        [--rates 10,3,2] [--duration 60] [--scans 250]

Writes reports/client/fleet-reach.json. About 5 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import asyncio
import time
from pathlib import Path
from typing import Any

from bench_kit import server
from reports_kit import REPORTS, ROOT, shown_path, write_report
from rich.console import Console
from rich.table import Table

from overlapmamba.client import NO_RETRY
from overlapmamba.client._replay import open_drive
from overlapmamba.client.fleet import simulate

DRIVE = ROOT / "data" / "synth" / "test"
ROBOTS = 8


def one_run(model: Path, drive: Any, rate: float, duration: float, scans: int | None) -> dict:
    with server({}, model=model) as url:
        report, _ = asyncio.run(
            simulate(
                url,
                "fleet",
                [drive],
                robots=ROBOTS,
                duration_s=duration,
                rate_hz=rate,
                retry=NO_RETRY,
                scans=scans,
            )
        )
    return {
        "rate_hz_asked": rate,
        "scans_asked": scans,
        "duration_s": report.duration_s,
        "observations": report.observations,
        "scans_per_robot": report.observations / ROBOTS,
        "throughput_per_s": report.throughput_per_s,
        "errors": report.errors,
        "queries_with_loop": report.queries_with_loop,
        "loop_closures": report.loop_closures,
        "precision": report.precision,
        "recall": report.recall,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, default=ROOT / "models" / "overlapmamba-any-sensor.onnx")
    ap.add_argument(
        "--rates", default="10,3,2", help="scans a second a robot asks, comma-separated"
    )
    ap.add_argument("--duration", type=float, default=60.0, help="seconds of each timed run")
    ap.add_argument("--scans", type=int, default=250, help="scans a robot in the last run")
    ap.add_argument("--out", type=Path, default=REPORTS / "client" / "fleet-reach.json")
    args = ap.parse_args()
    try:
        rates = [float(r) for r in args.rates.split(",")]
    except ValueError:
        ap.error(f"--rates must be numbers separated by commas; got {args.rates!r}")
    if not rates or min(rates) <= 0 or args.duration <= 0 or args.scans < 1:
        ap.error("--rates must be positive, --duration positive and --scans at least 1")
    if not (DRIVE / "manifest.json").is_file():
        raise SystemExit(f"{DRIVE} is missing: overlapmamba gen-data {DRIVE} --preset test")
    console = Console(width=120)
    drive = open_drive(DRIVE)
    t0 = time.perf_counter()
    runs = [one_run(args.model, drive, r, args.duration, None) for r in rates]
    runs.append(one_run(args.model, drive, min(rates), 600.0, args.scans))
    table = Table(title=f"{ROBOTS} robots on {DRIVE.name}, {shown_path(args.model)}")
    for col in ("asked", "time", "scans a robot", "observations/s", "precision", "recall"):
        table.add_column(col)
    for r in runs:
        asked = f"{r['rate_hz_asked']:g} Hz" + (
            f", {r['scans_asked']} scans" if r["scans_asked"] else f", {args.duration:g} s"
        )
        table.add_row(
            asked,
            f"{r['duration_s']:.0f} s",
            f"{r['scans_per_robot']:.0f}",
            f"{r['throughput_per_s']:.1f}",
            f"{r['precision']:.3f}",
            f"{r['recall']:.3f}",
        )
    console.print(table)
    record = {
        "model": shown_path(args.model),
        "drive": shown_path(DRIVE),
        "robots": ROBOTS,
        "runs": runs,
        "seconds": round(time.perf_counter() - t0, 1),
    }
    write_report(args.out, record)
    console.print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
