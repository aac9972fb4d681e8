"""Training throughput: scans/s of one training step (forward, ImTrihard, backward, Adam).

The reference configuration (18.1 M parameters, three scan directions, convLast2 1024,
64 NetVLAD clusters) at batch 16, on real KITTI range images when ../shared/data is present
(else seeded random ones: the speed does not depend on the content), with each scan backend
in the same run so their ratio is fair. Prints a table and writes JSON
(default reports/model/training.json).

Each backend is timed with the convolutions' weights channels-last (what ``overlapmamba
train`` runs: ``overlapmamba.train.model.channels_last``) and, for the ratio, in PyTorch's
default layout (``--layouts``), in the same run.

``--width narrow`` times the shipped width instead (``overlapmamba.train.presets.NARROW``), and
``--device cuda`` a GPU (the ``chunked`` backend: the C kernel is the CPU's), synchronising
before each step's clock stops.

Goal: one epoch of 2,000 scans in ≤ 600 s on 2 CPU cores, i.e. ≥ 3.33 scans/s.
Goal: the data side (the full augmentation set, ROBUST, on a batch) under 10 % of a
step;
the table's last row times it on the same batch, in the same run.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch
from reports_kit import REPORTS, write_report

from overlapmamba.core.sensors import get_profile
from overlapmamba.train.augment import ROBUST, AugmentConfig, Augmenter
from overlapmamba.train.losses import batch_hard_imtrihard
from overlapmamba.train.model import OverlapMamba, OverlapMambaConfig, channels_last
from overlapmamba.train.presets import NARROW
from overlapmamba.train.runtime import reexec_with_hugepages

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "kitti00_0000-0100"


def images(n: int) -> tuple[torch.Tensor, str]:
    profile = get_profile("kitti-hdl64")
    if (REAL / "velodyne").is_dir():
        from overlapmamba.core.io import read_points
        from overlapmamba.core.projection import project

        paths = sorted((REAL / "velodyne").glob("*.bin"))[:n]
        x = np.stack([project(read_points(p), profile) for p in paths])
        return torch.from_numpy(x)[:, None], f"real KITTI 00 frames 0–{n - 1}"
    g = torch.Generator().manual_seed(0)
    return torch.rand(n, 1, profile.height, profile.width, generator=g) * 50, "random images"


WIDTHS = {"reference": {}, "narrow": NARROW}
LAYOUTS = ("channels-last", "contiguous")


def step_times(
    backend: str,
    x: torch.Tensor,
    steps: int,
    width: str = "reference",
    device: str = "cpu",
    layout: str = "channels-last",
) -> np.ndarray:
    torch.manual_seed(0)
    cfg = OverlapMambaConfig(**WIDTHS[width], scan_backend=backend)
    model = OverlapMamba(cfg).to(device).train()
    if layout == "channels-last":
        model = channels_last(model)
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)
    B = len(x)
    x = x.to(device)
    # Four groups of four: each group overlaps within itself.
    overlap = torch.block_diag(*[torch.full((4, 4), 0.8)] * (B // 4)).to(device)
    sync = torch.cuda.synchronize if x.device.type == "cuda" else lambda: None
    out = []
    for i in range(steps + 1):  # the first step warms up (allocations, kernel build)
        t = time.perf_counter()
        desc, _ = model(x)
        loss = batch_hard_imtrihard(desc, overlap).value
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sync()
        if i:
            out.append(time.perf_counter() - t)
    return np.array(out)


def main() -> None:
    reexec_with_hugepages()  # as `overlapmamba train` does; OVERLAPMAMBA_NO_REEXEC=1 opts out
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--backends", nargs="+", default=None, help="default: fused chunked (CPU)")
    ap.add_argument("--width", choices=sorted(WIDTHS), default="reference")
    ap.add_argument(
        "--layouts",
        nargs="+",
        choices=LAYOUTS,
        default=list(LAYOUTS),
        help="the convolutions' weight layouts to time (the first is what training runs)",
    )
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    ap.add_argument("--json", type=Path, default=REPORTS / "model" / "training.json")
    args = ap.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        ap.error("--device cuda: no CUDA device is visible to PyTorch here")
    if args.backends is None:
        args.backends = ["chunked"] if args.device == "cuda" else ["fused", "chunked"]
    if args.device == "cuda" and "fused" in args.backends:
        ap.error("--device cuda: the fused backend is a CPU kernel; use chunked")
    torch.set_num_threads(args.threads)
    x, source = images(args.batch)
    rows = []
    for backend in args.backends:
        for layout in args.layouts:
            t = step_times(backend, x, args.steps, args.width, args.device, layout)
            med = float(np.median(t))
            rows.append(
                {
                    "backend": backend,
                    "layout": layout,
                    "step_median_s": med,
                    "step_p90_s": float(np.percentile(t, 90)),
                    "scans_per_s": args.batch / med,
                    "epoch_2000_scans_s": 2000 * med / args.batch,
                }
            )
    base = rows[0]["scans_per_s"]
    augment = Augmenter(AugmentConfig(**ROBUST), get_profile("kitti-hdl64"), circular=True)
    rng = np.random.default_rng(0)
    batch = x[:, 0].numpy()
    aug = []
    for _ in range(args.steps + 1):
        t0 = time.perf_counter()
        augment(batch, rng)
        aug.append(time.perf_counter() - t0)
    aug_s = float(np.median(aug[1:]))
    augment_row = {
        "augment_median_s": aug_s,
        "share_of_first_backend_step": aug_s / rows[0]["step_median_s"],
    }
    print(
        f"Training step, {args.width} config, batch {args.batch}, {args.device}, "
        f"{args.threads} threads, {source}, "
        f"GLIBC_TUNABLES={os.environ.get('GLIBC_TUNABLES', '') or 'unset'}"
    )
    print(
        f"{'scan backend':<14}{'layout':<15}{'step (median)':>15}{'p90':>9}{'scans/s':>10}"
        f"{'2,000-scan epoch':>18}{'vs first':>10}"
    )
    for r in rows:
        print(
            f"{r['backend']:<14}{r['layout']:<15}"
            f"{r['step_median_s']:>13.2f} s{r['step_p90_s']:>7.2f} s"
            f"{r['scans_per_s']:>10.2f}{r['epoch_2000_scans_s']:>16.0f} s"
            f"{r['scans_per_s'] / base:>9.2f}×"
        )
    print(
        f"{'augmentation':<29}{aug_s * 1000:>12.1f} ms   (the ROBUST set, on the batch above: "
        f"{augment_row['share_of_first_backend_step']:.1%} of a {rows[0]['backend']} step)"
    )
    args.json.parent.mkdir(parents=True, exist_ok=True)
    record = {
        "benchmark": "training-step",
        "source": source,
        "batch": args.batch,
        "width": args.width,
        "device": torch.cuda.get_device_name(0) if args.device == "cuda" else "cpu",
        "threads": args.threads,
        "steps": args.steps,
        "machine": {"platform": platform.platform(), "processor": platform.processor()},
        "torch": torch.__version__,
        "glibc_tunables": os.environ.get("GLIBC_TUNABLES", ""),
        "goal_scans_per_s": 2000 / 600,
        "rows": rows,
        "augmentation": augment_row,
    }
    write_report(args.json, record)
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
