"""The place-recognition service: HTTP overhead, throughput under concurrency, index search.

1. **HTTP overhead** — scan → descriptor through a real ``overlapmamba serve`` (uvicorn in a
   subprocess, temporary data folder) against the bare encoder in this process, in the same
   run: bare = ``lidar_core.io.decode`` + ``Encoder.project`` + ``Encoder.encode`` at B = 1;
   HTTP = ``POST /v1/descriptors`` with the same body (``application/octet-stream``,
   ``X-Point-Fields: xyzi``) over one keep-alive httpx connection, sequentially, descriptor
   JSON parsed. The two are timed in alternating blocks so drift hits both alike. Ratio =
   HTTP median ÷ bare median; goal ≤ 1.10. A third block times a 1024×512 @ 512×900 float32
   matrix product (0.47 GMAC, numpy's BLAS): HTTP ÷ sgemm says how the whole path compares
   with this machine's dense arithmetic (goal ≤ 9). Servers: the defaults (micro-batching,
   ``max_batch`` 8, ``max_wait_ms`` 2), ``max_wait_ms`` 0, and ``max_batch`` 1.
2. **Throughput** — 1, 4 and 8 concurrent clients (tasks sharing one httpx AsyncClient)
   posting scans for a fixed time: scans/s, latency p50/p99 and the server's encoder batch
   sizes (the ``/v1/stats`` histogram, before/after difference), with micro-batching (the
   defaults) and without (``OVERLAPMAMBA_BATCHING__MAX_BATCH=1``). The clients share this
   machine's cores with the server.
3. **Search** — ``service.backends.faiss.index.VectorIndex`` in process, 256-d float32 unit
   vectors, flat (exact) and IVF (nlist = ``ivf_lists(N)``) over an nprobe sweep: per-query
   p50/p99 at nq = 1 with ``faiss.omp_set_num_threads(1)`` (FAISS parallelises over queries, so a
   single-query search runs on one thread in the service too; builds use every core),
   recall@10 against the flat
   index, build times, and the filtered path (an ``allowed`` mask excluding ~half the ids)
   for flat and the chosen nprobe (the smallest reaching recall@10 ≥ 0.99). Goal: IVF p50
   < 1 ms at 1M keyframes with recall@10 ≥ 0.99. Also "place recall": recall over only
   those exact top-10 keyframes that belong to the query's own place.

   Main data set "places": N/V places (V = ``--views``, default 10) with centres uniform on
   the sphere; each keyframe is its place's centre plus Gaussian noise (σ such that two views
   of a place have cosine ≈ 0.9), normalised; queries are fresh views of random places. With
   V ≥ 10 the exact top-10 is the query's own place. Hard cases at ``--hard-sizes``: the same
   with 5 views per place (the exact top-10 then holds 5 unrelated, essentially random
   keyframes), and vectors uniform on the sphere (no structure for IVF to use).

Scans: KITTI 00 from ../shared/data when present, else seeded synthetic ones (a ground plane
and a ring of walls, 120k points). onnxruntime runs with intra-op threads = all cores both in
this process and in the server (both defaults). Before each part the CPU use of other
processes is sampled for a second; above 10 % a warning says the numbers will be noisy.
Prints one table per part and a summary with the goals (met / not met from this run's
numbers), and writes JSON (default bench-results/service.json). ``--quick``: sizes 10k and
100k, 12 overhead reps, 3 s per throughput run, 100 queries.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import gc
import json
import os
import platform
import socket
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import faiss
import httpx
import numpy as np
import onnxruntime as ort
from rich.console import Console
from rich.table import Table

from lidar_core.io import decode
from service.backends.faiss.index import VectorIndex
from service.encoder import Encoder
from service.settings import BatchSettings, IndexSettings

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "kitti00_0000-0100"
MODEL = ROOT / "models" / "overlapmamba-hdl64.onnx"
HEADERS = {"Content-Type": "application/octet-stream", "X-Point-Fields": "xyzi"}
DIM = 256
K = 10
NPROBES = (1, 2, 4, 8, 16, 24, 32, 48, 64, 128)
RECALL_GOAL = 0.99
RATIO_GOAL = 1.10
# A yardstick of this machine's speed, timed in the same run: a 0.47-GMAC float32 matrix
# product (numpy's BLAS, all cores). Goal: HTTP scan → descriptor ≤ 9× its time.
SGEMM = ((1024, 512), (512, 900))
SGEMM_GOAL = 9.0
P50_GOAL_MS = 1.0
CORES = os.cpu_count() or 1
DEFAULTS = BatchSettings()  # the service's own defaults, reported, not assumed
SERVICE_NPROBE = IndexSettings().ivf_nprobe

# ---- scans ----------------------------------------------------------------------------------


def synthetic_scan(seed: int, n: int = 120_000) -> np.ndarray:
    """(n, 4) float32 xyzi: a ground plane and a wavy ring of walls around the sensor."""
    rng = np.random.default_rng(seed)
    ng = n // 3
    r = 40 * np.sqrt(rng.uniform(0.01, 1, ng))
    a = rng.uniform(-np.pi, np.pi, ng)
    ground = np.column_stack([r * np.cos(a), r * np.sin(a), rng.normal(-1.73, 0.02, ng)])
    nw = n - ng
    a = rng.uniform(-np.pi, np.pi, nw)
    radius = 15 + 5 * np.sin(3 * a + seed) + rng.normal(0, 0.05, nw)
    walls = np.column_stack([radius * np.cos(a), radius * np.sin(a), rng.uniform(-1.7, 3, nw)])
    xyz = np.concatenate([ground, walls])
    return np.column_stack([xyz, rng.uniform(0, 1, n)]).astype(np.float32)


def scan_bodies(n: int) -> tuple[list[bytes], str]:
    paths = sorted((REAL / "velodyne").glob("*.bin"))[:n]
    if paths:
        pts = len(paths[0].read_bytes()) // 16
        return [p.read_bytes() for p in paths], (
            f"KITTI 00 frames 0–{len(paths) - 1} (frame 0: {pts} points)"
        )
    return [synthetic_scan(i).tobytes() for i in range(n)], "synthetic scans (120k points)"


def _machine_jiffies() -> tuple[int, int]:
    """(total, busy) CPU time of the whole machine from /proc/stat, in clock ticks."""
    values = [int(v) for v in Path("/proc/stat").read_text().split("\n")[0].split()[1:8]]
    return sum(values), sum(values) - values[3] - values[4]  # minus idle and iowait


def _pid_cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime


SERVER_CPU_S = [0.0]  # CPU seconds used by the benchmark's servers, added as each one stops


class OtherLoad:
    """The share of the machine's CPU used by *other* processes over a stretch of time:
    machine busy time (/proc/stat) minus this process's and its servers' CPU time. Anything
    above a few percent means the measurements competed with someone else's work. Linux
    only; elsewhere ``fraction()`` is None."""

    def __init__(self) -> None:
        try:
            self.start: tuple[int, int] | None = _machine_jiffies()
        except (OSError, ValueError, IndexError):
            self.start = None
        self.t0 = time.perf_counter()
        self.own0 = time.process_time() + SERVER_CPU_S[0]

    def fraction(self) -> float | None:
        if self.start is None:
            return None
        total, busy = _machine_jiffies()
        hz = os.sysconf("SC_CLK_TCK")
        own = time.process_time() + SERVER_CPU_S[0] - self.own0
        other = (busy - self.start[1]) / hz - own
        return max(0.0, other / max((total - self.start[0]) / hz, 1e-9))


def other_load(console: Console, part: str, watch: OtherLoad, when: str) -> float | None:
    busy = watch.fraction()
    if busy is not None and busy > 0.1:
        console.print(
            f"[yellow]warning:[/] {when} the {part} part, other processes used {100 * busy:.0f}% "
            "of the machine's CPU: these numbers are noisy; rerun when the machine is quiet"
        )
    return busy


# ---- servers --------------------------------------------------------------------------------


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def serve_command() -> list[str]:
    exe = Path(sys.executable).parent / "overlapmamba"
    return [str(exe)] if exe.is_file() else [sys.executable, "-m", "overlapmamba"]


@contextlib.contextmanager
def server(env_extra: dict[str, str], startup_s: float = 180.0) -> Iterator[str]:
    """A real ``overlapmamba serve`` on a free port with a temporary data folder; its base
    URL once /readyz answers 200. Always terminated (then killed) on exit."""
    with tempfile.TemporaryDirectory(prefix="om-bench-") as tmp:
        port = free_port()
        env = {k: v for k, v in os.environ.items() if not k.startswith("OVERLAPMAMBA_")}
        env |= env_extra
        cmd = [*serve_command(), "serve", "--port", str(port)]
        cmd += ["--data-dir", str(Path(tmp) / "data"), "--model", str(MODEL)]
        log_path = Path(tmp) / "server.log"
        with log_path.open("wb") as log:
            proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
            try:
                url = f"http://127.0.0.1:{port}"
                _wait_ready(proc, url, startup_s, log_path)
                yield url
            finally:
                with contextlib.suppress(OSError, ValueError, IndexError):
                    SERVER_CPU_S[0] += _pid_cpu_s(proc.pid)
                proc.terminate()
                try:
                    proc.wait(15)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()


def _wait_ready(proc: subprocess.Popen, url: str, limit_s: float, log: Path) -> None:
    deadline = time.monotonic() + limit_s
    with httpx.Client(base_url=url, timeout=5) as client:
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                tail = log.read_text(errors="replace")[-3000:]
                raise RuntimeError(f"server exited with {proc.returncode} before ready:\n{tail}")
            with contextlib.suppress(httpx.TransportError):
                if client.get("/readyz").status_code == 200:
                    return
            time.sleep(0.2)
    tail = log.read_text(errors="replace")[-3000:]
    raise RuntimeError(f"server not ready after {limit_s:.0f} s:\n{tail}")


# ---- part 1: HTTP overhead ------------------------------------------------------------------


def pct(ms: list[float] | np.ndarray, q: float) -> float:
    return float(np.percentile(np.asarray(ms, dtype=np.float64), q)) if len(ms) else float("nan")


def overhead(enc: Encoder, body: bytes, url: str, reps: int, block: int = 4) -> dict[str, Any]:
    """Bare and HTTP scan → descriptor, and the sgemm yardstick, in alternating blocks of
    ``block`` calls."""
    stages: dict[str, list[float]] = {"decode": [], "project": [], "encode": []}
    rng = np.random.default_rng(0)
    ma, mb = (rng.standard_normal(shape, dtype=np.float32) for shape in SGEMM)

    def sgemm() -> None:
        np.matmul(ma, mb)

    def bare() -> None:
        t0 = time.perf_counter()
        points = decode(body, "raw", fields="xyzi")
        t1 = time.perf_counter()
        image = enc.project(points)
        t2 = time.perf_counter()
        desc, _ = enc.encode(image[None])
        t3 = time.perf_counter()
        assert desc.shape == (1, enc.dim)
        for k, v in zip(stages, (t1 - t0, t2 - t1, t3 - t2), strict=True):
            stages[k].append(v * 1e3)

    server_t: list[dict[str, float]] = []
    with httpx.Client(base_url=url, timeout=60) as client:

        def http() -> None:
            r = client.post("/v1/descriptors", content=body, headers=HEADERS)
            r.raise_for_status()
            out = r.json()
            assert len(out["descriptor"]) == enc.dim
            server_t.append(out["timings_ms"])

        for _ in range(3):
            bare()
        time.sleep(0.05)
        for _ in range(3):
            http()
        for v in stages.values():
            v.clear()
        server_t.clear()
        b: list[float] = []
        h: list[float] = []
        g: list[float] = []
        sgemm()
        while len(b) < reps:
            # a pause at each switch lets the other side's onnxruntime threads stop spinning
            for fn, out in ((bare, b), (http, h), (sgemm, g)):
                time.sleep(0.05)
                for _ in range(min(block, reps - len(out))):
                    t = time.perf_counter()
                    fn()
                    out.append((time.perf_counter() - t) * 1e3)
    server_med = {k: float(np.median([t[k] for t in server_t])) for k in stages}
    res = {
        "reps": reps,
        "bare_ms": {"median": pct(b, 50), "p90": pct(b, 90)},
        "http_ms": {"median": pct(h, 50), "p90": pct(h, 90)},
        "ratio": pct(h, 50) / pct(b, 50),
        "sgemm_ms": {"median": pct(g, 50), "p90": pct(g, 90), "shape": SGEMM},
        "http_over_sgemm": pct(h, 50) / pct(g, 50),
        "bare_stage_median_ms": {k: float(np.median(v)) for k, v in stages.items()},
        "server_stage_median_ms": server_med,
    }
    # what the server's own stage timings do not cover: HTTP, body transfer, routing, JSON on
    # both ends (its "encode" includes the micro-batcher's wait)
    res["http_minus_server_stages_ms"] = pct(h, 50) - sum(server_med.values())
    return res


# ---- part 2: throughput ---------------------------------------------------------------------


async def _load(url: str, bodies: list[bytes], clients: int, duration: float) -> dict[str, Any]:
    lat: list[float] = []
    errors: Counter[str] = Counter()
    limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)
    async with httpx.AsyncClient(base_url=url, timeout=60, limits=limits) as client:

        async def post(i: int) -> None:
            t = time.perf_counter()
            try:
                r = await client.post(
                    "/v1/descriptors", content=bodies[i % len(bodies)], headers=HEADERS
                )
            except httpx.HTTPError as err:
                errors[type(err).__name__] += 1
                return
            if r.status_code == 200:
                r.json()
                lat.append((time.perf_counter() - t) * 1e3)
            else:
                errors[str(r.status_code)] += 1

        await asyncio.gather(*(post(i) for i in range(clients)))  # warm-up, not counted
        lat.clear()
        errors.clear()
        before = (await client.get("/v1/stats")).json()["batch_size_histogram"]
        t0 = time.perf_counter()
        stop = t0 + duration

        async def worker(w: int) -> None:
            i = w
            while time.perf_counter() < stop:
                await post(i)
                i += clients

        await asyncio.gather(*(worker(w) for w in range(clients)))
        elapsed = time.perf_counter() - t0
        after = (await client.get("/v1/stats")).json()["batch_size_histogram"]
    hist = {s: after[s] - before.get(s, 0) for s in after if after[s] - before.get(s, 0)}
    hist = dict(sorted(hist.items(), key=lambda kv: int(kv[0])))
    calls = sum(hist.values())
    return {
        "clients": clients,
        "duration_s": elapsed,
        "scans": len(lat),
        "scans_per_s": len(lat) / elapsed,
        "latency_ms": {"p50": pct(lat, 50), "p99": pct(lat, 99)},
        "errors": dict(errors),
        "batch_size_histogram": hist,
        "mean_batch": sum(int(s) * c for s, c in hist.items()) / calls if calls else 0.0,
    }


def throughput(url: str, bodies: list[bytes], duration: float) -> list[dict[str, Any]]:
    return [asyncio.run(_load(url, bodies, c, duration)) for c in (1, 4, 8)]


def http_part(args: argparse.Namespace, console: Console) -> dict[str, Any]:
    bodies, source = scan_bodies(16)
    body = bodies[0]
    console.print(f"HTTP part: {source}; loading the bare encoder …")
    enc = Encoder(MODEL)
    threads = enc.session.get_session_options().intra_op_num_threads
    configs = [
        ("batching", {}, True),
        ("batching, wait 0", {"OVERLAPMAMBA_BATCHING__MAX_WAIT_MS": "0"}, False),
        ("no batching", {"OVERLAPMAMBA_BATCHING__MAX_BATCH": "1"}, True),
    ]
    out: dict[str, Any] = {
        "scans": source,
        "body_bytes": len(body),
        "intra_op_threads": threads,
        "defaults": {"max_batch": DEFAULTS.max_batch, "max_wait_ms": DEFAULTS.max_wait_ms},
        "load_average_at_start": os.getloadavg(),
        "servers": {},
    }
    for name, env, load in configs:
        console.print(f"starting server: {name} {env or ''} …")
        t = time.perf_counter()
        with server(env) as url:
            ready_s = time.perf_counter() - t
            console.print(f"  ready in {ready_s:.1f} s; sequential overhead ({args.reps} reps) …")
            rec: dict[str, Any] = {"env": env, "ready_s": ready_s, "loadavg": os.getloadavg()}
            rec["overhead"] = overhead(enc, body, url, args.reps)
            if load:
                console.print(f"  throughput, 1/4/8 clients × {args.duration:.0f} s …")
                rec["throughput"] = throughput(url, bodies, args.duration)
        out["servers"][name] = rec
    del enc
    return out


def print_http(res: dict[str, Any], console: Console) -> None:
    d = res["defaults"]
    t = Table(
        title="HTTP overhead: POST /v1/descriptors ÷ bare decode+project+encode",
        caption=f"{res['scans']}, {res['body_bytes'] / 1e6:.1f} MB body, B=1, sequential; "
        f"onnxruntime {res['intra_op_threads']} intra-op threads on both sides. Servers: "
        f"batching = the defaults (max_batch {d['max_batch']}, max_wait_ms "
        f"{d['max_wait_ms']:g}); wait 0 = OVERLAPMAMBA_BATCHING__MAX_WAIT_MS=0; no batching "
        "= OVERLAPMAMBA_BATCHING__MAX_BATCH=1. Stages dec/proj/enc are medians; rest = HTTP "
        "median − the server's own stage medians (HTTP, transfer, routing, JSON).",
    )
    cols = ["server", "bare ms med/p90", "HTTP ms med/p90", f"ratio (≤ {RATIO_GOAL})"]
    cols += ["bare dec/proj/enc", "server dec/proj/enc", "rest ms", f"÷ sgemm (≤ {SGEMM_GOAL:g})"]
    for c in cols:
        t.add_column(c, justify="right")
    for name, rec in res["servers"].items():
        o = rec["overhead"]
        bs, ss = o["bare_stage_median_ms"], o["server_stage_median_ms"]
        t.add_row(
            name,
            f"{o['bare_ms']['median']:.1f} / {o['bare_ms']['p90']:.1f}",
            f"{o['http_ms']['median']:.1f} / {o['http_ms']['p90']:.1f}",
            f"{o['ratio']:.3f}",
            "/".join(f"{bs[k]:.1f}" for k in ("decode", "project", "encode")),
            "/".join(f"{ss[k]:.1f}" for k in ("decode", "project", "encode")),
            f"{o['http_minus_server_stages_ms']:.1f}",
            f"{o['http_over_sgemm']:.1f} ({o['sgemm_ms']['median']:.2f} ms)",
        )
    console.print(t)
    t = Table(
        title="Throughput: concurrent clients against the real server",
        caption="clients = tasks sharing one httpx AsyncClient in this process, on the same "
        "cores as the server; batch sizes = the server's /v1/stats histogram over the run "
        "(size:count)",
    )
    for c in ("server", "clients", "scans/s", "p50 ms", "p99 ms", "errors", "batch sizes"):
        t.add_column(c, justify="right")
    t.add_column("mean batch", justify="right")
    for name, rec in res["servers"].items():
        for r in rec.get("throughput", []):
            t.add_row(
                name,
                str(r["clients"]),
                f"{r['scans_per_s']:.2f}",
                f"{r['latency_ms']['p50']:.0f}",
                f"{r['latency_ms']['p99']:.0f}",
                str(sum(r["errors"].values())),
                " ".join(f"{s}:{c}" for s, c in r["batch_size_histogram"].items()),
                f"{r['mean_batch']:.2f}",
            )
    console.print(t)


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


# ---- summary --------------------------------------------------------------------------------


def summarise(record: dict[str, Any]) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []

    def verdict(ok: bool | None) -> str:
        return "not measured" if ok is None else ("met" if ok else "not met")

    http = record.get("http")
    if http:
        servers = http["servers"]
        for name, rec in servers.items():
            r = rec["overhead"]["ratio"]
            rows.append(
                {
                    "goal": f"HTTP overhead ratio ≤ {RATIO_GOAL} ({name})",
                    "measured": f"{r:.3f}",
                    "status": verdict(r <= RATIO_GOAL),
                }
            )
            o = rec["overhead"]
            if "http_over_sgemm" in o:
                q = o["http_over_sgemm"]
                rows.append(
                    {
                        "goal": f"HTTP scan → descriptor ≤ {SGEMM_GOAL}× the sgemm ({name})",
                        "measured": f"{o['http_ms']['median']:.1f} ÷ "
                        f"{o['sgemm_ms']['median']:.2f} ms = {q:.1f}",
                        "status": verdict(q <= SGEMM_GOAL),
                    }
                )
        with_b = servers.get("batching", {}).get("throughput", [])
        without = servers.get("no batching", {}).get("throughput", [])
        for a, b in zip(with_b, without, strict=False):
            rows.append(
                {
                    "goal": f"throughput, {a['clients']} client(s): with ÷ without micro-batching",
                    "measured": f"{a['scans_per_s']:.2f} ÷ {b['scans_per_s']:.2f} = "
                    f"{a['scans_per_s'] / b['scans_per_s']:.2f}",
                    "status": "info",
                }
            )
    search = record.get("search")
    if search:
        main = search["datasets"][search["main_dataset"]]
        all_reach = all(r["ivf"]["chosen_reaches_goal"] for r in main.values())
        detail = ", ".join(
            f"{int(n):,}: nprobe {r['ivf']['chosen_nprobe']}"
            + ("" if r["ivf"]["chosen_reaches_goal"] else " (max; not reached)")
            for n, r in main.items()
        )
        rows.append(
            {
                "goal": f"IVF recall@10 ≥ {RECALL_GOAL} ({search['main_dataset']})",
                "measured": detail,
                "status": verdict(all_reach),
            }
        )
        big = main.get("1000000")
        if big is None:
            rows.append(
                {
                    "goal": f"IVF p50 < {P50_GOAL_MS} ms at 1M at recall@10 ≥ {RECALL_GOAL}",
                    "measured": "1M not in --sizes",
                    "status": verdict(None),
                }
            )
        else:
            ivf = big["ivf"]
            p50 = ivf["nprobe"][ivf["chosen_nprobe"]]["p50_ms"]
            ok = ivf["chosen_reaches_goal"] and p50 < P50_GOAL_MS
            rows.append(
                {
                    "goal": f"IVF p50 < {P50_GOAL_MS} ms at 1M at recall@10 ≥ {RECALL_GOAL}",
                    "measured": f"{p50:.3f} ms at nprobe {ivf['chosen_nprobe']} (recall "
                    f"{ivf['nprobe'][ivf['chosen_nprobe']]['recall_at_10']:.3f})",
                    "status": verdict(ok),
                }
            )
        for n, r in main.items():
            row = r["ivf"]["nprobe"].get(SERVICE_NPROBE)
            if row:
                rows.append(
                    {
                        "goal": f"service default nprobe {SERVICE_NPROBE} at {int(n):,}",
                        "measured": f"p50 {row['p50_ms']:.3f} ms, recall@10 "
                        f"{row['recall_at_10']:.3f} (flat p50 {r['flat']['p50_ms']:.3f} ms)",
                        "status": "info",
                    }
                )
    for part in ("http", "search"):
        load = record.get(part, {}).get("other_cpu_fraction", {}).get("during")
        if load is not None:
            rows.append(
                {
                    "goal": f"quiet machine during the {part} part (other processes < 10% CPU)",
                    "measured": f"{100 * load:.0f}% of the CPU used by other processes",
                    "status": verdict(load < 0.1),
                }
            )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--quick", action="store_true", help="short run: fewer reps, smaller sizes")
    ap.add_argument("--sizes", help="keyframe counts for search [1e4,1e5,1e6; quick: 1e4,1e5]")
    ap.add_argument("--hard-sizes", help="sizes for the hard-case data sets [100000]")
    ap.add_argument("--views", type=int, default=10, help="keyframes per place (main data set)")
    ap.add_argument("--reps", type=int, help="sequential overhead reps per side [40; quick 12]")
    ap.add_argument("--duration", type=float, help="seconds per throughput run [10; quick 3]")
    ap.add_argument("--queries", type=int, help="search queries per size [200; quick 100]")
    ap.add_argument("--skip-http", action="store_true")
    ap.add_argument("--skip-search", action="store_true")
    ap.add_argument("--out", "--json", type=Path, default=ROOT / "bench-results" / "service.json")
    args = ap.parse_args()
    q = args.quick
    sizes = args.sizes or ("10000,100000" if q else "10000,100000,1000000")
    args.sizes = [int(float(s)) for s in sizes.split(",")]
    args.hard_sizes = [int(float(s)) for s in (args.hard_sizes or "100000").split(",")]
    args.reps = args.reps or (12 if q else 40)
    args.duration = args.duration or (3.0 if q else 10.0)
    args.queries = args.queries or (100 if q else 200)
    # a pipe or a log file gets 132 columns, not rich's 80, so the tables stay readable
    console = Console() if sys.stdout.isatty() else Console(width=132)

    record: dict[str, Any] = {
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor(),
            "cores": CORES,
            "python": platform.python_version(),
        },
        "onnxruntime": ort.__version__,
        "faiss": faiss.__version__,
        "httpx": httpx.__version__,
        "quick": q,
    }
    for part, skip, run, show in (
        ("http", args.skip_http, http_part, print_http),
        ("search", args.skip_search, search_part, print_search),
    ):
        if skip:
            continue
        probe = OtherLoad()
        time.sleep(1.0)
        before = other_load(console, part, probe, "before")
        watch = OtherLoad()
        record[part] = run(args, console)
        record[part]["other_cpu_fraction"] = {
            "before": before,
            "during": other_load(console, part, watch, "during"),
        }
        show(record[part], console)
    record["summary"] = summarise(record)
    t = Table(title="Summary (from this run's measurements)")
    for c in ("goal", "measured", "status"):
        t.add_column(c)
    for r in record["summary"]:
        colour = {"met": "green", "not met": "red"}.get(r["status"], "white")
        t.add_row(r["goal"], r["measured"], f"[{colour}]{r['status']}[/]")
    console.print(t)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(record, indent=2) + "\n")
    console.print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
