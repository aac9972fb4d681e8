"""A declared mount against none: scans from a robot's, an AMR's and a backpack's sensor,
described as the service takes them today and after levelling them and moving them to the
model's height (``overlapmamba.core.sensors.mount``).

The towns are renderings of one drive (``make data-sensors``; for ``--split val`` the
``val-*`` renderings, ``gen-data data/synth/val-vlp16-robot --preset val-kitti-hdl64 --sensor
vlp16 --mount robot --no-ground-truth`` and so on): the model sensor's car rendering
(``SPLIT-kitti-hdl64``, its loop table labelling every rendering: frame i is the same place
in each) and each mounted rendering. Per mounted rendering, the descriptor alone, F1max /
Recall@1 under the loop-closure protocol:

- ``own``: its queries against its own earlier scans (a fleet of that platform alone);
- ``against the car``: its queries against the car's earlier scans (a map made by the
  model's sensor on a car, queried from the platform).

Each without a mount (as the service takes a scan that names only its sensor) and with the
mount its manifest records (height, pitch, roll), as a robot would declare it.

    python benchmarks/mounts.py [--model models/overlapmamba-hdl64.onnx] [--split test]

Writes reports/model/mounts-SPLIT.json. ≈ 3 min on 2 cores.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from bench_kit import car_rendering
from reports_kit import REPORTS, ROOT, write_report
from rich.console import Console
from rich.table import Table

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.sensors.catalogue import CATALOGUE
from overlapmamba.core.sensors.input import SensorInput
from overlapmamba.core.sensors.mount import Mount
from overlapmamba.synth.mounting import get_mounting
from overlapmamba.train.evaluate import (
    cross_loop_closure,
    describe,
    loop_closure,
    summary,
)
from overlapmamba.train.rangecache import range_images

MOUNTED = ("vlp16-robot", "os0-128-amr", "xt32-backpack")


def manifest_mount(town: Path) -> tuple[str, Mount]:
    """The sensor and the mount a rendering's manifest records."""
    cfg = json.loads((town / "manifest.json").read_text())["config"]
    m = get_mounting(cfg["mount"]).with_pose(
        cfg.get("mount_height"), cfg.get("mount_pitch_deg"), cfg.get("mount_roll_deg")
    )
    return cfg["sensor"], Mount(height=m.height, pitch_deg=m.pitch_deg, roll_deg=m.roll_deg)


def _fr(m: dict[str, Any]) -> dict[str, float]:
    return {"f1max": m["all"]["f1max"], "recall@1": m["all"]["recall@1"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, default=ROOT / "models" / "overlapmamba-hdl64.onnx")
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "synth")
    ap.add_argument("--split", choices=("val", "test"), default="test")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    out = args.out or REPORTS / "model" / f"mounts-{args.split}.json"
    with car_rendering(args.model, args.data, args.split) as cr:
        model, profile, gt, d_car = cr.model, cr.profile, cr.gt, cr.d_car
        rows = []
        for name in MOUNTED:
            town = args.data / f"{args.split}-{name}"
            if not town.is_dir():
                continue
            sensor, mount = manifest_mount(town)
            seq = open_sequence(town)
            row: dict[str, Any] = {"town": town.name, "sensor": sensor, "mount": mount.key()}
            for label, declared in (("none", None), ("declared", mount)):
                inp = SensorInput(profile, CATALOGUE[sensor], "elevation", declared)
                images = range_images(seq, profile, sensor=inp, progress=False)
                d, _ = describe(model, images)
                row[label] = {
                    "own": _fr(summary(loop_closure(d, gt))),
                    "against_car": _fr(cross_loop_closure(d, d_car, gt)),
                    "cosine_to_car": float((d * d_car).sum(1).mean()),
                }
            rows.append(row)
    write_report(
        out,
        {"model": str(args.model), "split": args.split, "car": cr.car.root.name, "rows": rows},
    )
    t = Table(title=f"mounted renderings of the {args.split} drive, descriptor alone")
    for col in ("town", "mount", "own: none → declared", "against the car: none → declared"):
        t.add_column(col)
    for r in rows:
        cells = []
        for k in ("own", "against_car"):
            a, b = r["none"][k], r["declared"][k]
            cells.append(
                f"{a['f1max']:.3f}/{a['recall@1']:.3f} → {b['f1max']:.3f}/{b['recall@1']:.3f}"
            )
        t.add_row(r["town"], json.dumps(r["mount"]), *cells)
    Console().print(t)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
