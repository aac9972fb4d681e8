"""A generated sequence's ground truth: overlap and yaw of every pair of scans closer than
``gt_radius`` (computed with overlapmamba.core's overlap code, in worker processes), the loop table
the loop protocol asks for, and the revisits it holds.

    OUT/ground_truth/overlaps.npz   the pair table (pair_table "loops": only loop candidates)
    OUT/ground_truth/loops.npz      the loop table (overlapmamba.core.overlap.LoopGroundTruth)
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.overlap import (
    LoopGroundTruth,
    candidate_pairs,
    loop_params,
    loop_table_from_pairs,
    pair_overlaps,
)
from overlapmamba.core.sensors import get_profile
from overlapmamba.synth.config import GenConfig
from overlapmamba.synth.workers import DEFAULT_STALL_TIMEOUT_S, run_jobs


def _overlap_chunk(args) -> tuple[np.ndarray, np.ndarray]:
    root, sensor, pairs = args
    seq = open_sequence(root, kind="kitti", sensor=sensor, unfinished=True)
    return pair_overlaps(seq, pairs, get_profile(sensor), progress=False)


def compute_ground_truth(
    out: Path,
    cfg: GenConfig,
    workers: int,
    progress: bool,
    stall_timeout_s: float = DEFAULT_STALL_TIMEOUT_S,
) -> tuple[dict, LoopGroundTruth]:
    """Overlap/yaw of every pair closer than ``gt_radius`` (query later than reference), with
    overlapmamba.core's overlap code; the loop table is the subset the loop protocol asks for.

    With ``pair_table="loops"`` only the loop table's candidates are computed (pairs more than
    ``loop_exclude`` frames apart): the same loop table, without the neighbouring frames that
    only training samples from."""
    seq = open_sequence(out, kind="kitti", sensor=cfg.sensor, unfinished=True)
    profile = get_profile(cfg.sensor)
    min_gap = 1 if cfg.pair_table == "all" else cfg.loop_exclude + 1
    pairs = candidate_pairs(seq.positions(), radius=cfg.gt_radius, min_gap=min_gap)
    pairs = pairs[np.argsort(pairs[:, 0], kind="stable")]
    # Chunks of ≈25 whole queries, so each chunk projects its queries once.
    queries = np.unique(pairs[:, 0])
    firsts = [q[0] for q in np.array_split(queries, max(1, len(queries) // 25)) if len(q)]
    chunks = np.split(pairs, np.searchsorted(pairs[:, 0], firsts[1:]))
    jobs = [(str(out), cfg.sensor, c) for c in chunks]
    bar = tqdm(total=len(pairs), desc="overlap ground truth", unit="pair", disable=not progress)
    results: list = [None] * len(jobs)
    if workers <= 1:
        done: Iterable[tuple[int, Any]] = enumerate(map(_overlap_chunk, jobs))
    else:
        done = run_jobs(
            _overlap_chunk, jobs, workers=workers, stall_timeout_s=stall_timeout_s, what="chunk"
        )
    for i, res in done:
        results[i] = res
        bar.update(len(jobs[i][2]))
    bar.close()
    overlap = np.concatenate([r[0] for r in results]).astype(np.float32)
    yaw = np.concatenate([r[1] for r in results]).astype(np.float32)
    pos = seq.positions()
    dist = np.linalg.norm(pos[pairs[:, 0]] - pos[pairs[:, 1]], axis=1).astype(np.float32)
    gt_dir = out / "ground_truth"
    gt_dir.mkdir(exist_ok=True)
    table = {
        "query": pairs[:, 0],
        "reference": pairs[:, 1],
        "overlap": overlap,
        "yaw_deg": yaw,
        "distance": dist,
    }
    tmp = gt_dir / "overlaps.tmp.npz"
    np.savez_compressed(
        tmp,
        **table,
        radius=cfg.gt_radius,
        pair_table=cfg.pair_table,
        profile=json.dumps(profile.model_dump()),
    )
    os.replace(tmp, gt_dir / "overlaps.npz")
    params = loop_params(seq, profile, cfg.loop_params())
    loops = loop_table_from_pairs(seq, params, pairs[:, 0], pairs[:, 1], overlap, yaw)
    loops.save(gt_dir / "loops.npz")
    return table, loops


def read_overlaps(root: str | Path) -> dict[str, np.ndarray]:
    """The pair table written by :func:`compute_ground_truth`."""
    with np.load(Path(root) / "ground_truth" / "overlaps.npz", allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def revisit_frames(loops: LoopGroundTruth) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frames that revisit a place, split by direction (best-overlap reference's |yaw| > 90°),
    and each such frame's gap to that reference in frames."""
    frames, refs, yaw = loops.best_loops()
    rev = np.abs(yaw) > 90
    return frames[~rev], frames[rev], frames - refs
