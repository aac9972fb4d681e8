"""A training run's epochs as a report: what its ``metrics.json`` holds per epoch, without
the step losses and health log (a run folder is not committed; this is).

    python benchmarks/run_summary.py runs/common-towns [--out reports/model/common-towns.json]

Per epoch: the validation town (F1max, Recall@1; all, same-direction and reverse revisits),
each validation rendering by another sensor (its own loops, and against the validation
scans: ``overlapmamba.train.valsensors``), the selection score, the health numbers (d(q,p),
d(q,n), spread, active share, the collapse flag), the real-scan turn check, the seconds
spent (recalibrating, mining, training, validating), and how many of the planned epochs ran.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from reports_kit import REPORTS, write_report

from overlapmamba.train.valsensors import selection_score


def _fr(x: dict[str, Any]) -> dict[str, float]:
    return {"f1max": x["f1max"], "recall@1": x["recall@1"]}


def epoch_row(e: dict[str, Any]) -> dict[str, Any]:
    health = e.get("health") or {}
    sensors = e.get("val_sensors") or {}
    return {
        "epoch": e["epoch"],
        "val": {k: _fr(e["val"][k]) for k in ("all", "same", "reverse") if k in e["val"]},
        "val_sensors": {
            name: {"own": _fr(v["own"]["all"]), "cross": _fr(v["cross"]["all"])}
            for name, v in sensors.items()
        },
        "score": selection_score(e["val"], sensors or None),
        "health": {k: health.get(k) for k in ("d_pos", "d_neg", "spread", "separation", "active")},
        "collapsing": e.get("collapsing"),
        "real_cosine_min": (e.get("real") or {}).get("cosine_min"),
        "lr": e.get("lr"),
        "seconds": seconds(e),
    }


def seconds(e: dict[str, Any]) -> dict[str, float]:
    """Where an epoch's time went, as its metrics record it: batch-norm recalibration (epoch
    0), mining hard negatives, the training steps (data included) and validation."""
    mining = e.get("mining") or {}
    parts = {
        "calibrate": e.get("calibrate_s"),
        "mine": mining.get("mine_s"),
        "train": e.get("train_s"),
        "validate": e.get("val_s"),
    }
    return {k: float(v) for k, v in parts.items() if v is not None}


def summary(run: Path) -> dict[str, Any]:
    m = json.loads((run / "metrics.json").read_text())
    return {
        "run": str(run),
        "model_config": m["model_config"],
        "train_config": m["train_config"],
        "epochs_planned": m["train_config"]["epochs"],
        "epochs_run": max(e["epoch"] for e in m["history"]),
        "best": m["best"],
        "epochs": [epoch_row(e) for e in m["history"]],
        "seconds": sum(sum(seconds(e).values()) for e in m["history"]),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a run folder (its metrics.json)")
    ap.add_argument("--out", type=Path, default=None, help="default reports/model/RUN.json")
    ap.add_argument(
        "--trained-on",
        default="",
        help="where the run trained when not on this machine (e.g. a lent GPU's "
        "benchmarks/lent_gpu.py prepare.json: the machine and the towns simulated there)",
    )
    args = ap.parse_args()
    out = args.out or REPORTS / "model" / f"{args.run.name}.json"
    record = summary(args.run)
    if args.trained_on:
        path = Path(args.trained_on)
        record["trained_on"] = json.loads(path.read_text()) if path.is_file() else args.trained_on
    write_report(out, record)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
