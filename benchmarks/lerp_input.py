"""Another sensor's scan as the model's own sensor's beams (``elevation-lerp``) against each
model row showing its nearest beam (``elevation``), on renderings of one drive.

The towns are renderings of one drive (``make data-sensors``): the model sensor's car
rendering (``SPLIT-kitti-hdl64``, its loop table labelling every rendering: frame i is the
same place in each) and each other sensor's (``SPLIT-SENSOR``, on the car's roof), and the
car's own scans thinned to every second and fourth ring (declared as the sensor they now
are). Per rendering and input, the descriptor alone, F1max / Recall@1 under the loop-closure
protocol:

- ``own``: its queries against its own earlier scans (a fleet of that sensor alone);
- ``against the car``: its queries against the car's earlier scans (a map made by the
  model's sensor, queried from another): the across-sensor case;
- the mean cosine between a frame's descriptor and the car's of that frame.

The input that wins is the one with the higher mean of those four numbers (F1max and R@1,
own and against the car) over the renderings; ``--split val`` chooses, ``--split test``
reports. One view a scan (a one-view copy of the file, as ``benchmarks/mounts.py``): the
inputs differ before any view, and a third of the time.

    python benchmarks/lerp_input.py [--model models/overlapmamba-hdl64.onnx] [--split val]

Writes reports/model/lerp-input-SPLIT.json. 39 min (test) and 51 min (val) on 2 cores,
each sharing them with other jobs (the JSON's ``seconds``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np
from bench_kit import car_rendering
from reports_kit import REPORTS, ROOT, write_report
from rich.console import Console
from rich.table import Table

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.datasets.base import Sequence
from overlapmamba.core.sensors.catalogue import get_sensor, sensor_of_profile
from overlapmamba.core.sensors.input import SensorInput
from overlapmamba.core.sensors.profile import SensorProfile
from overlapmamba.train.evaluate import (
    cross_loop_closure,
    describe,
    loop_closure,
    summary,
)
from overlapmamba.train.rangecache import range_images
from overlapmamba.train.realscans import thin_points, thinned_sensor

SENSORS = ("vlp16", "hdl32", "xt32", "os1-128", "os0-128")
BEAMS = (32, 16)
INPUTS = ("elevation", "elevation-lerp")
KEYS = ("own_f1max", "own_recall@1", "car_f1max", "car_recall@1")


def thinned_images(car: Sequence, profile: SensorProfile, beams: int, mode: str) -> np.ndarray:
    """(N, H, W) the car's scans thinned to ``beams`` rings, declared as that sensor."""
    own = sensor_of_profile(profile)
    inp = SensorInput(profile, thinned_sensor(own, beams), mode)  # type: ignore[arg-type]
    return np.stack(
        [inp.project(thin_points(car.points(i).xyz, own, beams))[0] for i in range(len(car))]
    )


def score(d: np.ndarray, d_car: np.ndarray, gt: Any) -> dict[str, float]:
    own = summary(loop_closure(d, gt))["all"]
    car = cross_loop_closure(d, d_car, gt)["all"]
    return {
        "own_f1max": own["f1max"],
        "own_recall@1": own["recall@1"],
        "car_f1max": car["f1max"],
        "car_recall@1": car["recall@1"],
        "cosine_to_car": float((d * d_car).sum(1).mean()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, default=ROOT / "models" / "overlapmamba-hdl64.onnx")
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "synth")
    ap.add_argument("--split", choices=("val", "test"), default="val")
    ap.add_argument("--sensors", default=",".join(SENSORS), help="SPLIT-SENSOR renderings")
    ap.add_argument("--beams", default=",".join(map(str, BEAMS)), help="thinned ring counts")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    out = args.out or REPORTS / "model" / f"lerp-input-{args.split}.json"
    t0 = time.perf_counter()
    rows: list[dict[str, Any]] = []
    with car_rendering(args.model, args.data, args.split) as cr:
        model, profile, car, gt, d_car = cr.model, cr.profile, cr.car, cr.gt, cr.d_car
        for name in filter(None, args.sensors.split(",")):
            town = args.data / f"{args.split}-{name}"
            if not town.is_dir():
                raise SystemExit(f"{town} is missing: run `make data-sensors`")
            seq = open_sequence(town)
            row: dict[str, Any] = {"rendering": town.name, "sensor": seq.sensor}
            for mode in INPUTS:
                inp = SensorInput(profile, get_sensor(seq.sensor), mode)  # type: ignore[arg-type]
                d, _ = describe(model, range_images(seq, profile, sensor=inp, progress=False))
                row[mode] = score(d, d_car, gt)
            rows.append(row)
        for beams in (int(b) for b in args.beams.split(",") if b):
            row = {"rendering": f"{car.root.name}, {beams} rings", "sensor": f"thinned-{beams}"}
            for mode in INPUTS:
                d, _ = describe(model, thinned_images(car, profile, beams, mode))
                row[mode] = score(d, d_car, gt)
            rows.append(row)
    mean = {m: float(np.mean([[r[m][k] for k in KEYS] for r in rows])) for m in INPUTS}
    write_report(
        out,
        {
            "model": str(args.model),
            "split": args.split,
            "car": car.root.name,
            "views": 1,
            "rows": rows,
            "mean": mean,
            "pick": max(INPUTS, key=lambda m: mean[m]),
            "seconds": round(time.perf_counter() - t0, 1),
        },
    )
    t = Table(title=f"{args.split}: elevation → elevation-lerp, descriptor alone, one view")
    for col in ("rendering", "own F1max / R@1", "against the car F1max / R@1", "cosine"):
        t.add_column(col)
    for r in rows:
        a, b = r["elevation"], r["elevation-lerp"]
        t.add_row(
            r["rendering"],
            f"{a['own_f1max']:.3f}/{a['own_recall@1']:.3f} → "
            f"{b['own_f1max']:.3f}/{b['own_recall@1']:.3f}",
            f"{a['car_f1max']:.3f}/{a['car_recall@1']:.3f} → "
            f"{b['car_f1max']:.3f}/{b['car_recall@1']:.3f}",
            f"{a['cosine_to_car']:.3f} → {b['cosine_to_car']:.3f}",
        )
    Console(width=120).print(t)
    print(f"mean of the four: {mean}; wrote {out}")


if __name__ == "__main__":
    main()
