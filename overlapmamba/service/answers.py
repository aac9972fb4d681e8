"""What the use cases (:mod:`overlapmamba.service.places`) are given besides a scan, and what they
answer: typed results that the routes turn into their HTTP shapes, once, at the edge."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from overlapmamba.service.domain import InsertResult, Match


@dataclass(frozen=True)
class LoopClosure:
    """The call on a query: is it a revisit of a keyframe, and which one.

    With verification (a scan query, ``verify.candidates`` > 0, candidates with geometry): the
    verified candidate (the first in the answer's order under ``verify.stop_at_first``, the
    default; of highest fitness without it), with its relative pose. Otherwise (a descriptor
    query, ``verify=false``, keyframes without geometry): the top match when its re-ranking
    score is under ``loop_closure.max_score`` (a re-ranked answer, :mod:`.ranking`), or its
    descriptor distance under ``loop_closure.accept_distance`` — ``verified`` is then None."""

    accepted: bool
    threshold: float  # loop_closure.max_score or accept_distance (the unverified call)
    margin: float | None  # runner-up − best, in the rule's units
    rule: Literal["score", "distance"] = "distance"  # what threshold and margin compare
    keyframe_id: str | None = None
    verified: bool | None = None
    relative_pose: np.ndarray | None = None  # (4, 4) T_keyframe←query
    fitness: float | None = None
    # (6, 6) the relative pose's covariance (overlapmamba.core.posecov: x, y, z, then the
    # rotation vector, on the right); None without a covariance calibration
    covariance: np.ndarray | None = None


@dataclass
class Answer:
    """A place query's answer: the top k matches, best first, and the loop-closure call."""

    matches: list[Match]
    loop_closure: LoopClosure
    timings: dict[str, float]  # ms per stage, and "total"


InsertReason = Literal["first", "distance", "time", "always", "never", "not_due", "existing"]


@dataclass
class Observed(Answer):
    inserted: bool
    keyframe_id: str | None
    reason: InsertReason  # why it was (or was not) inserted


@dataclass(frozen=True)
class Inserted:
    result: InsertResult
    timings: dict[str, float]


@dataclass(frozen=True)
class Observation:
    """What a robot says about its scan besides the bytes."""

    robot_id: str
    session_id: str
    timestamp: float
    pose: list[float] | None = None
    insert: Literal["auto", "always", "never"] = "auto"
    k: int = 10
    verify: bool = True

    @property
    def keyframe_id(self) -> str:
        """The keyframe this observation becomes: ``robot:session:timestamp`` (a retry of it
        names the same one)."""
        return f"{self.robot_id}:{self.session_id}:{self.timestamp!r}"
