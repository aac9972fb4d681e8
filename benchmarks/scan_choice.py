"""Which way of running the selective scan the service picks when it loads a model, and
what each way costs where the service runs it.

A model file runs two ways (:mod:`overlapmamba.service.encoder`): the portable graph
(onnxruntime runs the scan's loops) and the C-kernel path (the graph cut at its scans, the
kernel the model was trained with between the cuts). With ``scan_kernel = auto`` (the
default) the encoder times both at load and serves with the kernel unless it costs more.
For each model file (default: the shipped file and its one-view twin), at the service's
default onnxruntime threads a call (``batching``: every core before encoder lanes, one a
lane since 2026-12-01, with a lane a core):

- ``loads``: the file loaded ``--loads`` times as the service loads it: how often each path
  was picked, with the timing each load logged;
- ``cost``: both paths of one load timed in blocks (a warm run, then ``--reps`` calls back
  to back, a pause between blocks so that one path's idle onnxruntime workers, which spin
  for a while after a run, do not run into the other's block), per scan: wall time and the
  process's CPU time, at one scan a call (its views) and eight (a full micro-batch,
  ``batching.max_batch``). Under a fleet's load the CPU time is what bounds throughput.

Real KITTI 00 scans (frames 0–7) where ../shared/data has them, else the load-time check's
fixed images.

    python benchmarks/scan_choice.py [--model FILE ...] [--loads 10] [--reps 10]

Writes reports/service/scan-choice.json (under a minute on 2 cores).
"""

from __future__ import annotations

import argparse
import logging
import time
from collections import Counter
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from bench_kit import REAL as KITTI
from reports_kit import REPORTS, ROOT, shown_path, write_report

from overlapmamba.service.encoder import Encoder, parity_image
from overlapmamba.service.settings import BatchSettings
from overlapmamba.service.threads import encoder_threads

MODELS = [ROOT / "models" / "overlapmamba-hdl64.onnx"]
MODELS.append(ROOT / "models" / "overlapmamba-hdl64-one-view.onnx")
# onnxruntime threads a call, as the service runs its encoder by default
THREADS = encoder_threads(BatchSettings().lanes, BatchSettings().intra_op_threads)[1]
PAUSE_S = 0.05  # between blocks: longer than onnxruntime's workers spin after a run


def scans(enc: Encoder, n: int) -> tuple[np.ndarray, str]:
    """(n · V, 1, H, W): n scans' V views each, as the encoder hands its graph them."""
    if (KITTI / "velodyne").is_dir():
        from overlapmamba.core.datasets import open_sequence

        seq = open_sequence(KITTI)
        images = np.stack([enc.project_offset(seq.points(i))[0] for i in range(n)])
        source = f"real KITTI 00 frames 0–{n - 1}"
    else:
        images = np.stack([parity_image(enc.meta)[0]] * enc.meta.views * n)
        source = "the load-time check's fixed images"
    p = enc.meta.profile
    return np.ascontiguousarray(images.reshape(-1, 1, p.height, p.width)), source


def block(fn: Callable[[], object], reps: int, per_call: int) -> dict[str, float]:
    """One warm call, then ``reps`` calls back to back: ms a scan of wall time and of the
    process's CPU time (every thread)."""
    fn()
    c0, w0 = time.process_time(), time.perf_counter()
    for _ in range(reps):
        fn()
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    time.sleep(PAUSE_S)
    return {"wall_ms": 1e3 * wall / reps / per_call, "cpu_ms": 1e3 * cpu / reps / per_call}


def measure(path: Path, loads: int, reps: int) -> dict[str, Any]:
    picked: Counter[str] = Counter()
    lines = []
    for _ in range(loads):
        enc = Encoder(path, intra_op_threads=THREADS)
        picked["c-kernel" if enc.staged is not None else "portable"] += 1
        lines.append(enc.scan_path)
    enc = Encoder(path, intra_op_threads=THREADS, scan_kernel=True)
    if enc.staged is None:
        raise SystemExit(f"{path}: the C-kernel path does not build here: {enc.scan_path}")
    cost: dict[str, Any] = {}
    for n in (1, 8):
        x, source = scans(enc, n)
        ways = {"c-kernel": partial(enc.staged.run, x), "portable": partial(enc._run_portable, x)}
        runs = max(2, reps // n)
        rows: dict[str, list[dict[str, float]]] = {w: [] for w in ways}
        time.sleep(PAUSE_S)
        for order in (("c-kernel", "portable"), ("portable", "c-kernel")):
            for way in order:
                rows[way].append(block(ways[way], runs, n))
        cost[f"{n}_scans_a_call"] = {
            way: {k: float(np.mean([r[k] for r in got])) for k in ("wall_ms", "cpu_ms")}
            for way, got in rows.items()
        }
        cost["images"] = source
    return {
        "model_id": enc.model_id,
        "views": enc.views,
        "loads": {"picked": dict(picked), "logged": lines},
        "cost": cost,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, action="append", help="default: the shipped files")
    ap.add_argument("--loads", type=int, default=10, help="loads of each file (auto choice)")
    ap.add_argument("--reps", type=int, default=10, help="calls a block at one scan a call")
    ap.add_argument("--out", type=Path, default=REPORTS / "service" / "scan-choice.json")
    args = ap.parse_args()
    logging.disable(logging.WARNING)  # each load's choice is recorded, not logged
    t0 = time.perf_counter()
    models = {shown_path(m): measure(m, args.loads, args.reps) for m in args.model or MODELS}
    for name, got in models.items():
        print(f"{name}: picked {got['loads']['picked']}")
        for n in ("1_scans_a_call", "8_scans_a_call"):
            row = got["cost"][n]
            print(
                f"  {n}: "
                + "; ".join(
                    f"{w} {v['wall_ms']:.1f} ms wall, {v['cpu_ms']:.1f} ms CPU a scan"
                    for w, v in row.items()
                )
            )
    write_report(
        args.out,
        {"threads": f"{THREADS} onnxruntime thread(s) a call (the service's default)"}
        | {"models": models}
        | {"seconds": time.perf_counter() - t0},
    )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
