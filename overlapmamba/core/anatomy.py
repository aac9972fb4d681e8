"""Where a loop-closure result goes wrong at its best operating point.

F1max says how much is lost, not why. At the threshold where F1 peaks
(:attr:`~overlapmamba.core.metrics.LoopClosureResult.f1max_threshold`) every query is one of:

* a **true closure**: accepted, and its top-1 candidate is a true loop;
* a **false alarm**: accepted with a candidate that is not a loop. By the candidate's
  distance from the query (metres, from the poses): a *neighbour* (within ``far`` metres —
  the same street, usually still sharing a little of the scan: ``overlapping`` counts those
  whose pair is in the loop table with an overlap above 0 but not above its loop threshold)
  or a *look-alike* elsewhere (``far`` metres or more). ``with_a_loop`` counts the false
  alarms whose query did have a true loop, ranked below the wrong candidate;
* a **missed loop**: a query with a true loop that is not a true closure, either because its
  top-1 is wrong (``wrong_top1``, accepted or not) or because its top-1 is right but farther
  than the threshold (``rejected``: the loop is found but not trusted).

Neighbours call for a sharper sense of position (the training's ambiguous band), look-alikes
for more distinctive descriptors, rejected loops for tighter clusters of revisits.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from overlapmamba.core.metrics import LoopClosureResult
from overlapmamba.core.overlap import LoopGroundTruth

FAR_M = 50.0  # a wrong candidate at least this far from the query is a look-alike


def _pair_overlap(gt: LoopGroundTruth, query: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Overlap of each (query, reference) pair from the loop table; NaN where it is absent."""
    n = max(gt.n_frames, 1)
    keys = gt.query.astype(np.int64) * n + gt.reference.astype(np.int64)
    order = np.argsort(keys, kind="stable")
    keys = keys[order]
    want = query.astype(np.int64) * n + reference.astype(np.int64)
    at = np.clip(np.searchsorted(keys, want), 0, max(len(keys) - 1, 0))
    out = np.full(len(want), np.nan)
    if len(keys):
        hit = keys[at] == want
        out[hit] = gt.overlap[order][at[hit]]
    return out


def errors_at_f1max(
    result: LoopClosureResult,
    gt: LoopGroundTruth,
    positions: np.ndarray,
    *,
    far: float = FAR_M,
    threshold: float | None = None,
) -> dict[str, Any]:
    """The anatomy of ``result`` at its F1max threshold, or at ``threshold`` (an operating
    point of one's own), see the module doc. ``positions``: (N, ≥2) scan positions in
    metres (e.g. the poses' translations), indexed like the frames."""
    if len(result.queries) != len(result.top1) or len(result.queries) != result.n_queries:
        raise ValueError("the result carries no per-query top-1 (made by an older evaluator)")
    t = result.f1max_threshold if threshold is None else float(threshold)
    accepted = result.top1_distance <= t
    right, has = result.top1_correct, result.has_loop
    alarm = accepted & ~right
    q, c = result.queries[alarm], result.top1[alarm]
    xy = np.asarray(positions, dtype=np.float64)[:, :2]
    metres = np.linalg.norm(xy[q] - xy[c], axis=1) if len(q) else np.zeros(0)
    overlap = _pair_overlap(gt, q, c)
    missed = has & ~(accepted & right)
    rejected = missed & right
    return {
        "threshold": t,
        "accepted": int(accepted.sum()),
        "true_closures": int((accepted & right).sum()),
        "false_alarms": {
            "total": int(alarm.sum()),
            "neighbours": int((metres < far).sum()),
            "look_alikes": int((metres >= far).sum()),
            "overlapping": int(((overlap > 0) & (overlap <= gt.min_overlap)).sum()),
            "with_a_loop": int((alarm & has).sum()),
            "median_m": float(np.median(metres)) if len(metres) else None,
        },
        "missed_loops": {
            "total": int(missed.sum()),
            "wrong_top1": int((missed & ~right).sum()),
            "rejected": int(rejected.sum()),
        },
        "far_m": far,
    }
