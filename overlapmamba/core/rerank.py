"""Two-stage retrieval: a descriptor shortlist, re-ranked by the yaw features' alignment.

The descriptor is global: it says "this street", and on the synthetic towns the shipped
model's wrong first answers across sessions were mostly the right street 5–20 m off (the
report's ``wrong_top1``). The model's per-column yaw features keep what the descriptor pools
away — where along the ring each structure is. Their circular cross-correlation at the best
roll (:func:`overlapmamba.core.yaw.estimate_yaw`'s confidence, computed anyway for the relative
yaw) is high only when the two scans see the same structures in the same arrangement, which
is what "the nearest scan" means. So the shortlist of the nearest descriptors is
re-ordered by

    score = d² − weight · c

with d² the squared L2 distance between unit descriptors (∈ [0, 4]) and c the aligned
correlation (∈ [−1, 1]); lower is better. The score is also what a loop-closure call
thresholds. Scan Context ranks its own shortlist the same way (ring-key candidates, then the
column-aligned distance).

``shortlist`` and ``weight`` were chosen on the ``val`` town and its second session ``val-s1``,
never on a test town (``benchmarks/rerank.py``: the mean of F1max and Recall@1 on the three
subsets and AR@1 across sessions).

A file whose first stage joins the network's descriptor to the yaw features' spectrum
(:mod:`overlapmamba.core.yaw_spectrum`, ``mixed``) can have its shortlist scored by the
network's own distance instead: ``part`` names the leading floats of each vector that hold
that descriptor, and d² is then the squared distance between those parts at unit length. The
spectrum still picks the shortlist (it does not turn with the scan); the correlation already
weighs the yaw features, so the score does not count them twice.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from overlapmamba.core.metrics import Retriever, nearest
from overlapmamba.core.yaw import circular_correlation
from overlapmamba.core.yaw_spectrum import SCORES, FirstStage, score_part, unit

if TYPE_CHECKING:
    from overlapmamba.core.modelmeta import EncoderMetadata


@dataclass(frozen=True)
class Rerank:
    """The second stage: re-rank the ``shortlist`` nearest descriptors (1: off) by
    d² − ``weight`` · aligned yaw-feature correlation; d² between the leading ``part`` floats
    of the two vectors at unit length (None: the whole vectors, as the shortlist ranks)."""

    shortlist: int = 20
    weight: float = 0.2
    part: int | None = None

    def __post_init__(self) -> None:
        if self.shortlist < 1:
            raise ValueError(
                f"rerank shortlist must be ≥ 1 (1: no re-ranking); got {self.shortlist}"
            )
        if not (self.weight >= 0 and np.isfinite(self.weight)):
            raise ValueError(f"rerank weight must be a finite number ≥ 0; got {self.weight}")
        if self.part is not None and self.part < 1:
            raise ValueError(
                f"rerank part must be ≥ 1 float (None: the whole vector); got {self.part}"
            )

    @property
    def on(self) -> bool:
        return self.shortlist > 1 and self.weight > 0

    def rows(self, vectors: np.ndarray) -> np.ndarray:
        """What the score's d² is measured between: ``vectors`` (N, D) themselves, or their
        leading ``part`` floats at unit length (a zero row stays zero)."""
        if self.part is None:
            return vectors
        if self.part >= vectors.shape[1]:
            raise ValueError(
                f"rerank part {self.part} is not a leading part of {vectors.shape[1]}-float vectors"
            )
        return unit(vectors[:, : self.part])

    @classmethod
    def parse(cls, text: str) -> Rerank:
        """``"K,WEIGHT"`` (e.g. ``"20,0.2"``) or ``"off"``."""
        if text.strip().lower() == "off":
            return OFF
        parts = text.split(",")
        try:
            if len(parts) != 2:
                raise ValueError
            k, weight = int(parts[0]), float(parts[1])
        except ValueError:
            raise ValueError(
                f"rerank {text!r} is not K,WEIGHT (e.g. 20,0.2: an integer K ≥ 1 and a "
                "weight ≥ 0) or off"
            ) from None
        return cls(k, weight)


OFF = Rerank(shortlist=1, weight=0.0)


def with_score(p: Rerank, score: str, meta: EncoderMetadata) -> Rerank:
    """``p`` with the score's d² measured as ``score`` (``stage`` or ``network``) says for the
    model of ``meta``, whose first stage decides where its network's descriptor lies
    (:func:`overlapmamba.core.yaw_spectrum.score_part`); a ValueError names a score that
    model cannot give."""
    if meta.reduction:  # a first stage reduced (overlapmamba.train.reduce_head)
        lead = meta.reduction.get("network_part")
        if score == "network" and not lead:
            raise ValueError(
                f"model {meta.model_id}: second-stage score 'network': its descriptor is its "
                f"first stage {meta.first_stage} reduced to {meta.descriptor_dim} floats, which "
                "no longer hold the network's own descriptor; allowed: score 'stage'"
            )
        if score not in SCORES:
            raise ValueError(f"second-stage score {score!r} is not one of {', '.join(SCORES)}")
        return replace(p, part=int(lead) if score == "network" and lead else None)
    try:
        stage = FirstStage.parse(meta.first_stage)
        part = score_part(stage, meta.descriptor_dim, meta.yaw_channels, score)
    except ValueError as e:
        raise ValueError(f"model {meta.model_id}: second-stage score {score!r}: {e}") from None
    return replace(p, part=part)


def aligned_correlation(query: np.ndarray, refs: np.ndarray) -> np.ndarray:
    """query (C, W), refs (K, C, W) → (K,): the yaw features' cosine similarity at the best
    circular roll (estimate_yaw's confidence, without the sub-column refinement)."""
    return circular_correlation(query, refs).max(axis=1)


def by_score(
    dist_sq: np.ndarray, correlation: np.ndarray, weight: float
) -> tuple[np.ndarray, np.ndarray]:
    """One shortlist (nearest descriptor first) in the second stage's order: (order into
    the shortlist, the scores d² − weight · c in that order; lower is better); ties keep the
    descriptor order. Evaluation, the service and the calibration benchmarks all order
    through here."""
    s = np.asarray(dist_sq, dtype=np.float64) - weight * np.asarray(correlation, np.float64)
    order = np.argsort(s, kind="stable")
    return order, s[order]


def rerank(
    query_yaw: np.ndarray, cand_yaw: np.ndarray, dist_sq: np.ndarray, p: Rerank
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Re-order one query's shortlist.

    query_yaw (C, W); cand_yaw (K, C, W), the candidates nearest first; dist_sq (K,) their
    squared descriptor distances → (order (K,) into the shortlist, the scores in that
    order, the correlations in that order). Ties keep the descriptor order."""
    d = np.asarray(dist_sq, dtype=np.float64)
    if cand_yaw.shape[0] != d.shape[0]:
        raise ValueError(f"{cand_yaw.shape[0]} candidates' features but {d.shape[0]} distances")
    if d.shape[0] == 0:
        empty = np.zeros(0)
        return np.zeros(0, dtype=np.int64), empty, empty
    c = aligned_correlation(query_yaw, cand_yaw)
    order, s = by_score(d, c, p.weight)
    return order, s, c[order]


def rerank_ranked(
    query_yaw: np.ndarray,
    yaw: np.ndarray,
    ranked: np.ndarray,
    dist_sq: np.ndarray,
    p: Rerank,
    desc: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Re-rank the first ``p.shortlist`` columns of a whole result table.

    query_yaw (Q, C, W) the queries' features; yaw (M, C, W) the database's; ranked (Q, n)
    database indices nearest first, padded with −1; dist_sq (Q, n) their squared distances
    (+inf where padded) → (ranked, scores) of the same shape: the first ``min(shortlist, n)``
    columns re-ordered and holding scores, the rest untouched (descriptor distances).
    ``desc`` = (queries' (Q, D), database's (M, D)) descriptors: with ``p.part`` the score's
    d² is between ``p.rows`` of them, and they are required."""
    ranked = np.array(ranked, dtype=np.int64, copy=True)
    out = np.array(dist_sq, dtype=np.float64, copy=True)
    if not p.on:
        return ranked, out
    if p.part is not None:
        if desc is None:
            raise ValueError("a second stage scored by part of the descriptors needs them")
        rows = p.rows(np.concatenate([desc[1], desc[0]]))
        out = scored_by(rows, len(desc[1]) + np.arange(len(desc[0])), ranked, out, p.shortlist)
    k = min(p.shortlist, ranked.shape[1])
    for i in range(len(ranked)):
        cand = ranked[i, :k]
        ok = cand >= 0
        n = int(ok.sum())  # padding comes last
        if n == 0:
            continue
        order, s, _ = rerank(query_yaw[i], yaw[cand[:n]], out[i, :n], p)
        ranked[i, :n] = cand[:n][order]
        out[i, :n] = s
    return ranked, out


def scored_by(
    scored: np.ndarray, queries: np.ndarray, ranked: np.ndarray, dist_sq: np.ndarray, k: int
) -> np.ndarray:
    """``dist_sq`` (Q, n) with its first ``k`` columns replaced by the squared distances
    between the ``scored`` rows (N, D') of each query and of its ranked candidates (padding
    stays +inf): the second stage's d² from other vectors than the shortlist's."""
    out = np.array(dist_sq, dtype=np.float64, copy=True)
    k = min(k, ranked.shape[1])
    cand = ranked[:, :k]
    ok = cand >= 0
    diff = scored[np.clip(cand, 0, None)] - scored[queries][:, None, :]
    out[:, :k] = np.where(ok, (diff.astype(np.float64) ** 2).sum(-1), np.inf)
    return out


def score_d2(p: Rerank, desc_q: np.ndarray, desc_db: np.ndarray, d2: np.ndarray) -> np.ndarray:
    """The score's d² between every query (desc_q (Q, D)) and every database row (desc_db
    (M, D)): ``d2`` (Q, M), their squared distances, as it is without ``p.part``, else
    between ``p.rows`` of them (unit rows: 2 − 2 · cosine)."""
    if p.part is None:
        return d2
    q, db = p.rows(desc_q), p.rows(desc_db)
    return np.maximum(2.0 - 2.0 * (q @ db.T), 0.0)


def two_stage(desc: np.ndarray, yaw: np.ndarray, p: Rerank) -> Retriever:
    """A retriever for :func:`overlapmamba.core.metrics.evaluate_retrieval` (query i searches frames
    0 … db_size − 1) in two stages: the ``p.shortlist`` nearest descriptors (desc (N, D)) re-ranked
    by their yaw features (yaw (N, C, W)), the score's d² between ``p.rows`` of them. Each
    query's answer is computed once, so the direction subsets share their queries'
    shortlists."""
    memo: dict[tuple[int, int, int], tuple[np.ndarray, np.ndarray]] = {}
    scored = p.rows(desc) if p.part is not None and p.on else None

    def retrieve(queries: np.ndarray, db_size: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        kk = max(k, p.shortlist)
        keys = [(int(q), int(n), kk) for q, n in zip(queries, db_size, strict=True)]
        todo = np.array([i for i, key in enumerate(keys) if key not in memo], dtype=np.int64)
        if len(todo):
            q, n = queries[todo], db_size[todo]
            allowed = np.arange(len(desc))[None, :] < n[:, None]
            ranked, dist = nearest(desc[q], desc, kk, allowed=allowed)
            if scored is not None:  # the score's d² in place, from rows computed once
                dist = scored_by(scored, q, ranked, dist, p.shortlist)
            ranked, score = rerank_ranked(yaw[q], yaw, ranked, dist, replace(p, part=None))
            for j, i in enumerate(todo):
                memo[keys[i]] = (ranked[j], score[j])
        rows = [memo[key] for key in keys]
        ranked = np.stack([r for r, _ in rows]) if rows else np.zeros((0, kk), np.int64)
        score = np.stack([s for _, s in rows]) if rows else np.zeros((0, kk))
        return ranked[:, :k], score[:, :k]

    return retrieve
