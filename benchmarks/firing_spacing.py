"""Whether a real head fires at the same azimuths every turn: the spacing between a KITTI
HDL-64E's neighbouring firings, scan by scan, on the real scans in ../shared/data.

KITTI stores each laser's returns in firing order, so the azimuth steps between neighbouring
points of one laser are whole multiples of the spacing; the median step between 0.1° and 0.3°
is the scan's spacing (a lost return makes a step of two, which the median ignores). If the
spacing varies between scans, so does the number of firings a turn, and the pattern in which
the firings meet a model's fixed column grid drifts from turn to turn: the simulator's
``drifting`` firing phase (:mod:`overlapmamba.synth.lidar`), and why
``benchmarks/firing_phase.py`` compares locked and drifting towns.

    python benchmarks/firing_spacing.py [--sequence ../shared/data/kitti00_0000-0100]

Writes JSON (default reports/model/firing-spacing.json). A few seconds.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from reports_kit import REPORTS, ROOT, shown_path, write_report
from rich.console import Console

KITTI = ROOT.parent / "shared" / "data" / "kitti00_0000-0100"
STEP_DEG = (0.1, 0.3)  # a KITTI HDL-64E's steps between neighbouring firings lie here


def spacing_deg(xyz: np.ndarray) -> float:
    """The median azimuth step between neighbouring returns in firing order, within
    ``STEP_DEG``: the scan's spacing between firings, in degrees."""
    az = np.degrees(np.arctan2(xyz[:, 1].astype(np.float64), xyz[:, 0].astype(np.float64)))
    step = np.diff(az)
    step = step[(step > STEP_DEG[0]) & (step < STEP_DEG[1])]
    if len(step) < 1000:
        raise ValueError(
            f"only {len(step)} azimuth steps of {STEP_DEG[0]}–{STEP_DEG[1]}°: not a KITTI "
            "HDL-64E scan in firing order"
        )
    return float(np.median(step))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sequence", type=Path, default=KITTI, help="a KITTI-layout folder")
    ap.add_argument("--out", type=Path, default=REPORTS / "model" / "firing-spacing.json")
    args = ap.parse_args()
    files = sorted((args.sequence / "velodyne").glob("*.bin"))
    if not files:
        raise SystemExit(f"{args.sequence}/velodyne holds no .bin scans")
    d = np.array([spacing_deg(np.fromfile(f, np.float32).reshape(-1, 4)) for f in files])
    turn = 360.0 / d
    result = {
        "sequence": shown_path(args.sequence),
        "scans": len(files),
        "spacing_deg": {
            "min": float(d.min()),
            "p05": float(np.percentile(d, 5)),
            "median": float(np.median(d)),
            "p95": float(np.percentile(d, 95)),
            "max": float(d.max()),
        },
        "firings_a_turn": {"min": float(turn.min()), "max": float(turn.max())},
        "spread": float((d.max() - d.min()) / np.median(d)),
        "per_scan_deg": [round(float(x), 6) for x in d],
    }
    write_report(args.out, result)
    Console().print(
        f"{len(files)} scans: spacing {d.min():.5f}–{d.max():.5f}° (median {np.median(d):.5f}°), "
        f"{turn.min():.0f}–{turn.max():.0f} firings a turn; wrote {args.out}"
    )


if __name__ == "__main__":
    main()
