"""The place-recognition service: HTTP overhead, throughput under concurrency, index search.

1. **HTTP overhead** — scan → descriptor through a real ``overlapmamba serve`` (uvicorn in a
   subprocess, temporary data folder) against the bare encoder in this process, in the same
   run: bare = ``overlapmamba.core.io.decode`` + ``Encoder.project`` + ``Encoder.encode`` at B = 1;
   HTTP = ``POST /v1/descriptors`` with the same body (``application/octet-stream``,
   ``X-Point-Fields: xyzi``) over one keep-alive httpx connection, sequentially, descriptor
   JSON parsed. The two are timed in alternating blocks so drift hits both alike. Ratio =
   HTTP median ÷ bare median; goal ≤ 1.10. A third block posts the same body to
   ``transport_floor.py`` (uvicorn, a route that reads the body and only waits as long as the
   bare path): its HTTP time less its wait is the transport's floor on this machine, and
   (bare + floor) ÷ bare the lowest ratio any server on this client and uvicorn could reach.
   A fourth block times a 1024×512 @ 512×900 float32 matrix product (0.47 GMAC, numpy's
   BLAS): HTTP ÷ sgemm says how the whole path compares with this machine's dense
   arithmetic (goal ≤ 9). Servers: the defaults (micro-batching, ``max_batch`` 2 a lane
   since 2026-12-01, 8 before, ``max_wait_ms`` 2), ``max_wait_ms`` 0, and ``max_batch`` 1.
2. **Throughput** — 1, 4 and 8 concurrent clients (tasks sharing one httpx AsyncClient)
   posting scans for a fixed time: scans/s, latency p50/p99 and the server's encoder batch
   sizes (the ``/v1/stats`` histogram, before/after difference), with micro-batching (the
   defaults) and without (``OVERLAPMAMBA_BATCHING__MAX_BATCH=1``). The clients share this
   machine's cores with the server.
3. **Search** — ``overlapmamba.service.backends.faiss.index.VectorIndex`` in process, 256-d float32
unit
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
numbers), and writes JSON (default reports/service/bench.json; a part skipped with
``--skip-http`` or ``--skip-search`` keeps its last measurement there, ``parts_measured``
saying which run each part is from). ``--quick``: sizes 10k and
100k, 12 overhead reps, 3 s per throughput run, 100 queries.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path
from typing import Any

import faiss
import httpx
import onnxruntime as ort
from bench_kit import CORES, OtherLoad, other_load
from reports_kit import REPORTS, provenance, shown_path, write_report
from rich.console import Console
from rich.table import Table
from serving_http import RATIO_GOAL, SGEMM_GOAL, http_part, print_http
from serving_search import P50_GOAL_MS, RECALL_GOAL, SERVICE_NPROBE, print_search, search_part

# ---- summary --------------------------------------------------------------------------------


def _nprobe(ivf: dict[str, Any]) -> dict[int, Any]:
    """An IVF sweep's rows by nprobe, as ints also where the part was read back from JSON
    (a part kept from an earlier run)."""
    return {int(k): v for k, v in ivf["nprobe"].items()}


def summarise(record: dict[str, Any]) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []

    def verdict(ok: bool | None) -> str:
        return "not measured" if ok is None else ("met" if ok else "not met")

    http = record.get("http")
    if http:
        servers = http["servers"]
        for name, rec in servers.items():
            r = rec["overhead"]["ratio"]
            floor = rec["overhead"].get("floor_ratio")
            rows.append(
                {
                    "goal": f"HTTP overhead ratio ≤ {RATIO_GOAL} ({name})",
                    "measured": f"{r:.3f}"
                    + (f" (transport floor {floor:.3f})" if floor is not None else ""),
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
            p50 = _nprobe(ivf)[ivf["chosen_nprobe"]]["p50_ms"]
            ok = ivf["chosen_reaches_goal"] and p50 < P50_GOAL_MS
            rows.append(
                {
                    "goal": f"IVF p50 < {P50_GOAL_MS} ms at 1M at recall@10 ≥ {RECALL_GOAL}",
                    "measured": f"{p50:.3f} ms at nprobe {ivf['chosen_nprobe']} (recall "
                    f"{_nprobe(ivf)[ivf['chosen_nprobe']]['recall_at_10']:.3f})",
                    "status": verdict(ok),
                }
            )
        for n, r in main.items():
            row = _nprobe(r["ivf"]).get(SERVICE_NPROBE)
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
    ap.add_argument("--out", "--json", type=Path, default=REPORTS / "service" / "bench.json")
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
    # A part skipped keeps the last measurement of it in --out, saying so (parts_measured).
    previous = json.loads(args.out.read_text()) if args.out.is_file() else {}
    this_run = provenance()
    measured: dict[str, str] = {}
    for part, skip, run, show in (
        ("http", args.skip_http, http_part, print_http),
        ("search", args.skip_search, search_part, print_search),
    ):
        if skip:
            if part in previous:
                record[part] = previous[part]
                was = previous.get("parts_measured", {}).get(part) or (
                    f"{previous['date'][:10]}, {previous['command']}"
                    if "date" in previous
                    else "an earlier run of benchmarks/serving.py"
                )
                measured[part] = f"kept from {shown_path(args.out)} ({was})"
            continue
        measured[part] = f"{str(this_run['date'])[:10]}, {this_run['command']}"
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
    record["parts_measured"] = measured
    record["summary"] = summarise(record)
    t = Table(title="Summary (from this run's measurements)")
    for c in ("goal", "measured", "status"):
        t.add_column(c)
    for r in record["summary"]:
        colour = {"met": "green", "not met": "red"}.get(r["status"], "white")
        t.add_row(r["goal"], r["measured"], f"[{colour}]{r['status']}[/]")
    console.print(t)
    write_report(args.out, record)
    console.print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
