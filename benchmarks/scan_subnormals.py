"""The C scan kernel with and without flushing subnormals to zero, on real scans, per
shipped model file, beside the portable graph (what the service falls back to).

The kernel flushes float32 subnormals to zero on its calling thread for the length of each
call (``overlapmamba/core/csrc/selective_scan.c``, FLUSH_BEGIN). Without it, on some x86
processors every multiply that reads or makes a subnormal costs a hundred cycles or more,
and the ring's correction makes them: it carries a state while any of its 8 lanes still
matters, and the fast-decaying lanes go subnormal meanwhile. On such a processor the kernel
became slower than the portable graph, and a server's load-time check (``scan_kernel =
"auto"``) served the portable graph instead.

For each file (default: every ``models/*.onnx`` that has a scan) and each real scan (KITTI
00, the HDL-64E of the model sensor; nuScenes scene 0061, an HDL-32E, projected as the
service projects it), interleaved in that order so that load on the machine hits all alike:
the CPU time of one scan's encode (its views, as served: one onnxruntime thread, one kernel
thread) by the kernel with the flush, without it, and by the portable graph; the kernel's
own share of each; the largest difference of descriptor and yaw features between the two
kernel runs; and which path the service picks at load (``Encoder``'s own timing).

    python benchmarks/scan_subnormals.py [--model FILE …] [--scans 20] [--repeats 2]

Writes reports/service/scan-subnormals.json (the processor is in its provenance: the effect
depends on it; on a processor without the penalty both kernel columns agree).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np
from bench_kit import model_record, served_input
from reports_kit import REPORTS, ROOT, shown_path, write_report
from rich.console import Console
from rich.table import Table

from overlapmamba.core import scan_kernel
from overlapmamba.core.datasets import open_sequence
from overlapmamba.service.encoder import INPUT, OUTPUTS, Encoder

SHARED = ROOT.parent / "shared" / "data"
SEQUENCES = {  # name → (folder, the sensor the service is told)
    "kitti00": (SHARED / "kitti00_0000-0100", None),
    "nuscenes-hdl32": (SHARED / "nuscenes_scene0061", "hdl32"),
}
WAYS = ("flush", "no flush", "portable")


def images(enc: Encoder, scans: int) -> dict[str, list[np.ndarray]]:
    """``scans`` scans of each real sequence (evenly spread) as the service gives them to
    the encoder: (1, V, H, W) images."""
    out: dict[str, list[np.ndarray]] = {}
    for name, (folder, sensor) in SEQUENCES.items():
        if not folder.is_dir():
            continue
        seq = open_sequence(folder)
        sensor_input = served_input(enc, sensor)
        picks = np.linspace(0, len(seq) - 1, min(scans, len(seq))).round().astype(int)
        out[name] = []
        for i in picks:
            img, _ = enc.project_offset(seq.points(int(i)), sensor_input)
            out[name].append(img[None])
    return out


def measure(path: Path, scans: int, repeats: int, console: Console) -> dict[str, Any] | None:
    kernel = Encoder(path, intra_op_threads=1, scan_kernel=True)
    if kernel.staged is None:
        console.print(f"{path.name}: no C-kernel path ({kernel.scan_path}); skipped")
        return None
    portable = Encoder(path, intra_op_threads=1, scan_kernel=False)
    lib = scan_kernel.load()
    batches = images(kernel, scans)
    cpu: dict[str, dict[str, list[float]]] = {s: {w: [] for w in WAYS} for s in batches}
    scan_part: dict[str, dict[str, list[float]]] = {s: {w: [] for w in WAYS[:2]} for s in batches}
    gap = 0.0
    staged = kernel.staged
    try:
        for rep in range(repeats + 1):  # the first round warms up and is not kept
            for seq, items in batches.items():
                for img in items:
                    outs = {}
                    for way in WAYS:
                        lib.scan_set_flush(int(way == "flush"))
                        enc = portable if way == "portable" else kernel
                        parts: dict[str, float] = {}
                        x = img.reshape(-1, 1, *img.shape[2:])
                        t0 = time.process_time()
                        if way == "portable":  # the same graph whole, as the service falls back
                            outs[way] = tuple(enc.session.run(list(OUTPUTS), {INPUT: x}))
                        else:
                            outs[way] = staged.run(x, parts)
                        spent = 1e3 * (time.process_time() - t0)
                        if rep:
                            cpu[seq][way].append(spent)
                            if way != "portable":
                                scan_part[seq][way].append(1e3 * parts["scan"])
                    gap = max(
                        gap,
                        *(
                            float(np.abs(a - b).max())
                            for a, b in zip(outs["flush"], outs["no flush"], strict=True)
                        ),
                    )
    finally:
        lib.scan_set_flush(1)
    served = Encoder(path, intra_op_threads=1)  # the load-time choice, with the flush
    record: dict[str, Any] = {
        **model_record(path, kernel),
        "served_at_load": served.scan_path,
        "max_abs_difference_flush_vs_not": gap,
        "sequences": {},
    }
    for seq in batches:
        row = {f"{w}_cpu_ms": float(np.median(cpu[seq][w])) for w in WAYS}
        row |= {f"{w}_scan_ms": float(np.median(scan_part[seq][w])) for w in WAYS[:2]}
        row["scans_timed"] = len(cpu[seq]["flush"])
        row["speedup_flush"] = row["no flush_cpu_ms"] / row["flush_cpu_ms"]
        row["kernel_vs_portable"] = row["flush_cpu_ms"] / row["portable_cpu_ms"]
        record["sequences"][seq] = row
    return record


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, action="append", help="default: every models/*.onnx")
    ap.add_argument("--scans", type=int, default=20, help="scans of each real sequence")
    ap.add_argument("--repeats", type=int, default=2, help="timed rounds over them")
    ap.add_argument("--out", type=Path, default=REPORTS / "service" / "scan-subnormals.json")
    args = ap.parse_args()
    if args.scans < 1 or args.repeats < 1:
        ap.error("--scans and --repeats must be at least 1")
    console = Console(width=140)
    try:
        lib = scan_kernel.load()
    except scan_kernel.KernelBuildError as err:
        raise SystemExit(f"the C scan kernel is not available here: {err}") from None
    if not lib.scan_flush_supported():
        raise SystemExit(
            "this processor's build does not flush subnormals (not x86): nothing to time"
        )
    models = args.model or sorted((ROOT / "models").glob("*.onnx"))
    t0 = time.perf_counter()
    rows = [r for m in models if (r := measure(m, args.scans, args.repeats, console))]
    table = Table(title="CPU ms a scan (median; one onnxruntime thread, one kernel thread)")
    for col in ("model", "scans", "flush", "no flush", "portable", "scan part", "at load"):
        table.add_column(col)
    for r in rows:
        for seq, s in r["sequences"].items():
            table.add_row(
                Path(r["model"]).stem,
                seq,
                f"{s['flush_cpu_ms']:.1f}",
                f"{s['no flush_cpu_ms']:.1f}",
                f"{s['portable_cpu_ms']:.1f}",
                f"{s['flush_scan_ms']:.1f} / {s['no flush_scan_ms']:.1f}",
                r["served_at_load"].split(" (")[0],
            )
    console.print(table)
    record = {
        "processor": scan_kernel.processor(),
        "models": [shown_path(Path(r["model"])) for r in rows],
        "sequences": {k: shown_path(v[0]) for k, v in SEQUENCES.items() if v[0].is_dir()},
        "files": rows,
        "seconds": round(time.perf_counter() - t0, 1),
    }
    write_report(args.out, record)
    console.print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
