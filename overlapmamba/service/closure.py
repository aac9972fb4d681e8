"""An answer's loop-closure call: from the order alone (the top-1 under a threshold, the
runner-up behind by a margin) and, where candidates were registered, from their verdicts
(:mod:`overlapmamba.service.verify`). :class:`~overlapmamba.service.places.PlaceService` makes
both calls on every scan query and observation."""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING, Literal

import numpy as np

from overlapmamba.core import posecov
from overlapmamba.service.answers import LoopClosure
from overlapmamba.service.calibrated_settings import CovarianceSettings, LoopClosureSettings
from overlapmamba.service.domain import Match

if TYPE_CHECKING:
    from overlapmamba.service.verify import Verdict


def unverified_call(matches: list[Match], lc: LoopClosureSettings) -> LoopClosure:
    """The loop-closure call from the order alone: the top-1's score under
    ``loop_closure.max_score`` when the answer was re-ranked
    (:mod:`overlapmamba.service.ranking`),
    else its distance under ``accept_distance``; and the runner-up at least ``min_margin``
    behind, in the same units."""
    rule: Literal["score", "distance"]
    if matches and matches[0].score is not None:
        rule, threshold = "score", lc.max_score
        values = [x.score for x in matches[:2] if x.score is not None]
    else:
        rule, threshold = "distance", lc.accept_distance
        values = [x.distance for x in matches[:2]]
    margin = values[1] - values[0] if len(values) > 1 else None
    accepted = bool(
        values and values[0] <= threshold and (margin is None or margin >= lc.min_margin)
    )
    return LoopClosure(accepted, threshold, margin, rule=rule)


def verified_closure(
    candidates: list[Match],
    descriptor_call: LoopClosure,
    cov: CovarianceSettings | None = None,
) -> LoopClosure:
    """The verified candidate of highest fitness (the only one registered as verified
    under ``verify.stop_at_first``); the descriptor's call only when no
    candidate could be judged (none has geometry). Candidates refused by the descriptor
    gate count as judged: a query far from every keyframe closes no loop. ``cov``: the
    covariance its relative pose carries (``covariance.*``; none when they are null)."""
    verdicts = [(c, c.verification) for c in candidates if c.verification is not None]
    judged = [(c, v) for c, v in verdicts if v.verified is not None]
    if not judged:
        return descriptor_call
    ok = [(c, v) for c, v in judged if v.verified]
    if not ok:
        return replace(descriptor_call, accepted=False, keyframe_id=None, verified=False)
    best, v = max(ok, key=lambda cv: cv[1].fitness or 0.0)
    return replace(
        descriptor_call,
        accepted=True,
        keyframe_id=best.keyframe.keyframe_id,
        verified=True,
        relative_pose=v.relative_pose,
        fitness=v.fitness,
        covariance=_covariance(v, cov),
    )


def _covariance(v: Verdict, cov: CovarianceSettings | None) -> np.ndarray | None:
    if cov is None or cov.estimator is None or cov.scale is None:
        return None
    return posecov.covariance(v.hessian, v.residual, cov.estimator, cov.scale)
