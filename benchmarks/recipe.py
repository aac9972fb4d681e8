"""Recipe experiments: one short training run per call, its validation and health per epoch,
appended as a JSON line (default reports/model/recipe.jsonl).

    python benchmarks/recipe.py NAME '{"train": {...}, "model": {...}}' \
        --data DIR [--data DIR …] --val DIR

Defaults: the narrow network of the recipe measurements (d_model 64, convLast2 256, 32
clusters), 3 epochs of 640 scans in batches of 16 (120 steps), epoch 0 with batch norm
recalibrated, the per-epoch turn check on ../shared/data's KITTI 00 scans. The spec's
``train`` and ``model`` dicts override TrainConfig and OverlapMambaConfig fields. The tables
in the README (Training: choosing the recipe) came from the tiny and tiny-val towns
(``gen-data DIR --preset tiny`` and ``--preset tiny-val``).
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

from reports_kit import REPORTS, provenance

from overlapmamba.train.model import OverlapMambaConfig
from overlapmamba.train.train import TrainConfig, train

ROOT = Path(__file__).resolve().parents[1]
NARROW = {"d_model": 64, "conv_last2": 256, "clusters": 32}
BASE = {"epochs": 3, "epoch_scans": 640, "batch_size": 16}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("name")
    ap.add_argument("spec", help='JSON: {"train": {...}, "model": {...}}')
    ap.add_argument("--data", type=Path, action="append", required=True)
    ap.add_argument("--val", type=Path, required=True)
    ap.add_argument("--out", type=Path, default=REPORTS / "model" / "recipe.jsonl")
    args = ap.parse_args()
    spec = json.loads(args.spec)
    model = OverlapMambaConfig(**{**NARROW, **spec.get("model", {})})
    cfg = TrainConfig(**{**BASE, **spec.get("train", {})})
    run = Path(tempfile.mkdtemp(prefix=f"recipe-{args.name}-"))
    t = time.time()
    try:
        history = train(args.data, args.val, run / "run", model, cfg, progress=False)
    finally:
        shutil.rmtree(run, ignore_errors=True)
    rows = []
    for h in history:
        v, health = h["val"], h.get("health") or {}
        rows.append(
            {
                "epoch": h["epoch"],
                "f1max": v["all"]["f1max"],
                "f1max_same": v["same"]["f1max"],
                "f1max_reverse": v["reverse"]["f1max"],
                "recall@1": v["all"]["recall@1"],
                **{k: health.get(k) for k in ("d_pos", "d_neg", "separation", "spread", "active")},
                "turned_over_1m_step": (h.get("real") or {}).get("turned_over_one_metre_step"),
                "train_s": h.get("train_s"),
                "data_s": h.get("data_s"),
            }
        )
    record = {
        **provenance(),
        "name": args.name,
        "spec": spec,
        "wall_s": time.time() - t,
        "epochs": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with args.out.open("a") as f:
        f.write(json.dumps(record) + "\n")
    for r in rows:
        print(
            f"{args.name} epoch {r['epoch']}: F1max {r['f1max']:.3f} (reverse "
            f"{r['f1max_reverse']:.3f}), R@1 {r['recall@1']:.3f}, spread {r['spread'] or 0:.4f}, "
            f"turned/1 m {r['turned_over_1m_step'] or float('nan'):.2f}"
        )


if __name__ == "__main__":
    main()
