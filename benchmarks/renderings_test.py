"""Checkpoints scored across sensors on the sensor test town, as the trainer scores ``val``.

Training validates every epoch on the sensor validation drive and its renderings by other
sensors (``overlapmamba.train.valsensors``: each rendering's own loop closure, and its queries
against the drive's scans: a map made by the model's sensor, queried by another). This scores
checkpoints the same way on the sensor *test* town (``test-kitti-hdl64`` and its renderings
by the VLP-16, OS0-128, XT32 and OS1-128, every one on a car): reported, never chosen on.
Each checkpoint takes the renderings by its own input (its config's ``sensor_input``), one
view a scan, with the selection score the trainer would give it.

    python benchmarks/renderings_test.py runs/NAME/best.pt … --out reports/model/NAME-test.json
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from reports_kit import REPORTS, ROOT, write_report

from overlapmamba.core.datasets import open_sequence
from overlapmamba.train.checkpoint import load_model, sensor_input_of
from overlapmamba.train.evaluate import describe, loop_closure, sequence_loops, summary
from overlapmamba.train.rangecache import range_images
from overlapmamba.train.train_inputs import training_input
from overlapmamba.train.valsensors import open_renderings, selection_score, validate_renderings

DRIVE = "data/synth/test-kitti-hdl64"
RENDERINGS = tuple(f"data/synth/test-{s}" for s in ("vlp16", "os0-128", "xt32", "os1-128"))


def score(checkpoint: Path, drive: str, renderings: list[str]) -> dict[str, Any]:
    """``checkpoint`` on ``drive`` and its ``renderings``: the trainer's validation fields."""
    model, profile, ckpt = load_model(checkpoint)
    mode = sensor_input_of(model)
    seq = open_sequence(ROOT / drive)
    images = range_images(seq, profile, sensor=training_input(profile, seq, mode))
    gt = sequence_loops(seq, profile)
    desc, _ = describe(model, images)
    val = summary(loop_closure(desc, gt))
    opened = open_renderings([str(ROOT / r) for r in renderings], seq, profile, False, mode)
    sensors = validate_renderings(model, opened, desc, gt, "cpu")
    return {
        "checkpoint": str(checkpoint),
        "sensor_input": mode,
        "epoch": ckpt.get("train", {}).get("epochs_done"),
        "drive": {k: {m: v[m] for m in ("f1max", "recall@1")} for k, v in val.items()},
        "renderings": {
            name: {
                way: {k: {m: v[m] for m in ("f1max", "recall@1")} for k, v in s[way].items()}
                for way in ("own", "cross")
            }
            for name, s in sensors.items()
        },
        "score": selection_score(val, sensors),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoints", type=Path, nargs="+")
    ap.add_argument("--drive", default=DRIVE)
    ap.add_argument("--renderings", nargs="+", default=list(RENDERINGS))
    ap.add_argument("--out", type=Path, default=REPORTS / "model" / "renderings-test.json")
    args = ap.parse_args()
    t0 = time.perf_counter()
    rows = []
    for ckpt in args.checkpoints:
        rows.append(score(ckpt, args.drive, args.renderings))
        r = rows[-1]
        cross = " ".join(
            f"{n} {v['cross']['all']['f1max']:.3f}" for n, v in r["renderings"].items()
        )
        print(f"{ckpt}: score {r['score']:.3f}, drive {r['drive']['all']['f1max']:.3f}; {cross}")
    record = {
        "drive": args.drive,
        "renderings": args.renderings,
        "checkpoints": rows,
        "seconds": round(time.perf_counter() - t0, 1),
    }
    write_report(args.out, record)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
