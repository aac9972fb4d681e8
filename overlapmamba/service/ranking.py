"""The answer's order: the descriptor shortlist re-ranked by the yaw features.

A scan query's matches come from the index nearest descriptor first, each of the first
``rerank.shortlist`` with the yaw features' correlation at the best roll (``yaw_confidence``, from
the relative-yaw estimate). They are re-ordered by the score of :mod:`overlapmamba.core.rerank`,
distance² − ``rerank.weight`` · yaw_confidence, and carry it; the loop-closure call then
thresholds that score (``loop_closure.max_score``). Where the shortlist cannot be scored as a
whole — a descriptor query (no yaw features), a keyframe inserted without yaw features among
the first ``k``, re-ranking off — the answer keeps the descriptor order and no score, and
``loop_closure.accept_distance`` decides: a score is never compared with a distance.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from overlapmamba.core.rerank import Rerank, by_score
from overlapmamba.service.domain import Match
from overlapmamba.service.settings import RerankSettings


def rerank_params(s: RerankSettings) -> Rerank:
    return Rerank(shortlist=s.shortlist, weight=s.weight)


def shortlist(k: int, p: Rerank) -> int:
    """How many matches a scan query must fetch (with yaw) to answer ``k`` re-ranked."""
    return max(k, p.shortlist) if p.on else k


def rerank_matches(matches: list[Match], p: Rerank) -> list[Match]:
    """The first ``p.shortlist`` matches re-ordered by score (ties keep the descriptor order) and
    scored, the rest as they came; unchanged when they cannot all be scored."""
    head = matches[: p.shortlist]
    if not p.on or not head or any(m.yaw_confidence is None for m in head):
        return matches
    order, s = by_score(
        np.array([m.distance for m in head]) ** 2,
        np.array([m.yaw_confidence for m in head], dtype=np.float64),
        p.weight,
    )
    ranked = [replace(head[i], score=float(x)) for i, x in zip(order, s, strict=True)]
    return ranked + matches[p.shortlist :]
