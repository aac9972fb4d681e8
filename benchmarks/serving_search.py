"""Part 3 of ``benchmarks/serving.py``: the FAISS index in process — flat and IVF over an
nprobe sweep, recall@10 and place recall, build times, the filtered path."""

from __future__ import annotations

import argparse
import gc
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import faiss
import numpy as np
from bench_kit import CORES, pct
from rich.console import Console
from rich.table import Table

from overlapmamba.service.backends.faiss.index import VectorIndex
from overlapmamba.service.settings import IndexSettings

DIM = 256
K = 10
NPROBES = (1, 2, 4, 8, 16, 24, 32, 48, 64, 128)
RECALL_GOAL = 0.99
P50_GOAL_MS = 1.0
SERVICE_NPROBE = IndexSettings().ivf_nprobe


# ---- part 3: search -------------------------------------------------------------------------


def _unit(x: np.ndarray) -> np.ndarray:
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return x


def place_sigma(cos: float = 0.9, dim: int = DIM) -> float:
    """Noise σ per coordinate so that two noisy views of one centre have cosine ≈ ``cos``:
    (c + e₁)·(c + e₂) ≈ 1 and |c + e|² ≈ 1 + dim·σ²."""
    return float(np.sqrt((1 / cos - 1) / dim))


@dataclass
class Data:
    x: np.ndarray  # (N, D) keyframes; id = row
    q: np.ndarray  # (nq, D) queries
    places: int = 0  # keyframe i belongs to place i mod places (0: no places)
    query_places: np.ndarray | None = None
    within_cosine: float | None = None  # mean cosine of two views of one place


def places(n: int, nq: int, views: int, rng: np.random.Generator) -> Data:
    """Keyframe i belongs to place i mod P (P = n // views): centre + noise, normalised."""
    p = max(1, n // views)
    sigma = place_sigma()
    centres = _unit(rng.standard_normal((p, DIM), dtype=np.float32))
    x = np.empty((n, DIM), np.float32)
    for s in range(0, n, 100_000):
        e = min(n, s + 100_000)
        x[s:e] = centres[np.arange(s, e) % p]
        x[s:e] += sigma * rng.standard_normal((e - s, DIM), dtype=np.float32)
        _unit(x[s:e])
    qp = rng.integers(0, p, nq)
    q = _unit(centres[qp] + sigma * rng.standard_normal((nq, DIM), dtype=np.float32))
    m = min(p, n - p, 10_000)
    within = float(np.mean(np.sum(x[:m] * x[p : p + m], axis=1))) if m > 0 else None
    return Data(x, q, p, qp, within)


def uniform(n: int, nq: int, rng: np.random.Generator) -> Data:
    x = np.empty((n, DIM), np.float32)
    for s in range(0, n, 100_000):
        e = min(n, s + 100_000)
        x[s:e] = _unit(rng.standard_normal((e - s, DIM), dtype=np.float32))
    return Data(x, _unit(rng.standard_normal((nq, DIM), dtype=np.float32)))


def run_queries(
    index: VectorIndex, queries: np.ndarray, allowed: np.ndarray | None
) -> tuple[list[np.ndarray], np.ndarray]:
    for q in queries[:5]:
        index.search(q, K, allowed)
    ids, ms = [], []
    for q in queries:
        t = time.perf_counter()
        _, i = index.search(q, K, allowed)
        ms.append(time.perf_counter() - t)
        ids.append(i)
    return ids, np.asarray(ms) * 1e3


def recalls(got: list[np.ndarray], exact: list[np.ndarray], data: Data) -> dict[str, float | None]:
    """recall@10: |approx top-10 ∩ exact top-10| / |exact top-10|, averaged. place recall:
    the same restricted to the exact top-10's keyframes of the query's own place (the ones
    place recognition needs; the rest of a top-10 can be unrelated, near-random keyframes)."""
    r, pr = [], []
    for i, (g, e) in enumerate(zip(got, exact, strict=True)):
        gs = set(g.tolist())
        r.append(len(gs & set(e.tolist())) / max(len(e), 1))
        if data.query_places is not None:
            own = {j for j in e.tolist() if j % data.places == data.query_places[i]}
            if own:
                pr.append(len(gs & own) / len(own))
    return {
        "recall_at_10": float(np.mean(r)),
        "place_recall": float(np.mean(pr)) if pr else None,
    }


def _row(ms: np.ndarray, rec: dict[str, float | None]) -> dict[str, Any]:
    return {"p50_ms": pct(ms, 50), "p99_ms": pct(ms, 99), **rec}


def search_one(data: Data, rng: np.random.Generator) -> dict[str, Any]:
    x, q = data.x, data.q
    n = len(x)
    ids = np.arange(n, dtype=np.int64)
    allowed = rng.random(n) < 0.5
    faiss.omp_set_num_threads(CORES)  # builds use every core, as the service's do
    t = time.perf_counter()
    flat = VectorIndex.flat(DIM)
    flat.add(ids, x)
    flat_build = time.perf_counter() - t
    t = time.perf_counter()
    ivf = VectorIndex.ivf(x)
    train_s = time.perf_counter() - t
    t = time.perf_counter()
    ivf.add(ids, x)
    add_s = time.perf_counter() - t

    faiss.omp_set_num_threads(1)  # one thread per search, as the service runs them
    exact, ms = run_queries(flat, q, None)
    exact_f, ms_f = run_queries(flat, q, allowed)
    res: dict[str, Any] = {
        "n": n,
        "allowed_fraction": float(allowed.mean()),
        "within_place_cosine": data.within_cosine,
        "flat": {
            "build_s": flat_build,
            **_row(ms, recalls(exact, exact, data)),
            "filtered": _row(ms_f, recalls(exact_f, exact_f, data)),
        },
        "ivf": {"nlist": ivf.nlist, "train_s": train_s, "add_s": add_s, "nprobe": {}},
    }
    for p in NPROBES:
        if p > ivf.nlist:
            continue
        ivf.nprobe = p
        got, ms = run_queries(ivf, q, None)
        res["ivf"]["nprobe"][p] = _row(ms, recalls(got, exact, data))
    reached = [p for p, r in res["ivf"]["nprobe"].items() if r["recall_at_10"] >= RECALL_GOAL]
    chosen = min(reached) if reached else max(res["ivf"]["nprobe"])
    res["ivf"]["chosen_nprobe"] = chosen
    res["ivf"]["chosen_reaches_goal"] = bool(reached)
    ivf.nprobe = chosen
    got, ms_f = run_queries(ivf, q, allowed)
    res["ivf"]["filtered"] = _row(ms_f, recalls(got, exact_f, data))
    faiss.omp_set_num_threads(CORES)
    return res


def search_part(args: argparse.Namespace, console: Console) -> dict[str, Any]:
    out: dict[str, Any] = {
        "dim": DIM,
        "k": K,
        "queries": args.queries,
        "views_per_place": args.views,
        "place_sigma": place_sigma(),
        "search_threads": 1,
        "build_threads": CORES,
        "service_default_nprobe": SERVICE_NPROBE,
        "load_average_at_start": os.getloadavg(),
        "datasets": {},
    }
    plans: list[tuple[str, Callable[[int, int, np.random.Generator], Data], list[int]]] = [
        (
            f"places ({args.views} views/place)",
            lambda n, nq, r: places(n, nq, args.views, r),
            args.sizes,
        )
    ]
    if args.views != 5:
        plans.append(
            ("places (5 views/place)", lambda n, nq, r: places(n, nq, 5, r), args.hard_sizes)
        )
    plans.append(("uniform on the sphere", uniform, args.hard_sizes))
    out["main_dataset"] = plans[0][0]
    for name, make, sizes in plans:
        out["datasets"][name] = {}
        for n in sizes:
            rng = np.random.default_rng(n)
            t = time.perf_counter()
            data = make(n, args.queries, rng)
            gen_s = time.perf_counter() - t
            console.print(f"search: {name}, N = {n:,} (generated in {gen_s:.1f} s) …")
            rec = search_one(data, rng)
            rec["generate_s"] = gen_s
            out["datasets"][name][str(n)] = rec
            del data
            gc.collect()
    return out


def _r(v: float | None) -> str:
    return "—" if v is None else f"{v:.3f}"


def print_search(res: dict[str, Any], console: Console) -> None:
    for name, by_size in res["datasets"].items():
        t = Table(
            title=f"Search, {name}: times in ms per query",
            caption=f"{res['dim']}-d unit vectors, k={res['k']}, {res['queries']} queries, "
            f"nq=1, faiss 1 thread per search ({res['build_threads']} for builds; build s = "
            f"flat add, IVF train+add). R@10 = recall@10 against flat; place R = the same "
            f"over the exact top-10's keyframes of the query's own place. ★ = smallest nprobe "
            f"with R@10 ≥ {RECALL_GOAL} (else the largest swept). filt = with an allowed mask "
            "of ~half the ids, for flat and ★. cos = mean cosine of two views of a place.",
        )
        cols = ["N", "index", "build s", "p50", "p99", "R@10", "place R"]
        cols += ["filt p50", "filt p99", "filt R@10", "filt place R"]
        for c in cols:
            t.add_column(c, justify="right")
        for n, r in by_size.items():
            f = r["flat"]
            ff = f["filtered"]
            cos = r["within_place_cosine"]
            t.add_row(
                f"{int(n):,}",
                "flat",
                f"{f['build_s']:.1f}",
                f"{f['p50_ms']:.3f}",
                f"{f['p99_ms']:.3f}",
                "1",
                "1" if f["place_recall"] is not None else "—",
                f"{ff['p50_ms']:.3f}",
                f"{ff['p99_ms']:.3f}",
                "1",
                "1" if ff["place_recall"] is not None else "—",
            )
            ivf = r["ivf"]
            for i, (p, row) in enumerate(ivf["nprobe"].items()):
                chosen = p == ivf["chosen_nprobe"]
                fil = ivf["filtered"] if chosen else None
                first = ["", f"cos {cos:.2f}" if cos is not None else ""]
                t.add_row(
                    first[i] if i < 2 else "",
                    f"ivf{ivf['nlist']} np{p}" + (" ★" if chosen else ""),
                    f"{ivf['train_s']:.1f}+{ivf['add_s']:.1f}" if i == 0 else "",
                    f"{row['p50_ms']:.3f}",
                    f"{row['p99_ms']:.3f}",
                    _r(row["recall_at_10"]),
                    _r(row["place_recall"]),
                    f"{fil['p50_ms']:.3f}" if fil else "",
                    f"{fil['p99_ms']:.3f}" if fil else "",
                    _r(fil["recall_at_10"]) if fil else "",
                    _r(fil["place_recall"]) if fil else "",
                )
            t.add_section()
        console.print(t)
