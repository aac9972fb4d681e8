"""Table V analogue: descriptor extraction and search time on CPU, at 1k and 10k database
frames, for Scan Context, the OT-style network and OverlapMamba.

- **Extraction** (per scan, B = 1, median of ``--reps``): Scan Context from the points;
  the networks from the points too: projection to the 64 × 900 range image, then the
  forward pass. Networks run in PyTorch eager (random weights: the time does not depend on
  them); OverlapMamba also as the shipped ONNX file in onnxruntime when it is present.
- **Search** (per query, top-1 of a database of N frames, median over ``--queries``):
  256-d descriptors by exact inner product in numpy and, when faiss is installed, in a
  ``faiss.IndexFlatIP`` (what the service uses); Scan Context by its two stages, ring-key
  nearest neighbours (10) then the column-shift distance to each.

Databases are real scans' descriptors/contexts tiled with small noise up to N (search time
does not depend on the content). Scans: KITTI 00 from ../shared/data when present, else the
synthetic test preset. Threads: 2 for PyTorch and onnxruntime (``--threads``). Prints a
table and writes JSON (default reports/model/place_recognition.json).
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from reports_kit import REPORTS, write_report
from rich.console import Console
from rich.table import Table

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.projection import project
from overlapmamba.core.scancontext import ScanContextParams, match, ring_key, scan_context
from overlapmamba.core.sensors import get_profile
from overlapmamba.train.model import OverlapMamba, OverlapMambaConfig

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "kitti00_0000-0100"
SYNTH = ROOT / "data" / "synth" / "test"
MODEL = ROOT / "models" / "overlapmamba-hdl64.onnx"
PROFILE = get_profile("kitti-hdl64")
SIZES = (1_000, 10_000)


def timed(fn, items: list, reps: int) -> float:
    """Median milliseconds of fn(item), cycling over the items, after one warm-up call."""
    fn(items[0])
    times = []
    for r in range(reps):
        t0 = time.perf_counter()
        fn(items[r % len(items)])
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def tile(base: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    reps = -(-n // len(base))
    out = np.concatenate([base] * reps)[:n].astype(np.float32)
    return out + rng.normal(0, 1e-3, out.shape).astype(np.float32)


def network_extractor(cfg: OverlapMambaConfig):
    model = OverlapMamba(cfg).eval()

    @torch.no_grad()
    def run(xyz: np.ndarray) -> np.ndarray:
        img = torch.from_numpy(project(xyz, PROFILE))[None, None]
        return model(img)[0].numpy()

    return run


def onnx_extractor(path: Path, threads: int):
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    sess = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])

    def run(xyz: np.ndarray) -> np.ndarray:
        return sess.run(["descriptor"], {"range_image": project(xyz, PROFILE)[None, None]})[0]

    return run


def descriptor_search(db: np.ndarray, queries: np.ndarray, reps: int) -> dict[str, float]:
    out = {"numpy_ms": timed(lambda q: int(np.argmax(db @ q)), list(queries), reps)}
    try:
        import faiss
    except ImportError:
        return out
    faiss.omp_set_num_threads(1)
    index = faiss.IndexFlatIP(db.shape[1])
    index.add(db)
    out["faiss_flat_ms"] = timed(lambda q: index.search(q[None], 1), list(queries), reps)
    return out


def scancontext_search(db: np.ndarray, queries: np.ndarray, reps: int, k: int) -> float:
    keys = ring_key(db)

    def search(q: np.ndarray) -> int:
        d = ((keys - ring_key(q)) ** 2).sum(1)
        cand = np.argpartition(d, k)[:k]
        dist, _ = match(q, db[cand])
        return int(cand[np.argmin(dist)])

    return timed(search, list(queries), reps)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--reps", type=int, default=20, help="extraction repetitions per method")
    ap.add_argument("--queries", type=int, default=200, help="search queries per size")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", type=Path, default=REPORTS / "model" / "place_recognition.json")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    rng = np.random.default_rng(0)

    source = REAL if (REAL / "velodyne").is_dir() else SYNTH
    if not source.is_dir():
        raise SystemExit(f"no scans: neither {REAL} nor {SYNTH} exists (run `make data`)")
    seq = open_sequence(source)
    scans = [seq.points(i).xyz for i in range(min(len(seq), 40))]

    params = ScanContextParams()
    ot_cfg = OverlapMambaConfig(mixer="transformer", spp=False)
    extract: dict[str, Any] = {
        "Scan Context (numpy)": lambda xyz: scan_context(xyz, params),
        "OT-style (PyTorch)": network_extractor(ot_cfg),
        "OverlapMamba (PyTorch)": network_extractor(OverlapMambaConfig()),
    }
    if MODEL.is_file():
        extract["OverlapMamba (shipped ONNX, onnxruntime)"] = onnx_extractor(MODEL, args.threads)
    extraction = {name: timed(fn, scans, args.reps) for name, fn in extract.items()}
    project_ms = timed(lambda xyz: project(xyz, PROFILE), scans, args.reps)

    contexts = np.stack([scan_context(x, params) for x in scans])
    descs = rng.normal(size=(len(scans), 256)).astype(np.float32)
    descs /= np.linalg.norm(descs, axis=1, keepdims=True)
    search: dict[int, dict[str, float]] = {}
    for n in SIZES:
        db = tile(descs, n, rng)
        q = tile(descs, args.queries, rng)
        search[n] = descriptor_search(db, q, args.queries)
        sc_db, sc_q = tile(contexts, n, rng), tile(contexts, args.queries, rng)
        search[n]["scancontext_ms"] = scancontext_search(
            sc_db, sc_q, args.queries, params.candidates
        )

    console = Console()
    t = Table(title=f"Table V: CPU time per scan ({args.threads} threads, {source.name})")
    t.add_column("method")
    t.add_column("extraction ms", justify="right")
    for n in SIZES:
        t.add_column(f"search ms @ {n // 1000}k", justify="right")
    for name, ms in extraction.items():
        row = [name, f"{ms:.1f}"]
        for n in SIZES:
            s = search[n]
            if name.startswith("Scan Context"):
                row.append(f"{s['scancontext_ms']:.2f}")
            else:
                fa = s.get("faiss_flat_ms")
                row.append(f"{s['numpy_ms']:.3f} numpy" + (f" / {fa:.3f} faiss" if fa else ""))
        t.add_row(*row)
    console.print(t)
    console.print(f"projection alone (inside every network's extraction): {project_ms:.1f} ms")
    record = {
        "machine": {"platform": platform.platform(), "processor": platform.processor()},
        "threads": args.threads,
        "scans": str(source),
        "extraction_ms": extraction,
        "projection_ms": project_ms,
        "search_ms": {str(n): v for n, v in search.items()},
        "torch": torch.__version__,
    }
    write_report(args.json, record)
    console.print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
