"""How far apart the column grids of a revisit's two scans are, on the synthetic towns.

A range image's columns follow the sensor's azimuth. Two scans of one place whose headings
differ by a whole number of columns (or by 180° plus one) see it on the same grid; any other
difference puts one grid a fraction of a column off the other, which the network is not
exactly invariant to. Whether the towns' revisits keep their grids in step says whether a
descriptor in the sensor's columns is favoured over one whose columns start at a direction
taken from the scan (aligned columns, ``overlapmamba.core.views``) by how the drives were
made rather than by what the network learned.

For every scan with an earlier one (outside the 100-frame exclusion) within 5 m, its nearest
such scan: the heading difference, its distance from 0° or 180° (same or reverse
direction), and its remainder in columns of the model's profile (``--width``, 900 by
default: 0.4°), folded to [0, ½]. A uniform remainder has median ¼ and puts a fifth within
0.1 of a column.

    python benchmarks/revisit_phase.py [--town data/synth/val ...]

Writes JSON (default reports/synthetic/revisit-phase.json). Seconds on 2 cores (poses only).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from reports_kit import REPORTS, ROOT, shown_path, write_report
from rich.console import Console
from rich.table import Table

from overlapmamba.core.datasets import open_sequence

TOWNS = ("val", "test", "test-b", "test-c")
EXCLUDE = 100  # frames: the loop-closure protocol's exclusion
RADIUS = 5.0  # m: the protocol's hit radius


def revisits(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(query, match) index pairs: each scan's nearest earlier scan outside the exclusion,
    where it lies within ``RADIUS``."""
    xy = poses[:, :2, 3]
    q, m = [], []
    for i in range(EXCLUDE + 1, len(poses)):
        d = np.linalg.norm(xy[: i - EXCLUDE] - xy[i], axis=1)
        j = int(np.argmin(d))
        if d[j] <= RADIUS:
            q.append(i)
            m.append(j)
    return np.array(q, np.int64), np.array(m, np.int64)


def town_phase(poses: np.ndarray, width: int) -> dict[str, float | int]:
    q, m = revisits(poses)
    yaw = np.degrees(np.arctan2(poses[:, 1, 0], poses[:, 0, 0]))
    diff = (yaw[q] - yaw[m]) % 360.0
    reverse = np.abs(diff - 180.0) < 90.0
    off = np.where(reverse, np.abs(diff - 180.0), np.minimum(diff, 360.0 - diff))
    cols = diff / (360.0 / width)
    frac = np.abs(cols - np.round(cols))
    return {
        "revisits": len(q),
        "reverse_share": float(reverse.mean()),
        "heading_off_median_deg": float(np.median(off)),
        "column_remainder_median": float(np.median(frac)),
        "within_tenth_of_a_column": float((frac < 0.1).mean()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--town", action="append", type=Path, help="default: the val and test towns")
    ap.add_argument("--width", type=int, default=900, help="columns a turn of the image holds")
    ap.add_argument("--json", type=Path, default=REPORTS / "synthetic" / "revisit-phase.json")
    args = ap.parse_args()
    towns = args.town or [ROOT / "data" / "synth" / t for t in TOWNS]
    rows = {}
    for town in towns:
        seq = open_sequence(town)
        rows[town.name] = town_phase(np.asarray(seq.poses), args.width)
    table = Table(title=f"revisits' column remainders ({args.width} columns)")
    for col in ("town", "revisits", "reverse", "heading off 0/180°", "median remainder", "< 0.1"):
        table.add_column(col)
    for name, r in rows.items():
        table.add_row(
            name,
            str(r["revisits"]),
            f"{r['reverse_share']:.2f}",
            f"{r['heading_off_median_deg']:.2f}",
            f"{r['column_remainder_median']:.3f}",
            f"{r['within_tenth_of_a_column']:.3f}",
        )
    Console().print(table)
    record = {
        "width": args.width,
        "exclude_frames": EXCLUDE,
        "radius_m": RADIUS,
        "uniform": {"column_remainder_median": 0.25, "within_tenth_of_a_column": 0.2},
        "towns": rows,
    }
    write_report(args.json, record)
    print(f"wrote {shown_path(args.json)}")


if __name__ == "__main__":
    main()
