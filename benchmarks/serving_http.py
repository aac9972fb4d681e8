"""Parts 1 and 2 of ``benchmarks/serving.py``: HTTP overhead against the bare encoder (and a
0.47-GMAC sgemm as this machine's yardstick), and throughput under 1, 4 and 8 clients."""

from __future__ import annotations

import argparse
import asyncio
import os
import time
from collections import Counter
from typing import Any

import httpx
import numpy as np
from bench_kit import MODEL, pct, scan_bodies, server
from rich.console import Console
from rich.table import Table
from transport_floor import floor_server

from overlapmamba.core.io import decode
from overlapmamba.service.encoder import Encoder
from overlapmamba.service.settings import BatchSettings
from overlapmamba.service.threads import encoder_threads

HEADERS = {"Content-Type": "application/octet-stream", "X-Point-Fields": "xyzi"}
RATIO_GOAL = 1.10
# A yardstick of this machine's speed, timed in the same run: a 0.47-GMAC float32 matrix
# product (numpy's BLAS, all cores). Goal: HTTP scan → descriptor ≤ 9× its time.
SGEMM = ((1024, 512), (512, 900))
SGEMM_GOAL = 9.0
DEFAULTS = BatchSettings()  # the service's own defaults, reported, not assumed


# ---- part 1: HTTP overhead ------------------------------------------------------------------


def overhead(
    enc: Encoder, body: bytes, url: str, floor_url: str, reps: int, block: int = 4
) -> dict[str, Any]:
    """Bare and HTTP scan → descriptor, the transport floor (``transport_floor``: the same
    body to a server that only waits as long as the bare path) and the sgemm yardstick, in
    alternating blocks of ``block`` calls."""
    stages: dict[str, list[float]] = {"decode": [], "project": [], "encode": []}
    rng = np.random.default_rng(0)
    ma, mb = (rng.standard_normal(shape, dtype=np.float32) for shape in SGEMM)

    def sgemm() -> None:
        np.matmul(ma, mb)

    def bare() -> None:
        t0 = time.perf_counter()
        points = decode(body, "raw", fields="xyzi")
        t1 = time.perf_counter()
        image, offset = enc.project_offset(points)
        t2 = time.perf_counter()
        desc, _ = enc.encode(image[None], np.array([offset]))
        t3 = time.perf_counter()
        assert desc.shape == (1, enc.dim)
        for k, v in zip(stages, (t1 - t0, t2 - t1, t3 - t2), strict=True):
            stages[k].append(v * 1e3)

    server_t: list[dict[str, float]] = []
    floor_gap: list[float] = []
    b: list[float] = []
    with (
        httpx.Client(base_url=url, timeout=60) as client,
        httpx.Client(base_url=floor_url, timeout=60) as floor_client,
    ):

        def floor() -> None:
            wait_ms = float(np.median(b)) if b else 16.0  # as long as the bare path takes
            t = time.perf_counter()
            r = floor_client.post(f"/floor?wait_ms={wait_ms:.3f}", content=body, headers=HEADERS)
            r.raise_for_status()
            out = r.json()
            floor_gap.append((time.perf_counter() - t) * 1e3 - out["waited_ms"])
            assert out["bytes"] == len(body) and len(out["descriptor"]) == enc.dim

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
            floor()
        for v in stages.values():
            v.clear()
        server_t.clear()
        floor_gap.clear()
        h: list[float] = []
        f: list[float] = []
        g: list[float] = []
        sgemm()
        while len(b) < reps:
            # a pause at each switch lets the other side's onnxruntime threads stop spinning
            for fn, out in ((bare, b), (http, h), (floor, f), (sgemm, g)):
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
    # the same for a server doing nothing: client, transfer, uvicorn, waking after the wait
    res["floor_gap_ms"] = {"median": pct(floor_gap, 50), "p90": pct(floor_gap, 90)}
    res["floor_ratio"] = (pct(b, 50) + pct(floor_gap, 50)) / pct(b, 50)
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
    # the bare side with the threads a server's encoder call gets by default (a lane a core,
    # one thread each on 2 cores): the ratio is then the HTTP path's, not a thread count's
    lanes, per_call = encoder_threads(DEFAULTS.lanes, DEFAULTS.intra_op_threads)
    enc = Encoder(MODEL, intra_op_threads=per_call)
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
        "defaults": {
            "max_batch": DEFAULTS.max_batch,
            "max_wait_ms": DEFAULTS.max_wait_ms,
            "lanes": lanes,
        },
        "load_average_at_start": os.getloadavg(),
        "servers": {},
    }
    for name, env, load in configs:
        console.print(f"starting server: {name} {env or ''} …")
        t = time.perf_counter()
        with server(env) as url, floor_server() as floor_url:
            ready_s = time.perf_counter() - t
            console.print(f"  ready in {ready_s:.1f} s; sequential overhead ({args.reps} reps) …")
            rec: dict[str, Any] = {"env": env, "ready_s": ready_s, "loadavg": os.getloadavg()}
            rec["overhead"] = overhead(enc, body, url, floor_url, args.reps)
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
        f"onnxruntime {res['intra_op_threads']} intra-op threads a call on both sides "
        f"(the server: {d.get('lanes', '?')} lanes). Servers: "
        f"batching = the defaults (max_batch {d['max_batch']}, max_wait_ms "
        f"{d['max_wait_ms']:g}); wait 0 = OVERLAPMAMBA_BATCHING__MAX_WAIT_MS=0; no batching "
        "= OVERLAPMAMBA_BATCHING__MAX_BATCH=1. Stages dec/proj/enc are medians; rest = HTTP "
        "median − the server's own stage medians (HTTP, transfer, routing, JSON); floor = the "
        "same for a server that only reads the body and waits as long as bare (no work), "
        "floor ratio = (bare + floor) ÷ bare: the lowest ratio this client and uvicorn allow.",
    )
    cols = ["server", "bare ms med/p90", "HTTP ms med/p90", f"ratio (≤ {RATIO_GOAL})"]
    cols += ["bare dec/proj/enc", "server dec/proj/enc", "rest ms", "floor ms", "floor ratio"]
    cols += [f"÷ sgemm (≤ {SGEMM_GOAL:g})"]
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
            f"{o['floor_gap_ms']['median']:.1f}",
            f"{o['floor_ratio']:.3f}",
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
