"""What the shipped model's sub-column views cost and buy (overlapmamba.core.views), four ways
with the same weights: one view; one view with aligned columns (each scan's columns start at
its mean bearing: one pass, a turn rolls the image by whole columns); V views met at the
descriptors (the encoder runs once a view, their descriptors are averaged); V views met at
the tokens (``token_views``: the per-column stem runs once a view, the blocks and head once
a scan).

The four files are written from the model's own weights (``with_views`` and
``with_column_phase`` rewrite the metadata; ``with_token_views`` traces the graph anew from
the recovered weights), so they differ only in where the views meet and the columns start.
For each:

- **cost**: a scan described as the service describes it (``Encoder.describe``: ``project_offset`` +
  ``Encoder.encode``) on real KITTI 00 scans, timed interleaved (each way in turn, rep after
  rep) in one process, with 1 and 2 onnxruntime threads, one and 8 scans a call, so that the
  ratios hold on a shared machine even when the absolute times drift; and the project stage;
- **turn invariance**: the minimum cosine between a real scan's descriptor and that of the
  same scan turned by a random continuous angle (``eval-real``'s turns,
  ``overlapmamba.train.realscans``), on KITTI 00 and nuScenes, for each of ``--seeds``;
- **loop closure** (``--sequence``, repeatable; choose on ``val``, report on test towns):
  ``overlapmamba eval`` F1max and Recall@1, the descriptor alone and two stages (``--rerank``).

Writes JSON (default reports/service/views.json).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from reports_kit import REPORTS, write_report
from rich.console import Console
from rich.table import Table

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.io import read_points
from overlapmamba.service.encoder import Encoder
from overlapmamba.train.modelfile import read_metadata, with_column_phase, with_views

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
KITTI = SHARED / "kitti00_0000-0100"
REAL = {"kitti00": KITTI, "nuscenes-hdl32": SHARED / "nuscenes_scene0061"}


def interleaved(
    fns: dict[str, Callable[[int], object]], reps: int, per: int
) -> dict[str, dict[str, float]]:
    """Median and p90 ms per scan of each function, called in turn ``reps`` times each
    (``per`` scans a call), after one warm-up call each."""
    for fn in fns.values():
        fn(0)
    times: dict[str, list[float]] = {k: [] for k in fns}
    for i in range(reps):
        for key, fn in fns.items():
            t0 = time.perf_counter()
            fn(i)
            times[key].append((time.perf_counter() - t0) / per * 1e3)
    return {
        k: {"median_ms": float(np.median(v)), "p90_ms": float(np.percentile(v, 90))}
        for k, v in times.items()
    }


def ways(model: Path, tmp: Path) -> dict[str, Path]:
    """The model's weights written four ways: {"one view", "aligned", "descriptors",
    "tokens"}."""
    from overlapmamba.train.recover import with_token_views

    meta = read_metadata(model)
    if meta.views == 1:
        raise SystemExit(f"{model} is described by one view: there are no views to compare")
    one = tmp / "one-view.onnx"
    if meta.graph_views > 1:
        with_token_views(model, one, 1)
        tokens = model
    else:
        with_views(model, one, 1)
        tokens = tmp / "tokens.onnx"
        with_token_views(model, tokens, meta.views)
    descriptors = tmp / "descriptors.onnx"
    if meta.graph_views > 1:
        with_views(one, descriptors, meta.views)
    else:
        descriptors = model
    if meta.aligned:
        raise SystemExit(f"{model} aligns its columns: give the file with the sensor's")
    aligned = tmp / "aligned.onnx"
    with_views(one, aligned, 1)
    with_column_phase(aligned, "aligned")
    return {"one view": one, "aligned": aligned, "descriptors": descriptors, "tokens": tokens}


def cost(paths: dict[str, Path], reps: int) -> tuple[list[dict], dict[str, str]]:
    """The cost rows, and the scan path each variant's encoder took at 2 threads (each loads
    as the service loads it, ``scan_kernel = "auto"``)."""
    clouds = [read_points(p) for p in sorted((KITTI / "velodyne").glob("*.bin"))[:16]]
    rows: list[dict] = []
    scan_paths: dict[str, str] = {}
    for threads in (1, 2):
        encs = {k: Encoder(p, intra_op_threads=threads) for k, p in paths.items()}
        scan_paths = {k: e.scan_path for k, e in encs.items()}
        for per in (1, 8):

            def call(enc: Encoder, per: int = per) -> Callable[[int], object]:
                def run(i: int) -> object:
                    batch = [clouds[(i * per + j) % len(clouds)] for j in range(per)]
                    return enc.describe(batch, batch=per)

                return run

            got = interleaved({k: call(e) for k, e in encs.items()}, reps, per)
            rows.append({"threads": threads, "scans_per_call": per, **got})
        project = interleaved(
            {
                k: (lambda i, e=encs[k]: e.project_offset(clouds[i % len(clouds)]))
                for k in ("one view", "aligned", "tokens")
            },
            reps,
            1,
        )
        rows.append({"threads": threads, "stage": "project", **project})
    return rows, scan_paths


def turn_minima(
    path: Path, seeds: int, vectors: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]]
) -> dict[str, dict]:
    """The lowest cosine between a real scan's vector and that of the same scan turned by a
    random continuous angle (``eval-real``'s turns, one pass a scan with the file's own
    views), per real set (``REAL``) and per named vector (``vectors[name](descriptor,
    yaw_features)``, rows at unit length), over ``seeds`` draws."""
    from overlapmamba.train.checkpoint import load_model

    model, profile, _ = load_model(path)
    out: dict[str, dict] = {}
    for name, folder in REAL.items():
        if not folder.is_dir():
            out[name] = {"skipped": f"{folder} is missing"}
            continue
        seq = open_sequence(folder)
        mins = turned_minima(model, profile, seq, seeds, vectors)
        out[name] = {
            "scans": len(seq),
            **{k: {"cosine_min_per_seed": v, "cosine_min": min(v)} for k, v in mins.items()},
        }
    return out


def turned_minima(
    model: Any,
    profile: Any,
    seq: Any,
    seeds: int,
    vectors: Mapping[str, Callable[[np.ndarray, np.ndarray], np.ndarray]],
    stride: int = 1,
) -> dict[str, list[float]]:
    """Per named vector, the lowest cosine between a scan's vector and its turned copy's over
    every ``stride``-th scan of ``seq``, one value per seed's draw of turns (a model and
    profile from ``overlapmamba.train.checkpoint.load_model``)."""
    from overlapmamba.train.checkpoint import aligned_of, input_of, views_of
    from overlapmamba.train.evaluate import describe
    from overlapmamba.train.realscans import real_turns

    sensor = input_of(model, profile, seq)
    mins: dict[str, list[float]] = {key: [] for key in vectors}
    for seed in range(seeds):
        t = real_turns(seq, sensor, seed, views_of(model), aligned_of(model), stride=stride)
        plain = describe(model, t.plain, offsets=t.plain_offsets)
        turned = describe(model, t.turned, offsets=t.turned_offsets)
        for key, vector in vectors.items():
            mins[key].append(float((vector(*plain) * vector(*turned)).sum(1).min()))
    return mins


def invariance(paths: dict[str, Path], seeds: int) -> dict[str, dict]:
    """Minimum cosine of the descriptor under a random continuous turn, per real set, way
    and seed."""
    out: dict[str, dict] = {}
    for way, path in paths.items():
        for name, row in turn_minima(path, seeds, {way: lambda desc, _yaw: desc}).items():
            out.setdefault(name, {}).update(row)
    return out


def loop_closure(paths: dict[str, Path], sequences: list[Path], rerank: str, tmp: Path) -> dict:
    """``overlapmamba eval`` of each way on each sequence: F1max, Recall@1, both stages."""
    out: dict[str, dict] = {}
    for seq in sequences:
        out[seq.name] = {}
        for way, path in paths.items():
            js = tmp / f"{seq.name}-{way.replace(' ', '-')}.json"
            cmd = [sys.executable, "-m", "overlapmamba", "eval", "--checkpoint", str(path)]
            cmd += ["--sequence", str(seq), "--rerank", rerank, "--json", str(js)]
            subprocess.run(cmd, check=True, capture_output=True)
            got = json.loads(js.read_text())
            out[seq.name][way] = {
                stage: {
                    sub: {k: got[key][sub][k] for k in ("f1max", "recall@1")}
                    for sub in ("all", "same", "reverse")
                }
                for stage, key in (("descriptor", "metrics"), ("two_stages", "metrics_reranked"))
            }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, default=ROOT / "models" / "overlapmamba-hdl64.onnx")
    ap.add_argument("--reps", type=int, default=40, help="timed calls per setting and way")
    ap.add_argument("--seeds", type=int, default=5, help="random turns drawn per real set")
    ap.add_argument("--sequence", type=Path, action="append", default=[], help="loop closure")
    ap.add_argument("--rerank", default="20,0.2", help="the second stage of --sequence's eval")
    ap.add_argument("--out", type=Path, default=REPORTS / "service" / "views.json")
    ap.add_argument(
        "--cost-only",
        action="store_true",
        help="measure the cost rows again and write them into --out, keeping its turn "
        "invariance and loop closure (and their command and date, as `measured_by`)",
    )
    args = ap.parse_args()
    console = Console()
    if not KITTI.is_dir():
        raise SystemExit(f"{KITTI} is missing: the real scans are needed")

    kept: dict = {}
    if args.cost_only:
        if not args.out.is_file():
            raise SystemExit(f"--cost-only keeps {args.out}'s other results: it does not exist")
        kept = json.loads(args.out.read_text())
    with tempfile.TemporaryDirectory() as tmp:
        paths = ways(args.model, Path(tmp))
        ids = {k: read_metadata(p).model_id for k, p in paths.items()}
        if kept and kept.get("model_ids") != ids:
            raise SystemExit(
                f"{args.out} measured other files ({kept.get('model_ids')}); run it in full"
            )
        views = read_metadata(paths["tokens"]).views
        rows, scan_paths = cost(paths, args.reps)
        if kept:
            turns = {k: v for k, v in kept["turn_invariance"].items() if k != "seeds"}
            loops = {k: v for k, v in kept["loop_closure"].items() if k != "rerank"}
        else:
            turns = invariance(paths, args.seeds)
            loops = loop_closure(paths, args.sequence, args.rerank, Path(tmp))

    result = {
        "machine": {
            "platform": platform.platform(),
            "cores": os.cpu_count(),
            "python": platform.python_version(),
        },
        "model": str(args.model),
        "views": views,
        "model_ids": ids,
        "scan_paths": scan_paths,
        "scans": "KITTI 00 frames 0–15",
        "reps": args.reps,
        "rows": rows,
        "turn_invariance": {"seeds": args.seeds, **turns},
        "loop_closure": {"rerank": args.rerank, **loops},
    }
    if kept:  # what the kept results were measured by
        result["turn_invariance"]["seeds"] = kept["turn_invariance"]["seeds"]
        result["loop_closure"]["rerank"] = kept["loop_closure"]["rerank"]
        result["measured_by"] = kept.get("measured_by") or {
            k: kept[k] for k in ("command", "commit", "date") if k in kept
        }
    write_report(args.out, result)

    t = Table(
        title=f"a scan described as the service does it: one view, {views} views met two ways"
    )
    cols = ("one view, ms/scan", "aligned", "at the descriptors", "at the tokens")
    for col in ("threads", "what", *cols):
        t.add_column(col, justify="right")
    for r in rows:
        what = r.get("stage") or f"project + encode, {r['scans_per_call']} a call"
        a = r["one view"]["median_ms"]
        cells = [
            f"{r[k]['median_ms']:.1f} ({r[k]['median_ms'] / a:.2f}×)" if k in r else "—"
            for k in ("aligned", "descriptors", "tokens")
        ]
        t.add_row(str(r["threads"]), what, f"{a:.1f}", *cells)
    console.print(t)
    for name, per in turns.items():
        if "skipped" not in per:
            console.print(
                name, {k: round(v["cosine_min"], 5) for k, v in per.items() if k != "scans"}
            )
    console.print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
