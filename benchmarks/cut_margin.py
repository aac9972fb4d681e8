"""What the cut at 50 m (the ``elevation-reach`` input) does to each sensor's margin: how
much nearer a scan's descriptor lies to the car's scan of the same place than to the car's
scan of another place, with and without the cut.

The towns are renderings of one drive (``make data-sensors``): frame i of ``SPLIT-SENSOR`` is
the pose of frame i of ``SPLIT-kitti-hdl64``. Every ``--step``-th frame, for each rendering
and each input (``elevation-fill`` uncut, ``elevation-reach`` cut; the car's scans as the
input takes them, so cut by ``elevation-reach`` too), the model file's descriptors
(its views, as the service computes them):

- ``paired``: the median cosine between a rendering's scan and the car's of the same frame;
- ``unrelated``: the median cosine between a rendering's scan and the car's scan half the
  drive on (another place);
- ``margin``: paired − unrelated;
- ``nearest_wrong``: the median over a rendering's scans of the highest cosine to a car scan
  of another place (more than ``HIT_M`` from it), what the paired cosine has to beat;
- ``recall@1``: the share of a rendering's scans whose nearest car scan (among the sampled
  frames) lies within ``HIT_M`` of it: retrieval across sensors on these frames.

    python benchmarks/cut_margin.py [--model models/overlapmamba-hdl64.onnx] [--split val]

Writes reports/model/cut-margin-SPLIT.json (≈ 2 min on 2 cores with the shipped file, step 10).
"""

from __future__ import annotations

import time
from typing import Any

import fill_gaps
import numpy as np
from reports_kit import REPORTS, shown_path, write_report

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.datasets.base import Sequence
from overlapmamba.service.encoder import Encoder

SENSORS = ("vlp16", "xt32", "os1-128", "os0-128")
INPUTS = ("elevation-fill", "elevation-reach")
HIT_M = 5.0  # m: the across-pairs benchmark's hit radius


def descriptors(enc: Encoder, seq: Sequence, mode: str, frames: list[int]) -> np.ndarray:
    """(N, D) unit descriptors of ``frames`` of ``seq`` taken by input ``mode``."""
    return fill_gaps.descriptors(enc, fill_gaps.images(enc, seq, frames, mode))


def margins(
    ds: np.ndarray, dc: np.ndarray, near: np.ndarray, other: np.ndarray
) -> dict[str, float]:
    """A rendering's unit descriptors ``ds`` against the car's ``dc`` of the same frames
    (row i of each: one pose); ``near`` (N, N): frames within ``HIT_M`` of each other;
    ``other``: for each frame, the car frame that stands for another place."""
    cos = ds @ dc.T
    paired = float(np.median(np.diag(cos)))
    unrelated = float(np.median(cos[np.arange(len(ds)), other]))
    return {
        "paired": paired,
        "unrelated": unrelated,
        "margin": paired - unrelated,
        "nearest_wrong": float(np.median(np.where(near, -np.inf, cos).max(1))),
        "recall@1": float(near[np.arange(len(ds)), cos.argmax(1)].mean()),
    }


def main() -> None:
    args = fill_gaps.drive_arguments(__doc__.split("\n\n")[0])
    out = args.out or REPORTS / "model" / f"cut-margin-{args.split}.json"
    t0 = time.perf_counter()
    enc = Encoder(args.model)
    towns = {s: args.data / f"{args.split}-{s}" for s in ("kitti-hdl64", *SENSORS)}
    missing = [str(t) for t in towns.values() if not (t / "manifest.json").is_file()]
    if missing:
        raise SystemExit(f"{', '.join(missing)} missing: run `make data-sensors`")
    car = open_sequence(towns["kitti-hdl64"])
    frames = list(range(0, len(car), args.step))
    other = np.roll(np.arange(len(frames)), len(frames) // 2)  # half the drive on
    xy = car.positions()[frames, :2]
    near = np.linalg.norm(xy[:, None] - xy[None], axis=-1) <= HIT_M  # the renderings' poses too
    rows: list[dict[str, Any]] = []
    for mode in INPUTS:
        dc = descriptors(enc, car, mode, frames)
        for s in SENSORS:
            ds = descriptors(enc, open_sequence(towns[s]), mode, frames)
            row = {"input": mode, "sensor": s, **margins(ds, dc, near, other)}
            rows.append(row)
            print(
                f"{mode} {s}: paired {row['paired']:.3f} unrelated {row['unrelated']:.3f} "
                f"nearest wrong {row['nearest_wrong']:.3f} recall@1 {row['recall@1']:.3f}",
                flush=True,
            )
    record = {
        "model": shown_path(args.model),
        "model_id": enc.meta.model_id,
        "views": enc.meta.views,
        "split": args.split,
        "frames": len(frames),
        "step": args.step,
        "hit_m": HIT_M,
        "rows": rows,
        "seconds": round(time.perf_counter() - t0, 1),
    }
    write_report(out, record)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
