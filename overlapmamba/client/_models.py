"""Typed results. Built from the service's JSON; numbers stay plain Python or numpy."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Descriptor:
    vector: np.ndarray  # (D,) float32, unit norm
    model_id: str
    timings_ms: dict[str, float | None] = field(default_factory=dict)


@dataclass(frozen=True)
class MapInfo:
    map_id: str
    model_id: str
    keyframes: int
    index: dict[str, Any]
    seq: int | None  # the FAISS backend's write sequence; None on Qdrant
    created: bool | None = None
    keep_geometry: bool = True
    sensor: str | None = None  # the sensor of scans that name none; None: the model's own
    mount: dict[str, float] | None = None  # where it sits (height, pitch_deg, roll_deg)

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> MapInfo:
        return cls(
            map_id=d["map_id"],
            model_id=d["model_id"],
            keyframes=int(d["keyframes"]),
            index=d["index"],
            seq=None if d.get("seq") is None else int(d["seq"]),
            created=d.get("created"),
            keep_geometry=bool(d.get("keep_geometry", True)),
            sensor=d.get("sensor"),
            mount=d.get("mount"),
        )


@dataclass(frozen=True)
class Keyframe:
    keyframe_id: str
    robot_id: str
    session_id: str
    timestamp: float
    pose: list[float] | None
    created: bool | None = None
    sensor: str | None = None  # the sensor of the scan it came from; None: not recorded
    # the answer is a retry's, after an earlier try's answer was lost: created False may be
    # that earlier try's own insert (the client cannot tell it from a keyframe there before)
    retried: bool = False

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Keyframe:
        return cls(
            keyframe_id=d["keyframe_id"],
            robot_id=d["robot_id"],
            session_id=d["session_id"],
            timestamp=float(d["timestamp"]),
            pose=d.get("pose"),
            created=d.get("created"),
            sensor=d.get("sensor"),
        )


@dataclass(frozen=True)
class Match:
    keyframe_id: str
    distance: float
    similarity: float
    robot_id: str
    session_id: str
    timestamp: float
    pose: list[float] | None
    yaw_deg: float | None
    yaw_confidence: float | None
    relative_pose: np.ndarray | None = None  # (4, 4) T_keyframe←query, when registered
    verification: Verification | None = None  # None: not verified (not asked, or beyond k)
    score: float | None = None  # the re-ranking score (lower is better); None: not re-ranked
    sensor: str | None = None  # the keyframe's sensor; None: not recorded

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Match:
        v = d.get("verification")
        return cls(
            keyframe_id=d["keyframe_id"],
            distance=float(d["distance"]),
            similarity=float(d["similarity"]),
            robot_id=d["robot_id"],
            session_id=d["session_id"],
            timestamp=float(d["timestamp"]),
            pose=d.get("pose"),
            yaw_deg=d.get("yaw_deg"),
            yaw_confidence=d.get("yaw_confidence"),
            score=d.get("score"),
            sensor=d.get("sensor"),
            relative_pose=_matrix(d.get("relative_pose")),
            verification=None if v is None else Verification.from_json(v),
        )


def _matrix(values: list[float] | None) -> np.ndarray | None:
    return _square(values, 4)


def _square(values: list[float] | None, n: int) -> np.ndarray | None:
    return None if values is None else np.asarray(values, dtype=np.float64).reshape(n, n)


@dataclass(frozen=True)
class Verification:
    """A candidate's registration against its keyframe's geometry. ``verified`` None: not
    registered, ``reason`` says why (the keyframe keeps no geometry, or an earlier candidate
    verified first: the server's ``verify.stop_at_first``)."""

    verified: bool | None
    fitness: float | None
    rmse: float | None
    reason: str | None
    # the best fit of the pair registered from the other quarter turns (the server's
    # verify.ambiguity_margin); None: not checked, or a server that predates the check
    rival_fitness: float | None = None

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Verification:
        return cls(
            d.get("verified"),
            d.get("fitness"),
            d.get("rmse"),
            d.get("reason"),
            d.get("rival_fitness"),
        )


@dataclass(frozen=True)
class LoopClosure:
    """The server's call. ``verified`` True: the keyframe ``keyframe_id`` was registered
    and ``relative_pose`` (4×4, T_keyframe←query) is the edge to add to a pose graph; None:
    the call is the re-ranking score or the descriptor distance alone (``rule``; no geometry,
    or verify=False)."""

    accepted: bool
    threshold: float
    margin_top1_top2: float | None
    keyframe_id: str | None = None
    verified: bool | None = None
    relative_pose: np.ndarray | None = None
    fitness: float | None = None
    rule: str = "distance"  # what threshold and the margin compare: "score" or "distance"
    # (6, 6) relative_pose's covariance: x, y, z (m), then the rotation vector (rad), on the
    # right in the query's frame (overlapmamba.core.posecov); None: the server gives none
    covariance: np.ndarray | None = None

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> LoopClosure:
        return cls(
            accepted=bool(d["accepted"]),
            threshold=float(d["threshold"]),
            margin_top1_top2=d.get("margin_top1_top2"),
            keyframe_id=d.get("keyframe_id"),
            verified=d.get("verified"),
            relative_pose=_matrix(d.get("relative_pose")),
            fitness=d.get("fitness"),
            rule=d.get("rule", "distance"),
            covariance=_square(d.get("covariance"), 6),
        )


@dataclass(frozen=True)
class QueryResult:
    matches: list[Match]
    loop_closure: LoopClosure
    timings_ms: dict[str, float | None]

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> QueryResult:
        return cls(
            matches=[Match.from_json(m) for m in d["matches"]],
            loop_closure=LoopClosure.from_json(d["loop_closure"]),
            timings_ms=d.get("timings_ms", {}),
        )


@dataclass(frozen=True)
class ObserveResult(QueryResult):
    inserted: bool = False
    keyframe_id: str | None = None
    insert_reason: str = ""
    seq: Any = None  # the stream's correlation value
    # the answer is a retry's, after an earlier try's answer was lost: an "existing"
    # keyframe is then that earlier try's insert of this very observation
    retried: bool = False

    @property
    def keyframe(self) -> str | None:
        """The keyframe this observation became (inserted now, or by the earlier try of a
        retry whose answer was lost), else None."""
        made = self.inserted or (self.retried and self.insert_reason == "existing")
        return self.keyframe_id if made else None

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> ObserveResult:
        q = QueryResult.from_json(d)
        return cls(
            matches=q.matches,
            loop_closure=q.loop_closure,
            timings_ms=q.timings_ms,
            inserted=bool(d["inserted"]),
            keyframe_id=d.get("keyframe_id"),
            insert_reason=d.get("insert_reason", ""),
            seq=d.get("seq"),
        )


@dataclass(frozen=True)
class BatchInsertResult:
    inserted: int
    existing: int
    keyframes: list[Keyframe]
    retried: bool = False  # as Keyframe.retried: "existing" may count an earlier try's


@dataclass(frozen=True)
class Observation:
    """One scan for ``stream()``: the robot's scan at ``timestamp`` (s), optional pose
    (x, y, z, qx, qy, qz, qw), insert mode ("auto", "always", "never") and whether the
    server verifies its candidates geometrically; ``sensor`` and ``mount``
    (HEIGHT[,PITCH[,ROLL]]): this scan's, when they are not the stream's."""

    scan: Any
    timestamp: float
    pose: Any = None
    insert: str = "auto"
    verify: bool = True
    sensor: str | None = None
    mount: str | float | tuple[float, ...] | None = None
    # sent again after a stream failed with it unanswered (the error's ``unanswered``): it
    # may have been carried out, so its answer comes with ``retried`` set, as an HTTP
    # retry's does (an "existing" keyframe may be this observation's own)
    retry: bool = False
