"""Describing scans in PyTorch: the plain layout against the channels-last copy ``describe``
runs (validation every epoch, ``eval``, the report, the benchmarks all describe this way).

For three widths of OverlapMamba (the tests' small network, ``narrow`` as shipped, the
reference configuration), untrained (seed 0: the cost does not depend on the weights), it
describes ``--scans`` random HDL-64E-sized range images two ways, alternating ``--repeats``
times so both meet the same machine:

- ``plain``: batches of 8 through the network as constructed (contiguous weights and input);
- ``channels_last``: :func:`overlapmamba.train.evaluate.describe` as shipped.

It reports the median seconds a scan each way, their ratio, and the largest difference
between the two ways' descriptors and yaw features. Writes
reports/model/describe-layout.json.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import torch
from reports_kit import REPORTS, write_report

from overlapmamba.train.evaluate import describe
from overlapmamba.train.model import OverlapMamba, OverlapMambaConfig
from overlapmamba.train.presets import NARROW

WIDTHS = {
    # tests/conftest.py's SMALL_MODEL (the tests are not a package this can import)
    "small (tests)": dict(d_model=32, d_state=4, dt_rank=4, conv_last2=48, clusters=6, out_dim=32),
    "narrow (shipped)": NARROW,
    "reference": {},
}


@torch.no_grad()
def plain(model: OverlapMamba, images: np.ndarray, batch: int = 8) -> tuple[np.ndarray, ...]:
    """The same batches as ``describe``, through the network as it is."""
    model.eval()
    d, y = zip(
        *(
            model(torch.from_numpy(images[s : s + batch, None]))
            for s in range(0, len(images), batch)
        ),
        strict=True,
    )
    return torch.cat(d).numpy(), torch.cat(y).numpy()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scans", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", type=Path, default=REPORTS / "model" / "describe-layout.json")
    args = ap.parse_args()
    if args.scans < 1 or args.repeats < 1:
        ap.error("--scans and --repeats must be at least 1")
    rng = np.random.default_rng(0)
    images = rng.uniform(0, 80, (args.scans, 64, 900)).astype(np.float32)
    rows = {}
    for name, width in WIDTHS.items():
        torch.manual_seed(0)
        model = OverlapMamba(OverlapMambaConfig(**width))
        ways = {
            "plain": lambda m=model: plain(m, images),
            "channels_last": lambda m=model: describe(m, images),
        }
        out = {k: f() for k, f in ways.items()}  # warm-up, and the outputs compared
        times: dict[str, list[float]] = {k: [] for k in ways}
        for _ in range(args.repeats):
            for k, f in ways.items():
                t = time.perf_counter()
                f()
                times[k].append((time.perf_counter() - t) / args.scans)
        med = {k: statistics.median(v) for k, v in times.items()}
        rows[name] = {
            "config": width,
            "seconds_a_scan": med,
            "channels_last_over_plain": med["channels_last"] / med["plain"],
            "max_abs_difference": {
                "descriptor": float(np.abs(out["plain"][0] - out["channels_last"][0]).max()),
                "yaw_features": float(np.abs(out["plain"][1] - out["channels_last"][1]).max()),
            },
        }
        print(
            f"{name:18s} plain {1e3 * med['plain']:.1f} ms  channels-last "
            f"{1e3 * med['channels_last']:.1f} ms a scan"
        )
    write_report(
        args.json,
        {
            "benchmark": "describe_layout",
            "scans": args.scans,
            "repeats": args.repeats,
            "threads": torch.get_num_threads(),
            "widths": rows,
        },
    )


if __name__ == "__main__":
    main()
