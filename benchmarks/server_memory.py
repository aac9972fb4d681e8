"""A real server's resident memory under concurrent scan queries, as its own ``/metrics``
reports it (``process_resident_memory_bytes``): when ready, then after each round of queries;
and its registration processes' (``overlapmamba_registration_resident_bytes``), which that
leaves out.

    python benchmarks/server_memory.py [--rounds 12] [--per-round 96] [--clients 16]

Each round sends ``--per-round`` scan queries (KITTI 00 frames, ``POST /v1/maps/m/query``)
from ``--clients`` threads at once, so every encoder lane runs full batches
(``batching.max_batch``, the shipped model's three views a scan). Measured three times, each
on a fresh server: with the service's defaults, with glibc's malloc held to two arenas
(``MALLOC_ARENA_MAX=2``; by default glibc gives up to eight a core, one per thread that
allocates, and memory freed in one arena is not reused by the others), and with batches of
8 scans (the default before it became 2). What it answers: how much memory a node needs at
the default batching, and whether it levels off (a leak would grow by the same amount every
round). Writes ``reports/service/server-memory.json``.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import sys
import time
from typing import Any

import httpx
from bench_kit import scan_bodies, server
from reports_kit import REPORTS, ROOT, write_report
from rich.console import Console

from overlapmamba.service.settings import BatchSettings

sys.path.insert(0, str(ROOT / "tests"))
from e2e_kit import resident_mb

CONFIGS = {
    "defaults": {},
    "MALLOC_ARENA_MAX=2": {"MALLOC_ARENA_MAX": "2"},
    # glibc's mmap threshold fixed at its initial 128 KiB: large blocks are never taken from
    # the heap, which the registration process needed to stay flat (service/registrar.py)
    "MALLOC_MMAP_THRESHOLD_=131072": {"MALLOC_MMAP_THRESHOLD_": "131072"},
    # the batches the service encoded before they became 2 a lane (batching.max_batch)
    "OVERLAPMAMBA_BATCHING__MAX_BATCH=8": {"OVERLAPMAMBA_BATCHING__MAX_BATCH": "8"},
}


def measure(env: dict[str, str], bodies: list[bytes], args: argparse.Namespace) -> dict[str, Any]:
    with server(env) as url, httpx.Client(base_url=url, timeout=120) as c:
        assert c.put("/v1/maps/m").status_code == 201
        ready, _ = resident_mb(c)
        if ready is None:
            raise SystemExit("the server's /metrics has no process_resident_memory_bytes (Linux)")

        def query(i: int) -> int:
            r = c.post(
                "/v1/maps/m/query",
                params={"k": 5},
                content=bodies[i % len(bodies)],
                headers={"Content-Type": "application/octet-stream"},
            )
            return r.status_code

        rounds = []
        with cf.ThreadPoolExecutor(args.clients) as pool:
            for n in range(args.rounds):
                t0 = time.perf_counter()
                codes = list(pool.map(query, range(n * args.per_round, (n + 1) * args.per_round)))
                seconds = time.perf_counter() - t0
                own, children = resident_mb(c)  # children: its registration processes'
                rounds.append(
                    {
                        "resident_mb": own,
                        "registration_mb": children,
                        "queries_per_s": args.per_round / seconds,
                        "errors": sum(code != 200 for code in codes),
                    }
                )
    return {"env": env, "ready_mb": ready, "rounds": rounds}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=12)
    ap.add_argument("--per-round", type=int, default=96)
    ap.add_argument("--clients", type=int, default=16)
    ap.add_argument("--out", default=str(REPORTS / "service" / "server-memory.json"))
    args = ap.parse_args()
    console = Console()
    bodies, source = scan_bodies(16)
    results = {}
    for name, env in CONFIGS.items():
        results[name] = r = measure(env, bodies, args)
        rss = [round(x["resident_mb"]) for x in r["rounds"]]
        console.print(f"{name}: ready {r['ready_mb']:.0f} MB, after each round {rss} MB")
    from pathlib import Path

    write_report(
        Path(args.out),
        {
            "scans": source,
            "rounds": args.rounds,
            "per_round": args.per_round,
            "clients": args.clients,
            "max_batch": BatchSettings().max_batch,
            "configs": results,
        },
    )
    console.print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
