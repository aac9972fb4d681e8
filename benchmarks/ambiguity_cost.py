"""What the ambiguity check (``verify.ambiguity_margin``) costs the verify stage, as the service
runs it.

Every ``--every``-th query of each town (``town_kit``: the shipped encoder, the service's
order), its candidates go through the service's verify stage
(``overlapmamba.service.verify.verify_candidates``, the file's own settings: the gate,
``stop_at_first``, the margin) three ways, one after the other on the same prepared query,
in an order that turns with each query:

- ``off``: no check (``verify.ambiguity_margin`` off);
- ``served``: the check as served: a turn registered only where its seed could rival;
- ``every_turn``: the check registering every turn (what it did before the screen).

Reported per way: the stage's time a query (mean, p50, p90; one thread, as served), GICP
runs a query (each ``small_gicp.align`` counted), closures accepted; and the queries whose
verdicts the two checks decided differently. In-process and on one core's work, it isolates
what the end-to-end run (``tests/test_e2e_load.py``) cannot: that run's throughput moves by
more between runs of the same hour than the check costs.

    python benchmarks/ambiguity_cost.py --model models/overlapmamba-hdl64-one-pass.onnx \\
        --town data/synth/test --json reports/service/ambiguity-cost-one-pass.json

≈ 3 min a 2,000-scan town on 2 cores. Time nothing else beside it.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np
from bench_kit import ROOT, AlignCounter, model_record, served_rerank, served_settings
from reports_kit import REPORTS, write_report
from rich.console import Console
from rich.table import Table
from town_kit import encode_town
from tqdm import tqdm

from overlapmamba.service.encoder import Encoder
from overlapmamba.service.verify import params_of, verify_candidates

WAYS = ("off", "served", "every_turn")


def run_town(enc: Encoder, path: Path, every: int) -> dict[str, Any]:
    served = served_settings(enc.meta)
    v = served.verify
    if v.ambiguity_margin is None:
        raise SystemExit(f"{enc.model_id} carries no ambiguity margin: nothing to compare")
    t = encode_town(enc, path, params_of(v), served_rerank(enc.meta))
    off = v.model_copy(update={"ambiguity_margin": None})
    settings = {"off": off, "served": v, "every_turn": v}
    ms: dict[str, list[float]] = {w: [] for w in WAYS}
    gicp = dict.fromkeys(WAYS, 0)
    accepted = dict.fromkeys(WAYS, 0)
    differ = 0
    queries = range(t.recent + 1, len(t.seq), every)
    with AlignCounter() as count:
        for n, i in enumerate(tqdm(queries, desc=f"verify {path.name}", unit="query")):
            top, deg = t.order(i, v.candidates)
            cands = [
                (t.blobs[j], float(a), float(np.sqrt(t.d2[i, j])))
                for j, a in zip(top, deg, strict=True)
            ]
            verified = {}
            for way in WAYS[n % 3 :] + WAYS[: n % 3]:
                t.prepared[i].spectra.clear()  # each way turns the query's grid itself
                before = count.calls
                t0 = time.perf_counter()
                out = verify_candidates(
                    t.prepared[i], cands, settings[way], screen=way != "every_turn"
                )
                ms[way].append((time.perf_counter() - t0) * 1e3)
                gicp[way] += count.calls - before
                accepted[way] += any(x.verified for x in out)
                verified[way] = [x.verified for x in out]
            differ += verified["served"] != verified["every_turn"]
            t.prepared[i].spectra.clear()
    q = len(ms["off"])
    ways = {
        w: {
            "ms_mean": float(np.mean(ms[w])),
            "ms_p50": float(np.median(ms[w])),
            "ms_p90": float(np.percentile(ms[w], 90)),
            "gicp_per_query": gicp[w] / q,
            "accepted": accepted[w],
        }
        for w in WAYS
    }
    return {"town": path.name, "queries": q, "ways": ways, "decided_differently": differ}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, default=ROOT / "models" / "overlapmamba-hdl64.onnx")
    ap.add_argument("--town", type=Path, action="append", required=True)
    ap.add_argument("--every", type=int, default=2, help="every N-th query (default 2)")
    ap.add_argument("--json", type=Path, default=REPORTS / "service" / "ambiguity-cost.json")
    args = ap.parse_args()
    if args.every < 1:
        ap.error(f"--every must be at least 1, not {args.every}")
    enc = Encoder(args.model)
    v = served_settings(enc.meta).verify
    towns = [run_town(enc, town, args.every) for town in args.town]
    report = {**model_record(args.model, enc), "verify": v.model_dump(), "towns": towns}
    write_report(args.json, report)
    table = Table(title=f"the verify stage a query, margin {v.ambiguity_margin:g} ({enc.model_id})")
    for col in ("town", "way", "ms mean", "ms p50", "ms p90", "GICP a query", "accepted"):
        table.add_column(col, justify="right")
    for r in towns:
        for w, x in r["ways"].items():
            table.add_row(
                r["town"],
                w,
                f"{x['ms_mean']:.2f}",
                f"{x['ms_p50']:.2f}",
                f"{x['ms_p90']:.2f}",
                f"{x['gicp_per_query']:.2f}",
                str(x["accepted"]),
            )
    Console(width=160).print(table)
    for r in towns:
        print(
            f"{r['town']}: {r['decided_differently']} of {r['queries']} queries decided otherwise"
        )
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
