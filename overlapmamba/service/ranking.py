"""The answer's order: the descriptor shortlist re-ranked by the yaw features.

A scan query's matches come from the index nearest descriptor first, each of the first
``rerank.shortlist`` with the yaw features' correlation at the best roll (``yaw_confidence``, from
the relative-yaw estimate). They are re-ordered by the score of :mod:`overlapmamba.core.rerank`,
d² − ``rerank.weight`` · yaw_confidence, and carry it; the loop-closure call then
thresholds that score (``loop_closure.max_score``). d² is the squared descriptor distance, or,
with ``rerank.score = "network"`` and a model whose first stage is mixed, the squared distance
between the network's own descriptors inside the two vectors (each candidate's as the map
stores it). Where the shortlist cannot be scored as a whole — a descriptor query (no yaw
features), a keyframe inserted without yaw features among the first ``k``, re-ranking off —
the answer keeps the descriptor order and no score, and ``loop_closure.accept_distance``
decides: a score is never compared with a distance.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from overlapmamba.core.modelmeta import EncoderMetadata
from overlapmamba.core.rerank import Rerank, by_score, with_score
from overlapmamba.service.domain import Match
from overlapmamba.service.settings import RerankSettings


def rerank_params(s: RerankSettings, meta: EncoderMetadata | None = None) -> Rerank:
    """The second stage the settings ask for, for the model of ``meta`` (what ``score``
    measures depends on its first stage; None: a model whose first stage is its descriptor).
    A ValueError names a score the model cannot give."""
    p = Rerank(shortlist=s.shortlist, weight=s.weight)
    if meta is not None:
        return with_score(p, s.score, meta)
    if s.score != "stage":
        raise ValueError(f"rerank.score {s.score!r} needs the model's first stage")
    return p


def shortlist(k: int, p: Rerank) -> int:
    """How many matches a scan query must fetch (with yaw) to answer ``k`` re-ranked."""
    return max(k, p.shortlist) if p.on else k


def rerank_matches(matches: list[Match], p: Rerank, query: np.ndarray | None = None) -> list[Match]:
    """The first ``p.shortlist`` matches re-ordered by score (ties keep the descriptor order) and
    scored, the rest as they came; unchanged when they cannot all be scored. With ``p.part``
    the score's d² is between ``p.rows`` of the ``query`` descriptor and of each candidate's
    stored one (``Keyframe.descriptor``)."""
    head = matches[: p.shortlist]
    if not p.on or not head or any(m.yaw_confidence is None for m in head):
        return matches
    if p.part is None:
        d2 = np.array([m.distance for m in head], np.float64) ** 2
    else:
        stored = [d for m in head if (d := m.keyframe.descriptor) is not None]
        if query is None or len(stored) < len(head):
            return matches
        rows = p.rows(np.stack([np.asarray(query, np.float32), *stored]))
        d2 = ((rows[1:].astype(np.float64) - rows[0]) ** 2).sum(axis=1)
    order, s = by_score(d2, np.array([m.yaw_confidence for m in head], np.float64), p.weight)
    ranked = [replace(head[i], score=float(x)) for i, x in zip(order, s, strict=True)]
    return ranked + matches[p.shortlist :]
