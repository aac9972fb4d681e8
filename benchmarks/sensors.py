"""The baseline across sensors: a model and Scan Context on every catalogue sensor's test
town, across sensors, and on real KITTI scans thinned to fewer rings.

Rows, all on test data (never chosen on):

- **same sensor** (``test-SENSOR`` and the low and tilted mountings, ``make data-sensors``):
  one drive through one town, rendered by each sensor, so the rows differ by the sensor
  alone. The loop-closure protocol (``overlapmamba.core.metrics``: the top-1 of the frames more than
  100 earlier, a loop when its overlap in the sensor's own image is above 0.3): F1max and
  Recall@1 of the descriptor alone, of the service's two stages (the descriptor shortlist
  re-ranked by the yaw features) and of Scan Context; and the service's verified loop
  closures (``benchmarks/verify_threshold.py``: registration of the first ``verify.candidates``
  candidates, the thresholds the model file carries, ``verify.ambiguity_margin`` among them
  when it has one): precision (a closure is right when
  its relative pose is within 1 m and 2°) and recall. Every scan enters the model as its
  sensor's, as the service projects a scan that names its sensor.
- **across sensors** (``test-s1-SENSOR`` queried against ``test-SENSOR``): a second drive
  through the town by one sensor against the first drive's map by another; AR@1/5/20 (a hit
  within 5 m), the descriptor alone, two stages, and Scan Context. The same as
  ``overlapmamba eval --sequence data/synth/test-s1-vlp16 --database data/synth/test-os1-128``.
- **real scans thinned** (``overlapmamba eval-real --beams 32,16``): KITTI 00's queries with
  every second or fourth ring against whole scans, declared as the sensor they now are;
- **a real HDL-32E** (``overlapmamba eval-real --sequence ../shared/data/nuscenes_scene0061
  --sensor hdl32 --hit-radius 6``): nuScenes keyframes, odd against even.

    python benchmarks/sensors.py [--model models/overlapmamba-hdl64.onnx]

Writes reports/model/sensors.json and the Markdown table reports/model/sensors.md, which the
README and the model card include as they are (a test keeps them equal). ≈ 2 h on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
from bench_kit import REAL, ROOT, provenance, served_input, served_rerank, served_settings
from closure_kit import descriptor_recall as verified_recall
from closure_kit import score
from rich.console import Console
from verify_threshold import run_town

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.metrics import evaluate_retrieval
from overlapmamba.core.rerank import Rerank, two_stage
from overlapmamba.core.scancontext import ScanContextParams
from overlapmamba.core.sensors import CATALOGUE
from overlapmamba.service.encoder import Encoder
from overlapmamba.service.settings import VerifySettings
from overlapmamba.train.checkpoint import load_model
from overlapmamba.train.evaluate import (
    loop_closure,
    scan_contexts,
    scancontext_loop_closure,
    sequence_loops,
    summary,
)
from overlapmamba.train.realscans import eval_real
from overlapmamba.train.sessions import (
    check_sessions,
    descriptor_recall,
    scan_context_recall,
    town_positions,
)

MOUNTED = ("test-vlp16-robot", "test-os0-128-amr", "test-xt32-backpack")
# (query drive, map): the pairs, and each map's own sensor across sessions beside
PAIRS = (
    ("kitti-hdl64", "kitti-hdl64"),
    ("vlp16", "kitti-hdl64"),
    ("os0-128", "kitti-hdl64"),
    ("xt32", "kitti-hdl64"),
    ("os1-128", "os1-128"),
    ("vlp16", "os1-128"),
    ("os0-128", "os1-128"),
    ("xt32", "os1-128"),
)
BEAMS = (32, 16)
MD = "reports/model/sensors.md"
NUSCENES = REAL.parent / "nuscenes_scene0061"


def same_sensor(
    enc: Encoder, town: Path, rerank: Rerank, v: VerifySettings, verify: bool = True
) -> dict[str, Any]:
    """One town: the model's loop closure alone and in two stages, Scan Context's, and the
    verified closures at the model's thresholds; its descriptors and contexts for later."""
    seq = open_sequence(town)
    gt = sequence_loops(seq)
    record = VerifySettings(
        candidates=v.candidates, min_fitness=0.0, max_rmse_m=1e9, gate_distance=v.gate_distance
    )
    margin = v.ambiguity_margin if verify else None
    rivals_from = None if margin is None else v.min_fitness  # the served check's registrations
    r = run_town(enc, town, v.candidates if verify else 0, record, rerank, rivals_from=rivals_from)
    desc, yaw = r["descriptors"], r["yaw_features"]
    contexts = scan_contexts(seq)
    alone = summary(loop_closure(desc, gt))
    staged = evaluate_retrieval(
        two_stage(desc, yaw, rerank),
        len(desc),
        gt.positives(),
        exclude_recent_frames=int(gt.params.get("exclude_recent", 100)),
    ).summary()
    # as the service answers: the first verified candidate unless v.stop_at_first is off
    at = (v.min_fitness, v.max_rmse_m, v.gate_distance, v.stop_at_first)
    verified = score(r["queries"], *at, margin=margin)
    row = {
        "town": str(town),
        "sensor": r["sensor"],
        "input": r["input"],
        "mount": _mount(town),
        "frames": len(seq),
        "queries_with_loop": int(alone["all"]["queries_with_loop"]),
        "descriptor": _fr(alone["all"]),
        "two_stage": _fr(staged),
        "scan_context": _fr(summary(scancontext_loop_closure(contexts, gt))["all"]),
        "answer_recall@5": verified_recall(r["queries"])["recall@5"] if verify else None,
        "verified": {
            **{k: verified[k] for k in ("accepted", "correct", "precision", "recall")},
            "stop_at_first": v.stop_at_first,
            "ambiguity_margin": margin,
        }
        if verify
        else None,  # --no-verify: nothing registered
    }
    if verify and "translation_error_m" in verified:
        row["verified"]["translation_error_m_median"] = verified["translation_error_m"]["median"]
    return {"row": row, "desc": desc, "yaw": yaw.astype(np.float32), "contexts": contexts}


def _fr(m: dict[str, Any]) -> dict[str, float]:
    return {"f1max": float(m["f1max"]), "recall@1": float(m["recall@1"])}


def _mount(town: Path) -> str:
    manifest = json.loads((town / "manifest.json").read_text())
    m = manifest["resolved"].get("mounting", {"name": "car", "height": 1.73, "pitch_deg": 0.0})
    tilt = f", pitched {m['pitch_deg']:g}°" if m.get("pitch_deg") else ""
    return f"{m['name']} {m['height']:g} m{tilt}"


def across(
    enc: Encoder,
    query: Path,
    database: Path,
    db: dict[str, Any],
    rerank: Rerank,
) -> dict[str, Any]:
    """A second drive's scans against a first drive's map of another sensor: AR@1/5/20."""
    qs, ds = open_sequence(query), open_sequence(database)
    check_sessions(ds, qs)
    inp = served_input(enc, qs.sensor)
    # as the service answers: mapped where the file carries a map for the sensor
    desc_q, yaw_q = enc.describe((qs.points(i) for i in range(len(qs))), inp)
    pos_db, pos_q = town_positions(ds), town_positions(qs)
    p = ScanContextParams()
    return {
        "query": str(query),
        "database": str(database),
        "query_sensor": qs.sensor,
        "map_sensor": ds.sensor,
        "descriptor": _ar(descriptor_recall(db["desc"], pos_db, desc_q, pos_q)),
        "two_stage": _ar(
            descriptor_recall(
                db["desc"], pos_db, desc_q, pos_q, yaw=(db["yaw"], yaw_q), rerank=rerank
            )
        ),
        "scan_context": _ar(
            scan_context_recall(db["contexts"], pos_db, scan_contexts(qs, p), pos_q, params=p)
        ),
    }


def _ar(r: dict[str, Any]) -> dict[str, Any]:
    return {"queries": r["queries"], **{f"ar@{n}": r[f"ar@{n}"] for n in (1, 5, 20)}}


def _short(commit: str) -> str:
    return commit[:12] + ("-dirty" if commit.endswith("-dirty") else "")


def markdown(report: dict[str, Any]) -> str:
    """The baseline table (README and model card include it as it is)."""
    f = lambda x: f"{x['f1max']:.3f} / {x['recall@1']:.3f}"  # noqa: E731
    lines = [
        f"<!-- written by {report['command']} at {_short(report['commit'])}, {report['date']} -->",
        "",
        "Same sensor: loop closure on one test town driven once and rendered by each sensor, "
        "F1max / Recall@1 (all revisits); verified closures at the model's thresholds.",
        "",
        "| sensor | mounting | descriptor alone | two stages (service) | Scan Context "
        "| verified precision / recall |",
        "|---|---|---|---|---|---|",
    ]
    for r in report["same_sensor"]:
        v = r["verified"]
        cell = (
            "not run"
            if v is None
            else f"{v['precision']:.3f} / {v['recall']:.3f} ({v['accepted']})"
        )
        lines.append(
            f"| {r['sensor']} ({r['input']}) | {r['mount']} | {f(r['descriptor'])} | "
            f"{f(r['two_stage'])} | {f(r['scan_context'])} | {cell} |"
        )
    lines += [
        "",
        "Across sensors: a second drive by one sensor queried against the first drive's map "
        "by another, AR@1 / AR@5 (a hit within 5 m).",
        "",
        "| queries | map | descriptor alone | two stages (service) | Scan Context |",
        "|---|---|---|---|---|",
    ]
    g = lambda x: f"{x['ar@1']:.3f} / {x['ar@5']:.3f}"  # noqa: E731
    for r in report["across_sensors"]:
        lines.append(
            f"| {r['query_sensor']} | {r['map_sensor']} | {g(r['descriptor'])} | "
            f"{g(r['two_stage'])} | {g(r['scan_context'])} |"
        )
    nu = report.get("real_hdl32")
    if nu:
        ret, inv = nu["retrieval_odd_to_even"], nu["yaw_invariance"]
        lines += [
            "",
            f"Real HDL-32E (nuScenes, {nu['scans']} keyframes, {nu['input']} into the model): "
            f"odd → even Recall@1 within {ret['hit_radius_m']:g} m "
            f"{ret['recall@1']:.3f}, two stages "
            f"{ret.get('reranked', {}).get('recall@1', float('nan')):.3f}, Scan Context "
            f"{ret['scan_context']['recall@1']:.3f}; minimum cosine under a random turn "
            f"{inv['cosine_min']:.5f}.",
        ]
    real = report.get("real_thinned")
    if real:
        ret = real["retrieval_odd_to_even"]
        lines += [
            "",
            f"Real KITTI 00 ({real['scans']} scans): odd frames, turned at random, against the "
            f"even frames, Recall@1 (hit within {ret['hit_radius_m']:g} m); thinned queries "
            "keep every second or fourth ring and are declared as the sensor they now are "
            "(undeclared: projected as the model's own sensor). Cosine: a thinned scan's "
            "descriptor to its whole self (median / min).",
            "",
            "| queries | Recall@1 | two stages | cosine to whole |",
            "|---|---|---|---|",
            f"| 64 rings (whole) | {ret['recall@1']:.3f} | "
            f"{ret.get('reranked', {}).get('recall@1', float('nan')):.3f} | 1 |",
        ]
        for b, t in real["thinned"].items():
            for how in ("declared", "undeclared"):
                x = t[how]
                c = x["cosine_to_full"]
                lines.append(
                    f"| {b} rings, {how} | {x['recall@1']:.3f} | "
                    f"{x.get('reranked', {}).get('recall@1', float('nan')):.3f} | "
                    f"{c['median']:.3f} / {c['min']:.3f} |"
                )
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", type=Path, default=ROOT / "models" / "overlapmamba-hdl64.onnx")
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "synth")
    ap.add_argument("--out", type=Path, default=ROOT / "reports" / "model" / "sensors.json")
    ap.add_argument("--markdown", type=Path, default=ROOT / MD)
    ap.add_argument(
        "--only", action="append", help="these towns only (e.g. test-vlp16; a quick look)"
    )
    ap.add_argument("--no-real", action="store_true", help="skip the real KITTI rows")
    ap.add_argument(
        "--no-verify",
        action="store_true",
        help="register nothing (a model whose thresholds were never calibrated: a quick look)",
    )
    args = ap.parse_args()
    console = Console(width=120)
    t0 = time.perf_counter()
    enc = Encoder(args.model)
    served = served_settings(enc.meta)
    rerank, v = served_rerank(enc.meta), served.verify
    names = args.only or [f"test-{s}" for s in CATALOGUE] + list(MOUNTED)
    towns = [args.data / n for n in names if (args.data / n / "manifest.json").is_file()]
    missing = sorted(set(names) - {t.name for t in towns})
    if missing:
        console.print(f"[yellow]missing (make data-sensors):[/] {', '.join(missing)}")
    done: dict[str, dict[str, Any]] = {}
    for town in towns:
        console.print(f"{town.name} …")
        done[town.name] = same_sensor(enc, town, rerank, v, verify=not args.no_verify)
        console.print(done[town.name]["row"])
    pairs = []
    for q, m in PAIRS:
        query, database = args.data / f"test-s1-{q}", args.data / f"test-{m}"
        if database.name in done and (query / "manifest.json").is_file():
            console.print(f"{query.name} against {database.name} …")
            pairs.append(across(enc, query, database, done[database.name], rerank))
            console.print(pairs[-1])
    real: dict[str, Any] = {}
    nuscenes: dict[str, Any] = {}
    if REAL.is_dir() and not args.no_real:
        model, profile, _ = load_model(args.model)
        real = eval_real(model, profile, open_sequence(REAL), rerank=rerank, beams=BEAMS)
        if NUSCENES.is_dir():
            seq = open_sequence(NUSCENES, sensor="hdl32")
            nuscenes = eval_real(model, profile, seq, rerank=rerank, hit_radius=6.0)
    report = {
        **provenance(),
        "model_id": enc.model_id,
        "rerank": {"shortlist": rerank.shortlist, "weight": rerank.weight},
        "verify": v.model_dump(
            include={
                "candidates",
                "min_fitness",
                "max_rmse_m",
                "gate_distance",
                "stop_at_first",
                "ambiguity_margin",
            }
        ),
        "missing": missing,
        "same_sensor": [d["row"] for d in done.values()],
        "across_sensors": pairs,
        "real_thinned": real,
        "real_hdl32": nuscenes,
        "seconds": time.perf_counter() - t0,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    args.markdown.write_text(markdown(report))
    console.print(markdown(report))
    console.print(f"wrote {args.out} and {args.markdown}")


if __name__ == "__main__":
    main()
