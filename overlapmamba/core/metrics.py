"""Place-recognition metrics, with the exact protocols written down.

Distances are squared L2 between descriptors (equivalent to cosine ranking for unit vectors).

**Loop-closure protocol** (OverlapTransformer, KITTI), :func:`evaluate_loop_closure`:

* Query i's database is frames 0 … i − exclude_recent_frames − 1 (exclude_recent_frames =
  100); queries with an empty database are skipped. Its *positives* are the database
  frames that are true loops (see :mod:`overlapmamba.core.overlap`).
* Top-1 retrieval gives a candidate and its distance d_i.
* PR curve — sweep a threshold t over every distinct d_i (plus t = −∞):
  accept when d_i ≤ t → TP if the candidate is a positive, else FP;
  reject otherwise → FN if query i has any positive, else TN.
  precision = TP / (TP + FP), taken as 1 when nothing is accepted;
  recall = TP / (TP + FN), taken as 1 when no query has a positive and as 0 when every
  query with a positive was accepted with a wrong candidate.
* **AUC** is the area under that precision–recall curve (trapezoids over recall, the
  t = −∞ point being recall 0, precision 1). **F1max** = max over t of 2PR / (P + R).
  When no scored query has a positive (a subset without loops) both are NaN: there is
  nothing to find, which is neither perfect nor zero (the curve's convention above would
  give F1max 1 and AUC 0).
* **Recall@N** is over queries that have a positive: a hit if any of the N nearest database
  frames is a positive. **Recall@1%** uses, per query, N_i = max(1, ⌈0.01 · |database_i|⌉)
  (the reference code is ambiguous; this is what we use).

**Database/query protocol** (e.g. odd → even frames, or NCLT), :func:`recall_at_n_curve`:
Recall@N as above over queries with at least one positive; **AR@N** (NCLT) is the mean of
Recall@1 … Recall@N, reported for N = 1, 5, 20.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np


def squared_distances(queries: np.ndarray, database: np.ndarray) -> np.ndarray:
    """(Q, D), (M, D) → (Q, M) float64 squared L2 distances, clamped at 0."""
    q = np.asarray(queries, dtype=np.float64)
    d = np.asarray(database, dtype=np.float64)
    out = (q * q).sum(1)[:, None] + (d * d).sum(1)[None, :] - 2.0 * q @ d.T
    return np.maximum(out, 0.0)


def nearest(
    queries: np.ndarray,
    database: np.ndarray,
    k: int,
    *,
    allowed: np.ndarray | None = None,
    chunk: int = 1024,
) -> tuple[np.ndarray, np.ndarray]:
    """Brute-force k nearest database entries of each query.

    allowed: optional (Q, M) bool — which database entries each query may return.
    → indices (Q, k) int64 padded with −1, distances (Q, k) float64 padded with +inf;
    ties are broken by the lower database index.
    """
    Q, M = len(queries), len(database)
    k = max(0, min(k, M))
    idx = np.full((Q, k), -1, dtype=np.int64)
    dist = np.full((Q, k), np.inf)
    if k == 0:
        return idx, dist
    for s in range(0, Q, chunk):
        d = squared_distances(queries[s : s + chunk], database)
        if allowed is not None:
            d[~allowed[s : s + chunk]] = np.inf
        order = np.argsort(d, axis=1, kind="stable")[:, :k]
        dd = np.take_along_axis(d, order, axis=1)
        order[np.isinf(dd)] = -1
        idx[s : s + chunk], dist[s : s + chunk] = order, dd
    return idx, dist


def recall_at_n_curve(
    ranked: np.ndarray, positives: Sequence[np.ndarray], max_n: int | None = None
) -> np.ndarray:
    """Recall@1 … Recall@max_n over queries with ≥ 1 positive.

    ranked: (Q, k) database indices, nearest first (−1 = none); positives: Q index arrays.
    Returns (max_n,) float64; NaN where no query has a positive.
    """
    max_n = ranked.shape[1] if max_n is None else max_n
    first_hit = []
    for row, pos in zip(ranked, positives, strict=True):
        if len(pos) == 0:
            continue
        hits = np.flatnonzero(np.isin(row, pos) & (row >= 0))
        first_hit.append(hits[0] if len(hits) else np.inf)
    if not first_hit:
        return np.full(max_n, np.nan)
    fh = np.asarray(first_hit, dtype=np.float64)
    return np.array([(fh < n).mean() for n in range(1, max_n + 1)])


def average_recall_at_n(curve: np.ndarray, n: int) -> float:
    """AR@N (NCLT): mean of Recall@1 … Recall@N."""
    return float(np.mean(curve[:n]))


def pr_curve(
    top1_distance: np.ndarray, top1_correct: np.ndarray, has_positive: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Precision, recall and thresholds of the loop-closure protocol (see module doc).

    Returns arrays of length T + 1: index 0 is t = −∞, then each distinct distance ascending.
    """
    d = np.asarray(top1_distance, dtype=np.float64)
    d = np.where(np.isnan(d), np.inf, d)  # no distance: the worst, accepted only at +inf
    ok = np.asarray(top1_correct, dtype=bool)
    has = np.asarray(has_positive, dtype=bool)
    if d.size == 0:
        return np.ones(1), np.ones(1), np.full(1, -np.inf)
    order = np.argsort(d, kind="stable")
    d, ok, has = d[order], ok[order], has[order]
    tp = np.cumsum(ok)
    fp = np.cumsum(~ok)
    accepted_with_loop = np.cumsum(has)
    # The last index of each group of equal distances is where that threshold lands.
    last = np.flatnonzero(np.r_[d[1:] != d[:-1], True])
    tp, fp = np.r_[0, tp[last]], np.r_[0, fp[last]]
    fn = has.sum() - np.r_[0, accepted_with_loop[last]]
    thresholds = np.r_[-np.inf, d[last]]
    with np.errstate(invalid="ignore", divide="ignore"):
        precision = np.where(tp + fp > 0, tp / np.maximum(tp + fp, 1), 1.0)
        # TP + FN = 0 with some query having a positive means every such query was accepted
        # with a wrong candidate: recall 0, not 1.
        no_positive = 1.0 if not has.any() else 0.0
        recall = np.where(tp + fn > 0, tp / np.maximum(tp + fn, 1), no_positive)
    return precision, recall, thresholds


def pr_curve_reference(
    top1_distance: np.ndarray, top1_correct: np.ndarray, has_positive: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Slow, obvious twin of :func:`pr_curve`, one threshold at a time. For tests."""
    dist = [math.inf if math.isnan(float(x)) else float(x) for x in top1_distance]
    thresholds = [-math.inf, *sorted(set(dist))]
    any_positive = any(bool(h) for h in has_positive)
    precision, recall = [], []
    for t in thresholds:
        tp = fp = fn = 0
        for d, ok, has in zip(dist, top1_correct, has_positive, strict=True):
            if d <= t:
                tp, fp = tp + bool(ok), fp + (not ok)
            elif has:
                fn += 1
        precision.append(tp / (tp + fp) if tp + fp else 1.0)
        recall.append(tp / (tp + fn) if tp + fn else (0.0 if any_positive else 1.0))
    return np.array(precision), np.array(recall), np.array(thresholds)


def pr_auc(precision: np.ndarray, recall: np.ndarray) -> float:
    """Trapezoidal area under the PR curve, integrating over recall (non-decreasing)."""
    return float(np.trapezoid(precision, recall))


def f1_scores(precision: np.ndarray, recall: np.ndarray) -> np.ndarray:
    """F1 at each point of a PR curve (0 where precision and recall are both 0)."""
    p, r = np.asarray(precision), np.asarray(recall)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(p + r > 0, 2 * p * r / (p + r), 0.0)


def f1_max(precision: np.ndarray, recall: np.ndarray) -> float:
    f1 = f1_scores(precision, recall)
    return float(f1.max()) if len(f1) else 0.0


@dataclass(frozen=True)
class LoopClosureResult:
    auc: float
    f1max: float
    recall_at_1: float
    recall_at_1pct: float
    recall_curve: np.ndarray  # Recall@1 … Recall@max_n
    precision: np.ndarray
    recall: np.ndarray
    thresholds: np.ndarray
    n_queries: int
    n_with_loop: int
    # Per scored query (ascending frame index): the frame, its top-1 candidate and distance,
    # whether that candidate is a positive, whether the query has any — what
    # :func:`errors_at_f1max` reads.
    queries: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    top1: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    top1_distance: np.ndarray = field(default_factory=lambda: np.zeros(0))
    top1_correct: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    has_loop: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))

    @property
    def f1max_threshold(self) -> float:
        """The acceptance threshold where F1 peaks (the first, i.e. strictest, on ties)."""
        f1 = f1_scores(self.precision, self.recall)
        return float(self.thresholds[int(np.argmax(f1))]) if len(f1) else -math.inf

    def summary(self) -> dict[str, float | int]:
        return {
            "auc": self.auc,
            "f1max": self.f1max,
            "recall@1": self.recall_at_1,
            "recall@1%": self.recall_at_1pct,
            "queries": self.n_queries,
            "queries_with_loop": self.n_with_loop,
        }


def evaluate_loop_closure(
    descriptors: np.ndarray,
    positives: Sequence[np.ndarray],
    *,
    exclude_recent_frames: int = 100,
    query_mask: np.ndarray | None = None,
    max_n: int = 25,
) -> LoopClosureResult:
    """Score one sequence under the loop-closure protocol (see module doc).

    descriptors: (N, D); positives: N arrays of earlier frame indices that are true loops
    (``LoopGroundTruth.positives()``); query_mask: optional (N,) bool to score a subset
    (e.g. reverse-direction revisits) — the database stays the full past.
    """
    desc = np.asarray(descriptors)

    def by_l2(queries: np.ndarray, db_size: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        allowed = np.arange(len(desc))[None, :] < db_size[:, None]
        return nearest(desc[queries], desc, k, allowed=allowed)

    return evaluate_retrieval(
        by_l2,
        len(desc),
        positives,
        exclude_recent_frames=exclude_recent_frames,
        query_mask=query_mask,
        max_n=max_n,
    )


Retriever = Callable[[np.ndarray, np.ndarray, int], tuple[np.ndarray, np.ndarray]]


def evaluate_retrieval(
    retrieve: Retriever,
    n_frames: int,
    positives: Sequence[np.ndarray],
    *,
    exclude_recent_frames: int = 100,
    query_mask: np.ndarray | None = None,
    max_n: int = 25,
) -> LoopClosureResult:
    """The loop-closure protocol for any retrieval method (e.g. Scan Context's two stages).

    ``retrieve(queries, db_size, k)`` returns, for query frame ``queries[i]`` searching frames
    0 … db_size[i] − 1, its k best frames (Q, k), padded with −1, and their distances (Q, k);
    only the top-1 distance enters the PR curve, the ranks give Recall@N.
    """
    N = n_frames
    if len(positives) != N:
        raise ValueError(f"{N} frames but {len(positives)} positive lists")
    queries = np.arange(exclude_recent_frames + 1, N)
    if query_mask is not None:
        queries = queries[np.asarray(query_mask, dtype=bool)[queries]]
    db_size = queries - exclude_recent_frames  # frames 0 … i − exclude_recent_frames − 1
    k_pct = np.maximum(1, np.ceil(0.01 * db_size)).astype(int)
    k = int(max(max_n, k_pct.max(initial=1)))
    ranked, dist = retrieve(queries, db_size, k)
    # Only database frames count: a positive inside the excluded window cannot be retrieved.
    pos = [
        np.asarray(positives[int(i)])[np.asarray(positives[int(i)]) < n]
        for i, n in zip(queries, db_size, strict=True)
    ]
    has = np.array([len(p) > 0 for p in pos], dtype=bool)
    correct = np.array([r[0] in p for r, p in zip(ranked, pos, strict=True)], dtype=bool)
    precision, recall, thresholds = pr_curve(dist[:, 0], correct, has)
    curve = recall_at_n_curve(ranked, pos, max_n)
    pct_hits = [
        bool(np.isin(r[:kk], p).any())
        for r, p, kk in zip(ranked, pos, k_pct, strict=True)
        if len(p)
    ]
    defined = bool(has.any())  # a subset without loops has no AUC or F1max
    return LoopClosureResult(
        auc=pr_auc(precision, recall) if defined else math.nan,
        f1max=f1_max(precision, recall) if defined else math.nan,
        recall_at_1=float(curve[0]) if len(curve) else math.nan,
        recall_at_1pct=float(np.mean(pct_hits)) if pct_hits else math.nan,
        recall_curve=curve,
        precision=precision,
        recall=recall,
        thresholds=thresholds,
        n_queries=len(queries),
        n_with_loop=int(has.sum()),
        queries=queries,
        top1=ranked[:, 0] if ranked.shape[1] else np.full(len(queries), -1),
        top1_distance=dist[:, 0] if dist.shape[1] else np.full(len(queries), np.inf),
        top1_correct=correct,
        has_loop=has,
    )


def pooled(results: Sequence[LoopClosureResult]) -> LoopClosureResult:
    """Several sequences' loop-closure results as one: every scored query of each (its
    database still its own sequence's past) in one PR curve, so one threshold is judged on
    all of them (a model calibrated for several towns or sensors at once); Recall@N and
    Recall@1% over all their queries with a loop. ``queries`` and ``top1`` stay frame
    indices within each query's own sequence."""
    if not results:
        raise ValueError("pooled() needs at least one result")
    cat = np.concatenate
    dist, correct = cat([r.top1_distance for r in results]), cat([r.top1_correct for r in results])
    has = cat([r.has_loop for r in results])
    precision, recall, thresholds = pr_curve(dist, correct, has)
    loops = np.array([r.n_with_loop for r in results], dtype=np.float64)
    defined = bool(has.any())

    some = loops > 0  # a sequence without loops has no Recall@N (NaN) and weighs nothing

    def weighted(values: list[float] | np.ndarray) -> float:
        v = np.asarray(values, dtype=np.float64)[some]
        return float((v * loops[some]).sum() / loops.sum()) if defined else math.nan

    curves = [r.recall_curve for r, s in zip(results, some, strict=True) if s]
    if len({len(c) for c in curves}) > 1:
        raise ValueError("pooled() needs results scored with the same max_n")
    curve = (
        (np.stack(curves) * loops[some, None]).sum(0) / loops.sum()
        if curves
        else results[0].recall_curve.copy()  # no loops anywhere: as one sequence gives it
    )
    return LoopClosureResult(
        auc=pr_auc(precision, recall) if defined else math.nan,
        f1max=f1_max(precision, recall) if defined else math.nan,
        recall_at_1=weighted([r.recall_at_1 for r in results]),
        recall_at_1pct=weighted([r.recall_at_1pct for r in results]),
        recall_curve=curve,
        precision=precision,
        recall=recall,
        thresholds=thresholds,
        n_queries=sum(r.n_queries for r in results),
        n_with_loop=int(loops.sum()),
        queries=cat([r.queries for r in results]),
        top1=cat([r.top1 for r in results]),
        top1_distance=dist,
        top1_correct=correct,
        has_loop=has,
    )
