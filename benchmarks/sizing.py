"""Sizing figures for docs/deploy.md: scans/s per core, bytes per keyframe, and the cost of
each map backend's operations, measured on this machine.

    encoder     the shipped model as the service runs it (project + encode, one scan per
                call) with 1 and with 2 onnxruntime threads, and as many lanes as cores,
                one thread each, encoding at once (the service's default,
                batching.lanes), on real KITTI scans when ../shared/data is there (else
                synthetic ones)
    storage     per keyframe with the model's real yaw-feature shape: the FAISS backend's
                store (SQLite + WAL), its snapshot and the process's resident memory; the
                Qdrant backend's point payload
    backends    insert and query (k = 10) latency through the one map interface, for FAISS
                and for Qdrant's *local mode* (exact numpy search, no server: it shows the
                payload and filter path, not a Qdrant server's speed)
    search      the query's "search" stage on a FAISS map of --search-keyframes (10,000):
                index + rows (k = 5 and the runner-up) + yaw (k = 5), split into its parts, with
                FAISS on 1 and on 2 OpenMP threads (index.threads), on an idle process and
                with the encoder busy in another thread (as under load); and the stage as a
                scan query runs it by default, two-stage: the rerank.shortlist (20) nearest and the
                runner-up, their yaw, re-ranked (overlapmamba.service.ranking)

Writes JSON (default reports/deploy/sizing.json). ``--model FILE --encoder-only --out …``
measures only another file's encoder rate (the one-view twin's: sizing-one-view.json).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
from bench_kit import served_rerank
from reports_kit import REPORTS, shown_path, write_report
from rich.console import Console
from rich.table import Table

from overlapmamba.core.io import read_points
from overlapmamba.core.yaw import estimate_yaw
from overlapmamba.service.backends.factory import open_backend
from overlapmamba.service.backends.qdrant.codec import point_payload
from overlapmamba.service.domain import Filters, NewKeyframe, content_hash
from overlapmamba.service.encoder import Encoder
from overlapmamba.service.ranking import rerank_matches, shortlist
from overlapmamba.service.settings import Settings
from overlapmamba.service.threads import cores

ROOT = Path(__file__).resolve().parents[1]
KITTI = ROOT.parent / "shared" / "data" / "kitti00_0000-0100" / "velodyne"


def rss_bytes() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    return 0


def scans(n: int) -> tuple[list, str]:
    if KITTI.is_dir():
        files = sorted(KITTI.glob("*.bin"))[:n]
        return [read_points(p) for p in files], f"KITTI 00 frames 0–{len(files) - 1}"
    import tempfile

    sys.path.insert(0, str(ROOT / "tests"))
    from service_kit import scan

    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(n):
            path = Path(tmp) / f"{i:06d}.bin"
            path.write_bytes(scan(i).tobytes())
            out.append(read_points(path))
    return out, "synthetic scans (tests/service_kit.py)"


def encoder_rate(model: Path, clouds: list, threads: int, reps: int) -> dict[str, float]:
    enc = Encoder(model, intra_op_threads=threads)

    def one(cloud) -> None:  # as the service describes a scan (yaw features unshifted too)
        image, offset = enc.project_offset(cloud)
        enc.encode(image[None], np.array([offset]))

    one(clouds[0])  # warm-up
    times = []
    for i in range(reps):
        t0 = time.perf_counter()
        one(clouds[i % len(clouds)])
        times.append(time.perf_counter() - t0)
    med = float(np.median(times))
    return {"lanes": 1, "threads": threads, "median_ms": med * 1e3, "scans_per_s": 1.0 / med}


def lanes_rate(model: Path, clouds: list, lanes: int, reps: int) -> dict[str, float]:
    """``lanes`` threads describing scans at once on one encoder, one onnxruntime thread a
    call (the service's default: ``batching.lanes``): the node's scans a second (wall) and
    the median time of one scan in a lane."""
    import concurrent.futures

    enc = Encoder(model, intra_op_threads=1)

    def one(cloud) -> float:
        t0 = time.perf_counter()
        image, offset = enc.project_offset(cloud)
        enc.encode(image[None], np.array([offset]))
        return time.perf_counter() - t0

    def lane(k: int) -> list[float]:
        return [one(clouds[(k + i) % len(clouds)]) for i in range(reps)]

    one(clouds[0])  # warm-up
    with concurrent.futures.ThreadPoolExecutor(lanes) as pool:
        t0 = time.perf_counter()
        times = [t for got in pool.map(lane, range(lanes)) for t in got]
        wall = time.perf_counter() - t0
    med = float(np.median(times))
    return {"lanes": lanes, "threads": 1, "median_ms": med * 1e3, "scans_per_s": len(times) / wall}


def unit(v: np.ndarray) -> np.ndarray:
    """A descriptor as the service keeps them: float32, unit norm."""
    return (v / np.linalg.norm(v)).astype(np.float32)


def rows(n: int, dim: int, yaw_shape: tuple[int, ...], seed: int = 0) -> list[NewKeyframe]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        d = unit(rng.normal(size=dim))
        out.append(
            NewKeyframe(
                keyframe_id=f"kf-{i}",
                robot_id=f"r{i % 8}",
                session_id=f"s{i % 3}",
                timestamp=float(i),
                pose=[float(i), 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
                descriptor=d,
                yaw=rng.normal(size=yaw_shape).astype(np.float32),
                content_hash=content_hash("descriptor", d.tobytes(), {"i": i}),
            )
        )
    return out


def folder_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def backend_costs(kind: str, root: Path, data: list[NewKeyframe], dim: int) -> dict:
    if kind == "faiss":
        s = Settings(data_dir=root)
    else:
        s = Settings(data_dir=root, index={"backend": "qdrant"}, qdrant={"path": root / "q"})
    b = open_backend(s, model_id="bench", dim=dim)
    b.load_all()
    m, _ = b.create("town", "flat")
    rss0 = rss_bytes()
    t_insert = []
    for r in data:
        t0 = time.perf_counter()
        m.insert([r])
        t_insert.append(time.perf_counter() - t0)
    rss1 = rss_bytes()
    rng = np.random.default_rng(1)
    t_query, t_filtered = [], []
    for _ in range(100):
        q = unit(rng.normal(size=dim))
        t0 = time.perf_counter()
        m.search(q, 10, Filters())
        t_query.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        m.search(q, 10, Filters(exclude_recent_s=500.0, session_id="s1", timestamp=len(data)))
        t_filtered.append(time.perf_counter() - t0)
    out: dict = {
        "n": len(data),
        "insert_p50_ms": float(np.median(t_insert)) * 1e3,
        "query_p50_ms": float(np.median(t_query)) * 1e3,
        "filtered_query_p50_ms": float(np.median(t_filtered)) * 1e3,
    }
    if kind == "faiss":
        snap = m.snapshot()
        folder = root / "maps" / "town"
        store = sum(f.stat().st_size for f in folder.glob("store.sqlite*"))
        out |= {
            "store_bytes_per_keyframe": store / len(data),
            "snapshot_bytes_per_keyframe": snap["bytes"] / len(data),
            "rss_bytes_per_keyframe": (rss1 - rss0) / len(data),
        }
    else:
        out |= {
            "payload_json_bytes_per_point": float(
                np.mean([len(json.dumps(point_payload(r, 0.0))) for r in data[:50]])
            ),
            "vector_bytes_per_point": dim * 4,
            "local_storage_bytes_per_point": folder_bytes(root / "q") / len(data),
        }
    b.close()
    return out


def _p(times: list[float]) -> dict[str, float]:
    ms = np.asarray(times) * 1e3
    return {"p50_ms": float(np.median(ms)), "p90_ms": float(np.percentile(ms, 90))}


def search_stage(
    root: Path, n: int, dim: int, yaw_shape: tuple[int, ...], enc: Encoder, cloud, reps: int
) -> list[dict]:
    """Map.search (what the query's ``timings_ms.search`` times, less the thread hop) and its
    parts, per (FAISS threads, load)."""
    import threading

    from overlapmamba.service.backends.faiss.index import set_threads

    b = open_backend(Settings(data_dir=root), model_id="bench", dim=dim)
    b.load_all()
    m, _ = b.create("town", "flat")
    data = rows(n, dim, yaw_shape, seed=2)
    for i in range(0, n, 500):
        m.insert(data[i : i + 500])
    rng = np.random.default_rng(3)
    queries = [
        (unit(rng.normal(size=dim)), rng.normal(size=yaw_shape).astype(np.float32))
        for _ in range(reps)
    ]
    image, offset = enc.project_offset(cloud)
    image, offsets = image[None], np.array([offset])
    p = served_rerank(enc.meta)  # as the service re-ranks
    n_short = shortlist(5, p)
    out = []
    for load in ("idle", "encoder busy"):
        stop = threading.Event()

        def busy(stop: threading.Event = stop) -> None:
            while not stop.is_set():
                enc.encode(image, offsets)

        worker = threading.Thread(target=busy, daemon=True) if load != "idle" else None
        if worker:
            worker.start()
        for threads in (1, 2):
            set_threads(threads)
            whole, index, rows_, yaw, staged = [], [], [], [], []
            for q, qy in queries:
                t0 = time.perf_counter()
                m.search(q, 6, Filters(), qy, yaw_k=5)  # a query with k = 5, one stage
                whole.append(time.perf_counter() - t0)
                t0 = time.perf_counter()  # the same query as served: two stages
                found = m.search(
                    q, n_short + 1, Filters(), qy, yaw_k=n_short, descriptors=p.part is not None
                )
                rerank_matches(found, p, q)
                staged.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                _, ids = m.index.search(q, 6, None)
                index.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                got = m.store.by_ids([int(i) for i in ids])
                rows_.append(time.perf_counter() - t0)
                refs = np.stack([got[int(i)][1] for i in ids[:5]])  # not the runner-up
                t0 = time.perf_counter()
                estimate_yaw(qy, refs)
                yaw.append(time.perf_counter() - t0)
            out.append(
                {
                    "load": load,
                    "faiss_threads": threads,
                    "keyframes": n,
                    "search": _p(whole),
                    "search_two_stage": _p(staged) | {"shortlist": n_short},
                    "index": _p(index),
                    "rows": _p(rows_),
                    "yaw": _p(yaw),
                }
            )
        if worker:
            stop.set()
            worker.join()
    set_threads(1)
    b.close()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", type=Path, default=ROOT / "models" / "overlapmamba-hdl64.onnx")
    ap.add_argument("--keyframes", type=int, default=2000)
    ap.add_argument("--reps", type=int, default=30)
    ap.add_argument("--search-keyframes", type=int, default=10_000)
    ap.add_argument("--search-reps", type=int, default=200)
    ap.add_argument("--work", type=Path, default=ROOT / "bench-results" / "sizing-work")
    ap.add_argument("--out", type=Path, default=REPORTS / "deploy" / "sizing.json")
    ap.add_argument(
        "--encoder-only",
        action="store_true",
        help="only the encoder's rate (another model file beside the default's sizing)",
    )
    args = ap.parse_args()
    console = Console()

    clouds, source = scans(16)
    enc_rates = [encoder_rate(args.model, clouds, t, args.reps) for t in (1, 2)]
    if cores() > 1:  # the service's default: a lane a core, one thread each
        enc_rates.append(lanes_rate(args.model, clouds, cores(), args.reps))
    enc = Encoder(args.model, intra_op_threads=1)
    image, offset = enc.project_offset(clouds[0])
    desc, yaw = enc.encode(image[None], np.array([offset]))
    dim, yaw_shape = desc.shape[1], tuple(yaw.shape[1:])
    model = {"path": shown_path(args.model), "model_id": enc.model_id, "views": enc.views}
    model["column_phase"] = enc.meta.column_phase
    machine = {
        "platform": platform.platform(),
        "cores": os.cpu_count(),
        "python": platform.python_version(),
    }
    if args.encoder_only:
        write_report(
            args.out, {"machine": machine, "scans": source, "model": model, "encoder": enc_rates}
        )
        console.print(f"wrote {shown_path(args.out)}")
        return

    import shutil

    shutil.rmtree(args.work, ignore_errors=True)
    data = rows(args.keyframes, dim, yaw_shape)
    backends = {k: backend_costs(k, args.work / k, data, dim) for k in ("faiss", "qdrant")}
    shutil.rmtree(args.work, ignore_errors=True)
    search = search_stage(
        args.work / "search",
        args.search_keyframes,
        dim,
        yaw_shape,
        enc,
        clouds[0],
        args.search_reps,
    )
    shutil.rmtree(args.work, ignore_errors=True)

    result = {
        "machine": machine,
        "scans": source,
        "model": model,
        "encoder": enc_rates,
        "descriptor_dim": dim,
        "yaw_shape": list(yaw_shape),
        "backends": backends,
        "search_stage": search,
    }
    write_report(args.out, result)

    t = Table(title=f"encoder, one scan per call ({source})")
    for col in ("lanes", "onnxruntime threads a lane", "median ms / scan", "scans/s"):
        t.add_column(col, justify="right")
    for r in enc_rates:
        t.add_row(
            str(r["lanes"]), str(r["threads"]), f"{r['median_ms']:.1f}", f"{r['scans_per_s']:.1f}"
        )
    console.print(t)
    t = Table(title=f"map backends, {args.keyframes} keyframes (dim {dim}, yaw {yaw_shape})")
    t.add_column("figure")
    for k in backends:
        t.add_column(k, justify="right")
    keys = sorted({k for v in backends.values() for k in v})
    for key in keys:
        t.add_row(key, *[_fmt(backends[b].get(key)) for b in backends])
    console.print(t)
    t = Table(
        title=f"search stage: k = 5 with yaw (+ the runner-up, without), FAISS map of "
        f"{args.search_keyframes:,} keyframes, p50 (p90) ms"
    )
    cols = ("search (whole)", "index", "rows", "yaw", "two stages (whole)")
    for col in ("load", "FAISS threads", *cols):
        t.add_column(col, justify="right")
    for r in search:
        cells = [
            f"{r[k]['p50_ms']:.3f} ({r[k]['p90_ms']:.3f})"
            for k in ("search", "index", "rows", "yaw", "search_two_stage")
        ]
        t.add_row(r["load"], str(r["faiss_threads"]), *cells)
    console.print(t)
    console.print(f"wrote {args.out}")


def _fmt(v: object) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:,.3f}" if v < 100 else f"{v:,.0f}"
    return str(v)


if __name__ == "__main__":
    main()
