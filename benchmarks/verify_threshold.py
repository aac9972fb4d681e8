"""Calibrate and measure verified loop closures on synthetic towns.

Per town, as the service does it: every scan is encoded by the shipped ONNX encoder
(``overlapmamba.service.encoder.Encoder``) and kept as a keyframe's compact geometry
(``overlapmamba.core.geometry``); each query (the loop-closure protocol of
``overlapmamba.core.metrics``:
the database is every frame more than ``exclude_recent_frames`` earlier) takes its top
``--candidates`` in the service's order (the ``rerank.shortlist`` nearest descriptors re-ranked by
d² − weight · aligned yaw-feature correlation: ``overlapmamba.service.ranking``; ``--rerank off``
for the descriptor order), seeds each with the yaw from the yaw features and registers it
(``overlapmamba.service.verify.verify_candidates``). Every candidate is registered; the
closure is scored both ways the service can answer: the first verified candidate in the
answer's order (``verify.stop_at_first``, the default; ``verified_stop_at_first``) and the
verified candidate of highest fitness (``verified``). It is **correct** when its relative
pose is right: within 1 m and 2° of the poses' T = P_keyframe⁻¹ · P_query (an edge a pose
graph can take). Also reported: the precision counting
only pairs the town's ground truth calls loops (overlap above its
``min_overlap``, 0.3) as correct — stricter, since a registration can be exact on a pair
that shares less. Recall: queries with a ground-truth loop whose closure is correct and a
loop, over all queries with a loop (what the descriptor's Recall@5 bounds).

``--across`` adds the calibration town's pairs of drives by the issue's five sensors (a query
of one against another's map: ``benchmarks/verify_across.py``) to what is calibrated on;
``--each`` asks the precision target of each town and each pair, not only of all queries
together: a fleet whose every sensor pair must be safe. The fitness and rmse thresholds and
the ambiguity margin are then chosen together (``verify_rules.joint``): the triple of highest recall
that holds the target everywhere; the gate and a larger margin follow as below.

``--calibrate`` (the validation town only): sweeps the fitness and rmse thresholds and picks
the pair of highest recall whose precision is at least ``--target`` (0.99) under both ways
of choosing the closure, then the nearest descriptor gate that costs at most 0.005 of that
recall (precision at the target both ways too), then the largest ambiguity margin that
costs at most 0.005 more (each candidate the sweep may accept registered from the other
quarter turns too: ``overlapmamba.service.verify.rival_fitness``): the service's
``verify.min_fitness``, ``verify.max_rmse_m``, ``verify.gate_distance`` and
``verify.ambiguity_margin``; with ``--write-calibration`` they are recorded in the model
file, which the service takes them from. Without it, the thresholds in force
(``--min-fitness``, ``--max-rmse``, ``--gate-distance``, ``--ambiguity-margin``, default
the ones the service answers with for ``--model``: its file's calibration) are scored on
each town given: precision, recall against the answer's Recall@1 and Recall@5 on the same
queries (the candidates in the service's order), pose errors, and the time per query. Each
town's scans enter the model as its sensor's (its manifest's), as the service projects a
scan that names its sensor. Prints tables, writes JSON.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
from bench_kit import (
    ROOT,
    provenance,
    served_rerank,
    served_settings,
    write_calibration,
)
from closure_kit import candidate, descriptor_recall, recorded_rival, score
from reports_kit import REPORTS, write_report
from rich.console import Console
from rich.table import Table
from town_kit import encode_town
from tqdm import tqdm
from verify_rules import FITNESS, calibrate

from overlapmamba.core.rerank import Rerank
from overlapmamba.service.encoder import Encoder
from overlapmamba.service.settings import VerifySettings
from overlapmamba.service.verify import params_of, verify_candidates


def run_town(
    enc: Encoder,
    path: Path,
    k: int,
    v: VerifySettings,
    rerank: Rerank,
    batch: int = 8,
    rivals_from: float | None = None,
) -> dict[str, Any]:
    """Every query's candidates: rank, correctness, fitness, rmse, pose errors. Each is
    registered whatever ``v.stop_at_first`` says: :func:`score` answers both ways from them.
    ``rivals_from``: each candidate whose fitness reaches it is registered again from the other
    quarter turns too, as the service does one that passes its thresholds with
    ``verify.ambiguity_margin`` (``closure_kit.recorded_rival``: its ``rival`` and
    ``turns``; every turn, where the service screens those that cannot rival; timed with the
    query)."""
    v = v.model_copy(update={"stop_at_first": False})
    params = params_of(v)
    t = encode_town(enc, path, params, rerank, batch)
    seq, prepared, blobs, d2 = t.seq, t.prepared, t.blobs, t.d2
    positives = t.truth.positives()
    queries = []
    ms = []
    for i in tqdm(range(t.recent + 1, len(seq)), desc=f"verify {path.name}", unit="query"):
        top, deg = t.order(i, k)
        t0 = time.perf_counter()
        verdicts = verify_candidates(
            prepared[i],
            [(blobs[j], float(a), float(np.sqrt(d2[i, j]))) for j, a in zip(top, deg, strict=True)],
            v,
        )
        rivals = [
            recorded_rival(prepared[i], blobs[j], float(a), x, params, rivals_from)
            for j, a, x in zip(top, deg, verdicts, strict=True)
        ]
        ms.append((time.perf_counter() - t0) * 1e3)
        prepared[i].spectra.clear()  # the query's turned spectra serve its own registrations
        pos = set(positives[i].tolist())
        cands = [
            candidate(
                j, float(np.sqrt(d2[i, j])), int(j) in pos, verdict, seq.poses[j], seq.poses[i]
            )
            | {"seed_deg": float(a)}
            | rival
            for j, verdict, a, rival in zip(top, verdicts, deg, rivals, strict=True)
        ]
        queries.append(
            {"query": i, "has_loop": bool(len(pos)), "candidates": cands, "group": path.name}
        )
    return {
        "town": str(path),
        "descriptors": t.desc,  # (N, D): the loop-closure metrics of the same answers
        "yaw_features": t.yaw,  # (N, C, W) float16, as the store keeps them
        "sensor": t.sensor.sensor.name,
        "input": t.sensor.kind,
        "frames": len(seq),
        "exclude_recent": t.recent,
        "queries": queries,
        "verify_ms": ms,
        "geometry_bytes": [len(b) for b in blobs if b is not None],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, default=ROOT / "models" / "overlapmamba-hdl64.onnx")
    pre, _ = ap.parse_known_args()
    enc = Encoder(pre.model)
    served = served_settings(enc.meta)  # the model file's calibration, else the defaults
    ap.add_argument("--town", type=Path, action="append", help="default: data/synth/val")
    ap.add_argument("--calibrate", action="store_true", help="sweep the thresholds (val only)")
    ap.add_argument(
        "--write-calibration",
        action="store_true",
        help="with --calibrate: record the chosen thresholds in the model file",
    )
    ap.add_argument("--target", type=float, default=0.99, help="precision to calibrate for")
    ap.add_argument(
        "--candidates", type=int, default=served.verify.candidates, help="registered per query"
    )
    ap.add_argument("--min-fitness", type=float, default=served.verify.min_fitness)
    ap.add_argument("--max-rmse", type=float, default=served.verify.max_rmse_m)
    ap.add_argument("--gate-distance", type=float, default=served.verify.gate_distance)
    ap.add_argument(
        "--ambiguity-margin",
        type=lambda s: None if s == "off" else float(s),
        default=served.verify.ambiguity_margin,
        help="MARGIN or off (default: the service's verify.ambiguity_margin)",
    )
    ap.add_argument(
        "--json",
        type=Path,
        help="default reports/service/verify_threshold.json calibrating, else verify-test.json",
    )
    default_rerank = f"{served.rerank.shortlist},{served.rerank.weight:g}"
    ap.add_argument(
        "--rerank", default=default_rerank, help="K,WEIGHT or off (default: the service's)"
    )
    ap.add_argument(
        "--across",
        action="store_true",
        help="with --calibrate: also the calibration town's pairs of drives by the issue's "
        "five sensors, each query against another drive's map (benchmarks/verify_across.py), "
        "so that the thresholds hold for a map by one sensor and a query by another",
    )
    ap.add_argument(
        "--each",
        action="store_true",
        help="with --calibrate: the precision target must hold on each town and each pair "
        "of drives, not only over all of them (a fleet's every sensor pair is safe)",
    )
    args = ap.parse_args()
    towns = args.town or [ROOT / "data" / "synth" / "val"]
    if args.each and not args.calibrate:
        ap.error("--each is a calibration rule: give it with --calibrate")
    if args.across and not args.calibrate:
        ap.error("--across adds calibration data: give it with --calibrate")
    if args.calibrate and any(t.name.startswith("test") for t in towns):
        ap.error("calibrate on the validation town, never on a test town")
    if args.write_calibration and not args.calibrate:
        ap.error("--write-calibration records what --calibrate chose: give both")
    console = Console()
    # record everything; calibrating, register every candidate too (the gate is swept after)
    register_within = None if args.calibrate else args.gate_distance
    v = VerifySettings(
        candidates=args.candidates, min_fitness=0.0, max_rmse_m=1e9, gate_distance=register_within
    )
    rerank = served_rerank(enc.meta, args.rerank)  # its score as the service scores
    # each candidate that may pass is registered against its rivals too: calibrating, every one
    # the fitness sweep may accept; measuring, those the served thresholds do, with the margin
    rivals_from = FITNESS[0] if args.calibrate else None
    if not args.calibrate and args.ambiguity_margin is not None:
        rivals_from = args.min_fitness
    results = [run_town(enc, t, args.candidates, v, rerank, rivals_from=rivals_from) for t in towns]
    in_force = {  # the thresholds scored: the file's calibration unless given
        "min_fitness": args.min_fitness,
        "max_rmse_m": args.max_rmse,
        "gate_distance": args.gate_distance,
        "ambiguity_margin": args.ambiguity_margin,
    }
    report: dict[str, Any] = {
        **provenance(),
        "model_id": enc.model_id,
        "candidates": args.candidates,
        "rerank": asdict(rerank),
        "towns": [],
    }
    if args.calibrate:
        queries = [q for r in results for q in r["queries"]]
        pairs: list[str] = []
        if args.across:  # the calibration town's drives, pair by pair, as the service answers
            from verify_across import val_pair_queries

            across, pairs = val_pair_queries(enc, v, rerank, rivals_from=rivals_from)
            report["across"] = {"pairs": pairs, "queries": len(across)}
            queries += across
        out = calibrate(queries, args.target, args.each, in_force)
        cal = report["calibration"] = out["calibration"]
        report |= {key: val for key, val in out.items() if key != "calibration"}
        chosen, gate, margin = cal["chosen"], cal.get("gate"), cal.get("ambiguity")
        table = Table(title=f"verified closures on {', '.join(t.name for t in towns)}")
        for col in (
            "min fitness",
            "max rmse",
            "accepted",
            "precision",
            "prec. (gt loops)",
            "recall",
        ):
            table.add_column(col, justify="right")
        for s in out["sweep"]:
            if s["max_rmse_m"] == 1e9 or s is chosen:
                table.add_row(
                    f"{s['min_fitness']:.2f}",
                    "—" if s["max_rmse_m"] == 1e9 else f"{s['max_rmse_m']:.1f}",
                    str(s["accepted"]),
                    f"{s['precision']:.3f}",
                    f"{s['precision_ground_truth_loops']:.3f}",
                    f"{s['recall']:.3f}",
                )
        console.print(table)
        console.print(f"chosen for precision ≥ {args.target}: {chosen}")
        if chosen is not None:
            console.print(f"descriptor gate: {gate}")
        if gate is not None:
            console.print(f"ambiguity margin: {margin}")
        for name in ("in_force", "calibrated"):
            if name in cal:
                s = cal[name]
                console.print(
                    f"{name}: precision {s['precision']:.4f}, recall {s['recall']:.4f}, "
                    f"worst {s['worst_group']['group']}: {s['worst_group']['precision']:.4f}"
                )
        if chosen is not None and args.write_calibration and gate is not None:
            values = {
                "min_fitness": chosen["min_fitness"],
                "max_rmse_m": chosen["max_rmse_m"],
                "gate_distance": gate["gate_distance"],
                "ambiguity_margin": None if margin is None else margin["ambiguity_margin"],
            }
            data = ", ".join([*map(str, towns), *pairs])
            write_calibration(args.model, "verify", values, data)
    table = Table(title=f"verified loop closures ({enc.model_id}, candidates={args.candidates})")
    for col in (
        "town",
        "queries",
        "with loop",
        "answer R@1",
        "answer R@5",
        "accepted",
        "precision",
        "prec. (gt loops)",
        "recall",
        "t err m (med)",
        "yaw err ° (med)",
        "ms/query (med)",
        "registered/query",
    ):
        table.add_column(col, justify="right")
    served_at = (args.min_fitness, args.max_rmse, args.gate_distance)
    for r in results:
        s = score(r["queries"], *served_at, margin=args.ambiguity_margin)
        rec = descriptor_recall(r["queries"])
        row = {
            "town": r["town"],
            "queries": len(r["queries"]),
            "with_loop": sum(q["has_loop"] for q in r["queries"]),
            "descriptor": rec,
            "verified": s,
            "verified_stop_at_first": score(
                r["queries"], *served_at, True, margin=args.ambiguity_margin
            ),
            "verify_ms": {
                "median": float(np.median(r["verify_ms"])),
                "p90": float(np.percentile(r["verify_ms"], 90)),
            },
            "geometry_bytes": {
                "median": float(np.median(r["geometry_bytes"])),
                "max": int(np.max(r["geometry_bytes"])),
            },
        }
        report["towns"].append(row)
        table.add_row(
            Path(r["town"]).name,
            str(row["queries"]),
            str(row["with_loop"]),
            f"{rec['recall@1']:.3f}",
            f"{rec['recall@5']:.3f}",
            str(s["accepted"]),
            f"{s['precision']:.3f}",
            f"{s['precision_ground_truth_loops']:.3f}",
            f"{s['recall']:.3f}",
            f"{s.get('translation_error_m', {}).get('median', float('nan')):.3f}",
            f"{s.get('yaw_error_deg', {}).get('median', float('nan')):.3f}",
            f"{row['verify_ms']['median']:.1f}",
            f"{s['registered_per_query']:.2f}",
        )
    console.print(table)
    report["thresholds"] = in_force
    if args.json is None:
        name = "verify_threshold.json" if args.calibrate else "verify-test.json"
        args.json = REPORTS / "service" / name
    write_report(args.json, report)
    console.print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
