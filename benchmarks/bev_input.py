"""Which cells of a polar bird's-eye view agree across sensors: the ``bev`` input's design.

No network: each layout of cells (height bands above the reference ground × rings of range,
:func:`overlapmamba.core.sensors.bev.project_bev_offset`, one view) is described by a hand-made
turn-invariant spectrum, each row's magnitudes of the first ``--harmonics`` Fourier
components over the columns, L2-normalised, and scored under the loop-closure protocol on
the validation drive and its renderings by other sensors (``val-kitti-hdl64`` and
``val-vlp16``, ``val-os0-128``, ``val-xt32``, ``val-os1-128``: frame i is the same place in
each): ``own``, a rendering's queries against its own earlier scans, and ``cross``, against
the HDL-64E's. A layout whose cells mean the same for every sensor scores ``cross`` close to
``own``; the one the input ships with was chosen here, on validation drives only.

    python benchmarks/bev_input.py [--out reports/model/bev-input.json]

≈ 5 min on 2 cores (reading the 10,000 scans is most of it).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np
from reports_kit import REPORTS, ROOT, write_report

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.sensors import get_profile
from overlapmamba.core.sensors.bev import BEV_BANDS, BEV_RINGS, project_bev_offset
from overlapmamba.train.evaluate import cross_loop_closure, loop_closure, sequence_loops, summary

SENSORS = ("kitti-hdl64", "vlp16", "os0-128", "xt32", "os1-128")
# (name, bands in m above the reference ground, rings): the shipped layout first
LAYOUTS: tuple[tuple[str, tuple[float, ...], int], ...] = (
    ("shipped", BEV_BANDS, BEV_RINGS),
    ("one band 0.3-1.7 m", (0.3, 1.7), 64),
    ("one band 0.3-3 m", (0.3, 3.0), 64),
    ("three bands to 3 m", (0.3, 1.0, 1.7, 3.0), 21),
    ("three bands to 5 m", (0.3, 1.7, 3.0, 5.0), 21),
    ("four bands to 5 m", (0.3, 1.0, 1.7, 3.0, 5.0), 16),
)


def spectrum(image: np.ndarray, harmonics: int) -> np.ndarray:
    """(H, W) cells (1 occupied, else empty) → the rows' turn-invariant magnitudes, L2."""
    f = np.abs(np.fft.rfft((image > 0).astype(np.float32), axis=1))[:, :harmonics].ravel()
    return (f / max(float(np.linalg.norm(f)), 1e-9)).astype(np.float32)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "synth")
    ap.add_argument("--harmonics", type=int, default=16)
    ap.add_argument("--out", type=Path, default=REPORTS / "model" / "bev-input.json")
    args = ap.parse_args()
    t0 = time.perf_counter()
    profile = get_profile("kitti-hdl64")
    desc: dict[str, dict[str, np.ndarray]] = {}
    for s in SENSORS:
        seq = open_sequence(args.data / f"val-{s}")
        rows: dict[str, list[np.ndarray]] = {name: [] for name, _, _ in LAYOUTS}
        for i in range(len(seq)):
            xyz = seq.points(i).xyz  # every val rendering sits on the car's roof, level
            for name, bands, rings in LAYOUTS:
                image = project_bev_offset(xyz, profile, 1, bands, rings)[0][0]
                rows[name].append(spectrum(image, args.harmonics))
        desc[s] = {name: np.stack(v) for name, v in rows.items()}
        print(f"{s}: {len(seq)} scans", flush=True)
    gt = sequence_loops(open_sequence(args.data / "val-kitti-hdl64"))
    layouts: list[dict[str, Any]] = []
    for name, bands, rings in LAYOUTS:
        row: dict[str, Any] = {"name": name, "bands_m": list(bands), "rings": rings}
        for s in SENSORS:
            own = summary(loop_closure(desc[s][name], gt))["all"]
            row[s] = {"own": {k: own[k] for k in ("f1max", "recall@1")}}
            if s != SENSORS[0]:
                cross = cross_loop_closure(desc[s][name], desc[SENSORS[0]][name], gt)["all"]
                row[s]["cross"] = {k: cross[k] for k in ("f1max", "recall@1")}
        others = SENSORS[1:]
        row["mean_own_f1max"] = float(np.mean([row[s]["own"]["f1max"] for s in SENSORS]))
        row["mean_cross_f1max"] = float(np.mean([row[s]["cross"]["f1max"] for s in others]))
        layouts.append(row)
        print(
            f"{name:22s} own {row['mean_own_f1max']:.3f} cross {row['mean_cross_f1max']:.3f}",
            flush=True,
        )
    record = {
        "data": {s: str((args.data / f"val-{s}").relative_to(ROOT)) for s in SENSORS},
        "descriptor": f"per-row |FFT| over columns, first {args.harmonics} harmonics, L2",
        "layouts": layouts,
        "seconds": round(time.perf_counter() - t0, 1),
    }
    write_report(args.out, record)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
