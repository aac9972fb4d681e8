"""What the shipped model's sub-column views cost (overlapmamba.core.views): a scan described as the
service describes it (``Encoder.project`` + ``Encoder.encode``), with the model's views and
with one, on real KITTI 00 scans.

The one-view model is the same graph written with ``views = 1``
(``overlapmamba.train.modelfile.with_views``: the file the model id ``om-ef2469f958d5098b`` names),
so the two differ only in how many projections a scan makes and how many graph rows the encoder
runs. Timed interleaved (one view, then the model's, rep after rep) in one process, with 1 and 2
onnxruntime threads, one scan per call and 8 scans per call (per scan), so that the ratio holds on a
shared machine even when the absolute times drift. Also reported: the project stage alone.

Writes JSON (default reports/service/views.json).
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from reports_kit import REPORTS, write_report
from rich.console import Console
from rich.table import Table

from overlapmamba.core.io import read_points
from overlapmamba.service.encoder import Encoder
from overlapmamba.train.modelfile import with_views

ROOT = Path(__file__).resolve().parents[1]
KITTI = ROOT.parent / "shared" / "data" / "kitti00_0000-0100" / "velodyne"


def interleaved(
    fns: dict[str, Callable[[int], object]], reps: int, per: int
) -> dict[str, dict[str, float]]:
    """Median and p90 ms per scan of each function, called in turn ``reps`` times each
    (``per`` scans a call), after one warm-up call each."""
    for fn in fns.values():
        fn(0)
    times: dict[str, list[float]] = {k: [] for k in fns}
    for i in range(reps):
        for key, fn in fns.items():
            t0 = time.perf_counter()
            fn(i)
            times[key].append((time.perf_counter() - t0) / per * 1e3)
    return {
        k: {"median_ms": float(np.median(v)), "p90_ms": float(np.percentile(v, 90))}
        for k, v in times.items()
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, default=ROOT / "models" / "overlapmamba-hdl64.onnx")
    ap.add_argument("--reps", type=int, default=40, help="timed calls per setting and model")
    ap.add_argument("--out", type=Path, default=REPORTS / "service" / "views.json")
    args = ap.parse_args()
    console = Console()
    if not KITTI.is_dir():
        raise SystemExit(f"{KITTI} is missing: the real scans are needed")
    clouds = [read_points(p) for p in sorted(KITTI.glob("*.bin"))[:16]]

    with tempfile.TemporaryDirectory() as tmp:
        one_path = Path(tmp) / "one-view.onnx"
        with_views(args.model, one_path, 1)
        rows = []
        for threads in (1, 2):
            models = {
                "one view": Encoder(one_path, intra_op_threads=threads),
                "shipped": Encoder(args.model, intra_op_threads=threads),
            }
            views = models["shipped"].views
            for per in (1, 8):

                def call(enc: Encoder, per: int = per) -> Callable[[int], object]:
                    def run(i: int) -> object:
                        batch = [clouds[(i * per + j) % len(clouds)] for j in range(per)]
                        return enc.encode(np.stack([enc.project(c) for c in batch]))

                    return run

                got = interleaved({k: call(e) for k, e in models.items()}, args.reps, per)
                rows.append({"threads": threads, "scans_per_call": per, **got})
            project = interleaved(
                {k: (lambda i, e=e: e.project(clouds[i % len(clouds)])) for k, e in models.items()},
                args.reps,
                1,
            )
            rows.append({"threads": threads, "stage": "project", **project})

    result = {
        "machine": {
            "platform": platform.platform(),
            "cores": os.cpu_count(),
            "python": platform.python_version(),
        },
        "model": str(args.model),
        "views": views,
        "scans": "KITTI 00 frames 0–15",
        "reps": args.reps,
        "rows": rows,
    }
    write_report(args.out, result)

    t = Table(title=f"a scan described as the service does it: one view against {views}")
    for col in ("threads", "what", "one view, ms/scan (p90)", f"{views} views", "ratio"):
        t.add_column(col, justify="right")
    for r in rows:
        what = r.get("stage") or f"project + encode, {r['scans_per_call']} a call"
        a, b = r["one view"], r["shipped"]
        t.add_row(
            str(r["threads"]),
            what,
            f"{a['median_ms']:.1f} ({a['p90_ms']:.1f})",
            f"{b['median_ms']:.1f} ({b['p90_ms']:.1f})",
            f"{b['median_ms'] / a['median_ms']:.2f}",
        )
    console.print(t)
    console.print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
