"""How close ``sensor_like`` comes to the real thing: the validation drive of the sensor towns
rendered by each sensor (``val-SENSOR``), against the model sensor's scan of the same frame
(``val-kitti-hdl64``) seen as that sensor would see it (``overlapmamba.train.augment.SensorLook``).

Per sensor, over every 40th frame (validation data: the augmentation's design was checked
here, never on test towns):

- ``covered``: the share of the rendering's input pixels (as the service projects that
  sensor's scan) that the simulated image also fills; ``agree_1m``: of the pixels both fill,
  the share within 1 m of each other; ``extra``: the simulated pixels the rendering lacks,
  as a share of the rendering's; ``kept_by_range``: the share of simulated returns the
  rendering also has, by 10 m range bin (far returns the sensor loses);
- descriptor cosines with ``--model`` (one view): rendering against simulation, rendering
  against the model sensor's own scan, simulation against the model sensor's own scan.

    python benchmarks/sensor_like.py [--model models/overlapmamba-hdl64.onnx]

Writes reports/model/sensor-like.json. ≈ 1 min on 2 cores.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
from bench_kit import refuse_aligned
from reports_kit import REPORTS, ROOT, write_report
from rich.console import Console
from rich.table import Table

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.sensors.catalogue import CATALOGUE
from overlapmamba.core.sensors.input import SensorInput
from overlapmamba.core.views import project_views
from overlapmamba.train.augment import SensorLook
from overlapmamba.train.checkpoint import load_model
from overlapmamba.train.evaluate import describe
from overlapmamba.train.modelfile import with_views

SENSORS = ("vlp16", "vlp32c", "hdl32", "xt32", "os1-64", "os1-128", "os0-128", "os2-128")
BINS_M = 10.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, default=ROOT / "models" / "overlapmamba-hdl64.onnx")
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "synth")
    ap.add_argument("--every", type=int, default=40, help="every N-th frame")
    ap.add_argument("--out", type=Path, default=REPORTS / "model" / "sensor-like.json")
    args = ap.parse_args()
    ref_path = args.data / "val-kitti-hdl64"
    if not ref_path.is_dir():
        raise SystemExit(f"{ref_path} is missing: run `make data-sensors`")
    refuse_aligned(args.model, "the augmentation's images take the sensor's columns")
    with tempfile.TemporaryDirectory() as tmp:
        one = Path(tmp) / "one-view.onnx"  # a scan as one view: what the augmentation makes
        with_views(args.model, one, 1)
        model, profile, _ = load_model(one)
        ref = open_sequence(ref_path)
        frames = range(0, len(ref), args.every)
        own = np.stack([project_views(ref.points(i), profile, 1)[0] for i in frames])
        d_own, _ = describe(model, own)
        empty = np.float32(profile.empty_value)
        rows = []
        for name in SENSORS:
            path = args.data / f"val-{name}"
            if not path.is_dir():
                continue
            seq = open_sequence(path)
            served = SensorInput(profile, CATALOGUE[name], "elevation")
            real = np.stack([served.project(seq.points(i))[0] for i in frames])
            sim = own.copy()
            look = SensorLook(profile, CATALOGUE[name])
            for img in sim:
                look.apply(img, 0.0, empty)
            rv, sv = real != empty, sim != empty
            both = rv & sv
            bins = np.minimum((sim[sv] // BINS_M).astype(int), int(profile.max_range // BINS_M) - 1)
            n_bin = np.bincount(bins, minlength=int(profile.max_range // BINS_M))
            kept = np.bincount(bins, weights=rv[sv], minlength=len(n_bin))
            d_real, _ = describe(model, real)
            d_sim, _ = describe(model, sim)
            rows.append(
                {
                    "sensor": name,
                    "covered": float(both.sum() / rv.sum()),
                    "agree_1m": float((np.abs(real - sim)[both] < 1.0).mean()),
                    "extra": float((sv & ~rv).sum() / rv.sum()),
                    "kept_by_range": [
                        {"from_m": k * BINS_M, "share": float(kept[k] / n_bin[k])}
                        for k in range(len(n_bin))
                        if n_bin[k]
                    ],
                    "cosine_real_sim": float((d_real * d_sim).sum(1).mean()),
                    "cosine_real_own": float((d_real * d_own).sum(1).mean()),
                    "cosine_sim_own": float((d_sim * d_own).sum(1).mean()),
                }
            )
    write_report(
        args.out,
        {
            "model": str(args.model),
            "reference": str(
                ref_path.relative_to(ROOT) if ref_path.is_relative_to(ROOT) else ref_path
            ),
            "frames": len(frames),
            "rows": rows,
        },
    )
    t = Table(title="sensor_like against each sensor's rendering of the same frames")
    for col in ("sensor", "covered", "agree ≤ 1 m", "extra", "cos real·sim", "real·own", "sim·own"):
        t.add_column(col)
    for r in rows:
        t.add_row(
            r["sensor"],
            *(f"{r[k]:.3f}" for k in ("covered", "agree_1m", "extra")),
            *(f"{r[k]:.3f}" for k in ("cosine_real_sim", "cosine_real_own", "cosine_sim_own")),
        )
    Console().print(t)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
