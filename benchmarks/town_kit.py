"""A synthetic town as the service holds it, for the benchmarks that query it as the service
does (``verify_threshold.run_town``, ``ambiguity_cost.py``): every scan encoded by the shipped
encoder and prepared for registration, and each query's candidates in the service's order.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from bench_kit import served_input
from tqdm import tqdm

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.overlap import LoopGroundTruth
from overlapmamba.core.rerank import Rerank, by_score, score_d2
from overlapmamba.core.yaw import estimate_yaw
from overlapmamba.service.encoder import Encoder
from overlapmamba.service.registration import (
    Prepared,
    RegistrationParams,
    keyframe_geometry,
    prepare,
)


@dataclass
class Town:
    """A town as the service holds it (:func:`encode_town`): each scan's descriptor and yaw
    features (float16, as the store keeps them), its registration grid and the geometry its
    keyframe keeps, and the descriptor and second-stage distances between every two."""

    seq: Any
    truth: LoopGroundTruth
    recent: int  # frames before a query that are not its candidates
    sensor: Any  # the SensorInput its scans are projected with
    rerank: Rerank
    desc: np.ndarray
    yaw: np.ndarray
    prepared: list[Prepared]
    blobs: list[bytes | None]
    d2: np.ndarray
    s2: np.ndarray

    def order(self, i: int, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Query ``i``'s first ``k`` candidates in the service's order
        (``overlapmamba.service.ranking``) and the seed yaw of each."""
        r = self.rerank
        top = np.argsort(self.d2[i, : i - self.recent], kind="stable")[: max(k, r.shortlist)]
        yaw = self.yaw
        deg, conf = estimate_yaw(yaw[i].astype(np.float32), yaw[top].astype(np.float32))
        if r.on:
            order, _ = by_score(self.s2[i, top], conf, r.weight)
            top, deg = top[order], deg[order]
        return top[:k], deg[:k]


def encode_town(
    enc: Encoder, path: Path, params: RegistrationParams, rerank: Rerank, batch: int = 8
) -> Town:
    """Every scan of the town at ``path`` encoded by the shipped encoder and prepared for
    registration, as the service does with each scan it is sent."""
    seq = open_sequence(path)
    sensor = served_input(enc, seq.sensor)
    truth = LoopGroundTruth.load(path / "ground_truth" / "loops.npz")
    n = len(seq)
    descs, yaws, blobs, prepared = [], [], [], []
    for start in tqdm(range(0, n, batch), desc=f"encode {path.name}", unit="batch"):
        pts = [seq.points(i) for i in range(start, min(n, start + batch))]
        d, y = enc.describe(pts, sensor, batch=len(pts))  # as the service answers
        descs.append(d)
        yaws.append(np.asarray(y, dtype=np.float16))  # as the store keeps them
        # as the service does: one registration grid per scan, the keyframe keeps it
        prepared += [prepare(p.xyz, params) for p in pts]
        blobs += [keyframe_geometry(q, params) for q in prepared[-len(pts) :]]
    desc = np.concatenate(descs)
    d2 = np.maximum(2.0 - 2.0 * desc @ desc.T, 0.0)
    recent = int(truth.params.get("exclude_recent", 100))
    return Town(
        seq,
        truth,
        recent,
        sensor,
        rerank,
        desc,
        np.concatenate(yaws),
        prepared,
        blobs,
        d2,
        score_d2(rerank, desc, desc, d2),
    )
