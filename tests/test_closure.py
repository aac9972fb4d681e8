"""An answer's loop-closure call (overlapmamba.service.closure), without a server: the order's
call by score or distance and margin, and the verified candidate chosen over it."""

from __future__ import annotations

import numpy as np

from overlapmamba.service.answers import LoopClosure
from overlapmamba.service.calibrated_settings import LoopClosureSettings
from overlapmamba.service.closure import unverified_call, verified_closure
from overlapmamba.service.domain import Keyframe, Match
from overlapmamba.service.verify import Verdict


def _match(name: str, distance: float, score: float | None = None, verdict=None) -> Match:
    kf = Keyframe(0, name, "r", "s", 0.0, None, "h", 0, 0.0)
    return Match(kf, 1 - distance**2 / 2, distance, 0.0, 1.0, verdict, score)


def _verdict(ok: bool | None, fitness: float | None) -> Verdict:
    return Verdict(ok, fitness, 0.1, None if ok else "why", np.eye(4) if fitness else None)


def test_the_orders_call_is_the_top_ones_score_when_reranked_else_its_distance():
    lc = LoopClosureSettings(accept_distance=0.2, max_score=0.0, min_margin=0.05)
    near = unverified_call([_match("a", 0.1), _match("b", 0.3)], lc)
    assert (near.accepted, near.rule, near.threshold) == (True, "distance", 0.2)
    assert abs(near.margin - 0.2) < 1e-9
    close_second = unverified_call([_match("a", 0.1), _match("b", 0.12)], lc)
    assert not close_second.accepted  # the runner-up within min_margin
    scored = unverified_call([_match("a", 0.5, -0.1), _match("b", 0.6, 0.2)], lc)
    assert (scored.accepted, scored.rule, scored.threshold) == (True, "score", 0.0)
    assert not unverified_call([], lc).accepted


def test_a_verified_candidate_wins_and_none_judged_keeps_the_orders_call():
    call = LoopClosure(True, 0.2, 0.1, keyframe_id="a")
    best = verified_closure(
        [
            _match("a", 0.1, verdict=_verdict(False, 0.2)),
            _match("b", 0.2, verdict=_verdict(True, 0.6)),
            _match("c", 0.3, verdict=_verdict(True, 0.9)),
        ],
        call,
    )
    assert (best.accepted, best.verified, best.keyframe_id, best.fitness) == (True, True, "c", 0.9)
    refused = verified_closure([_match("a", 0.1, verdict=_verdict(False, 0.1))], call)
    assert (refused.accepted, refused.verified, refused.keyframe_id) == (False, False, None)
    unjudged = [_match("a", 0.1, verdict=_verdict(None, None)), _match("b", 0.2)]
    assert verified_closure(unjudged, call) is call  # no geometry: the order's call stands
