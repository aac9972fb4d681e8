"""Hard negatives mined by the current model: the distant look-alikes a batch never meets.

A batch holds a few places (4 groups of anchor, positives, near miss), so the hardest
negative a query sees is nearly always its near miss: a different place within the pair
table's radius. Loop closure fails on something else: a *distant* place that looks alike
(perceptual aliasing), accepted under one global distance threshold. Random batches almost
never contain one. Mining puts them there:

    epoch start → describe a random pool of training scans with the current weights
      → for each pool anchor: its K nearest pool scans in descriptor space that are clearly
        a different place (not overlapping it above the negative threshold)
      → a share of the epoch's groups takes one of them as its negative (BatchSampler)

The pool and the picks come from the epoch's seeded generator, and the descriptors from the
epoch's starting weights, so ``--resume`` stays exact.

Shapes: pool (P,) global scan indices; descriptors (P, D) unit vectors; candidates: anchor →
(≤ K,) global indices, nearest first.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class HardNegatives:
    candidates: dict[int, np.ndarray]  # anchor → its hardest clearly different scans
    anchors: np.ndarray  # anchors with at least one candidate (sorted)
    stats: dict[str, float]  # what mining found (logged with the epoch)


def mine(
    pool: np.ndarray,
    descriptors: np.ndarray,
    related: Callable[[int], np.ndarray],
    anchors: np.ndarray,
    top: int,
) -> HardNegatives:
    """For every pool scan that is an anchor: its ``top`` nearest pool scans (squared L2
    between unit descriptors) among those ``related(anchor)`` does not list (scans that
    overlap it above the negative threshold) and other than itself."""
    d = np.asarray(descriptors, np.float32)
    d2 = np.clip(2.0 - 2.0 * (d @ d.T), 0.0, None)  # (P, P), unit vectors
    is_anchor = np.isin(pool, anchors)
    where = {int(g): i for i, g in enumerate(pool)}
    candidates: dict[int, np.ndarray] = {}
    mined_d2, random_d2 = [], []
    for i in np.flatnonzero(is_anchor):
        a = int(pool[i])
        row = d2[i].copy()
        row[i] = np.inf
        for j in related(a):
            k = where.get(int(j))
            if k is not None:
                row[k] = np.inf
        k = min(top, int(np.isfinite(row).sum()))
        if k == 0:
            continue
        nearest = np.argpartition(row, k - 1)[:k]
        nearest = nearest[np.argsort(row[nearest], kind="stable")]
        candidates[a] = pool[nearest]
        mined_d2.append(float(row[nearest].mean()))
        random_d2.append(float(row[np.isfinite(row)].mean()))
    stats = {
        "pool": float(len(pool)),
        "anchors": float(len(candidates)),
        "mined_d2": float(np.mean(mined_d2)) if mined_d2 else float("nan"),
        "pool_d2": float(np.mean(random_d2)) if random_d2 else float("nan"),
    }
    return HardNegatives(candidates, np.array(sorted(candidates), np.int64), stats)
