"""One-column gaps in other sensors' images, and what filling them does to the descriptor
(the ``elevation-fill`` input, :mod:`overlapmamba.core.sensors.gaps`).

The towns are renderings of one drive (``make data-sensors``): frame i of ``SPLIT-SENSOR`` is
the same pose as frame i of the car's ``SPLIT-kitti-hdl64``, so a scan and the car's scan of
its frame are the same place seen by two sensors. Every ``--step``-th frame, per rendering:

- ``gap_share``: the share of the image's cells that are one-column gaps (an empty cell
  between two returns in its row), as the file's projection makes them (view 0);
- the median cosine between its descriptor and the car's of the same frame, three ways:
  ``elevation`` (as served today), ``elevation-fill`` (its gaps filled, the car's scan taken
  natively, as the mode serves it) and ``fill-every-sensor`` (the car's gaps filled too);
- beside them, the median cosine between the car's frame and one far from it (what an
  unrelated place scores), and between the car's scan filled and plain (how far filling
  moves the model's own sensor's descriptor);
- the model's own sensor's cost: the car drive's loop closure (every frame, the descriptor
  alone, F1max / Recall@1) with its scans plain and filled.

The pick (``--split val`` picks, ``--split test`` reports): the way with the highest mean
paired cosine over the renderings among those that keep the car's own F1max and Recall@1
(issue 40: no regression on the model's own sensor). The descriptors are the file's as the
service computes them (its views).

    python benchmarks/fill_gaps.py [--model models/overlapmamba-hdl64.onnx] [--split val]

Writes reports/model/fill-gaps-SPLIT.json (the JSON's ``seconds``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np
from reports_kit import REPORTS, ROOT, write_report
from rich.console import Console
from rich.table import Table

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.datasets.base import Sequence
from overlapmamba.core.sensors.catalogue import get_sensor
from overlapmamba.core.sensors.gaps import fill_gaps, gaps
from overlapmamba.core.sensors.input import SensorInput
from overlapmamba.service.encoder import Encoder
from overlapmamba.train.evaluate import loop_closure, sequence_loops, summary

SENSORS = ("vlp16", "hdl32", "xt32", "os1-128", "os0-128")
WAYS = ("elevation", "elevation-fill", "fill-every-sensor")


def images(enc: Encoder, seq: Sequence, frames: list[int], mode: str = "elevation") -> np.ndarray:
    """(N, V, H, W) the file's images of ``frames`` taken by input ``mode`` from the scans'
    own sensor."""
    inp = SensorInput(enc.meta.profile, get_sensor(seq.sensor), mode)  # type: ignore[arg-type]
    return np.stack([inp.project(seq.points(i), enc.meta.views) for i in frames])


def descriptors(enc: Encoder, imgs: np.ndarray) -> np.ndarray:
    out = [enc.encode(imgs[i : i + 8])[0] for i in range(0, len(imgs), 8)]
    d = np.concatenate(out)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def own_loops(enc: Encoder, seq: Sequence) -> dict[str, dict[str, float]]:
    """The car drive's loop closure, descriptor alone, its scans plain and filled."""
    gt = sequence_loops(seq)
    d: dict[str, list[np.ndarray]] = {"plain": [], "filled": []}
    for start in range(0, len(seq), 64):
        imgs = images(enc, seq, list(range(start, min(start + 64, len(seq)))))
        d["plain"].append(descriptors(enc, imgs))
        d["filled"].append(descriptors(enc, fill_gaps(imgs, enc.meta.profile.empty_value)))
    out: dict[str, dict[str, float]] = {}
    for way, parts in d.items():
        s = summary(loop_closure(np.concatenate(parts), gt))["all"]
        out[way] = {"f1max": float(s["f1max"]), "recall@1": float(s["recall@1"])}
    return out


def median_cosine(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.median((a * b).sum(1)))


def drive_arguments(description: str) -> argparse.Namespace:
    """The options of a benchmark on one drive's renderings (this one's and
    ``cut_margin.py``'s): the model file, the data folder, the split, the frame step, the
    output."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--model", type=Path, default=ROOT / "models" / "overlapmamba-hdl64.onnx")
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "synth")
    ap.add_argument("--split", choices=("val", "test"), default="val")
    ap.add_argument("--step", type=int, default=10, help="every STEP-th frame")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    if args.step < 1:
        raise SystemExit(f"--step must be 1 or more; got {args.step}")
    return args


def main() -> None:
    args = drive_arguments(__doc__.split("\n\n")[0])
    out = args.out or REPORTS / "model" / f"fill-gaps-{args.split}.json"
    t0 = time.perf_counter()
    enc = Encoder(args.model)
    if enc.meta.sensor_input != "elevation" or enc.meta.aligned:
        raise SystemExit(
            f"{args.model} takes {enc.meta.sensor_input!r} (columns {enc.meta.column_phase}): "
            "this benchmark compares ways of projecting against a file that takes "
            "'elevation' in the sensor's columns"
        )
    empty = enc.meta.profile.empty_value
    car_town = args.data / f"{args.split}-kitti-hdl64"
    for town in (car_town, *(args.data / f"{args.split}-{s}" for s in SENSORS)):
        if not town.is_dir():
            raise SystemExit(f"{town} is missing: run `make data-sensors`")
    car_seq = open_sequence(car_town)
    frames = list(range(0, len(car_seq), args.step))
    car_imgs = images(enc, car_seq, frames)
    car = {
        "plain": descriptors(enc, car_imgs),
        "filled": descriptors(enc, fill_gaps(car_imgs, empty)),
    }
    far = np.roll(
        np.arange(len(frames)), len(frames) // 2
    )  # each frame against one half a drive on
    record: dict[str, Any] = {
        "model": str(args.model),
        "model_id": enc.meta.model_id,
        "views": enc.meta.views,
        "split": args.split,
        "car": car_town.name,
        "frames": len(frames),
        "car_gap_share": float(gaps(car_imgs[:, 0], empty).mean()),
        "car_far_cosine": median_cosine(car["plain"], car["plain"][far]),
        "car_filled_to_plain_cosine": median_cosine(car["plain"], car["filled"]),
    }
    rows = []
    for name in SENSORS:
        imgs = images(enc, open_sequence(args.data / f"{args.split}-{name}"), frames)
        plain, filled = descriptors(enc, imgs), descriptors(enc, fill_gaps(imgs, empty))
        rows.append(
            {
                "rendering": f"{args.split}-{name}",
                "sensor": name,
                "columns": get_sensor(name).columns,
                "gap_share": float(gaps(imgs[:, 0], empty).mean()),
                "elevation": median_cosine(plain, car["plain"]),
                "elevation-fill": median_cosine(filled, car["plain"]),
                "fill-every-sensor": median_cosine(filled, car["filled"]),
            }
        )
    mean = {w: float(np.mean([r[w] for r in rows])) for w in WAYS}
    own = own_loops(enc, car_seq)
    keeps = {
        "elevation": True,
        "elevation-fill": True,  # the car's scans are taken natively: unchanged
        "fill-every-sensor": all(own["filled"][k] >= own["plain"][k] for k in own["plain"]),
    }
    record |= {
        "rows": rows,
        "car_loop_closure": own,
        "mean": mean,
        "keeps_own": keeps,
        "pick": max((w for w in WAYS if keeps[w]), key=lambda w: mean[w]),
        "seconds": round(time.perf_counter() - t0, 1),
    }
    write_report(out, record)
    t = Table(title=f"{args.split}: median cosine to the car's scan of the same frame")
    for col in ("rendering", "columns", "gap share", *WAYS):
        t.add_column(col)
    for r in rows:
        t.add_row(
            r["rendering"],
            str(r["columns"]),
            f"{r['gap_share']:.3f}",
            *(f"{r[w]:.3f}" for w in WAYS),
        )
    Console(width=120).print(t)
    print(
        f"car: gap share {record['car_gap_share']:.3f}, "
        f"a far frame {record['car_far_cosine']:.3f}, "
        f"filled to plain {record['car_filled_to_plain_cosine']:.3f}; own loops {own}; "
        f"mean {mean}; "
        f"pick {record['pick']}; wrote {out}"
    )


if __name__ == "__main__":
    main()
