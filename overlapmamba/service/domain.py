"""The service's own vocabulary, below HTTP and below every storage engine: map ids, keyframes
as they are written and as they are stored, query filters, matches, and the checks every
backend applies to what it is asked to write.

Nothing here knows FastAPI, SQLite, FAISS or Qdrant: routes (``overlapmamba.service.api``) translate
HTTP into these types, backends (``overlapmamba.service.backends``) store and search them.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from overlapmamba.service.errors import BadRequest, Conflict, Unprocessable
from overlapmamba.service.settings import MAP_ID_PATTERN

if TYPE_CHECKING:
    from overlapmamba.service.verify import Verdict

MAP_ID = re.compile(MAP_ID_PATTERN)
POSE_FORMAT = "x,y,z,qx,qy,qz,qw (7 finite numbers, metres and a non-zero quaternion)"


def check_map_id(map_id: str) -> str:
    if not MAP_ID.fullmatch(map_id):
        raise BadRequest(
            f"map id {map_id!r} is not allowed; allowed: {MAP_ID_PATTERN} "
            "(lower-case letters, digits, '_' and '-', at most 64 characters)",
            pattern=MAP_ID_PATTERN,
        )
    return map_id


@dataclass(frozen=True)
class NewKeyframe:
    """A keyframe as it is written: checked, content-hashed, its descriptor a unit vector."""

    keyframe_id: str
    robot_id: str
    session_id: str
    timestamp: float
    pose: list[float] | None
    descriptor: np.ndarray  # (D,) float32
    yaw: np.ndarray | None  # (C, W) float32
    content_hash: str
    geometry: bytes | None = None  # overlapmamba.core.geometry blob
    sensor: str | None = None  # the sensor of the scan it came from (None: not said)
    # hashes of this same content as an earlier release hashed it: a row stored then and
    # sent again is the same keyframe, not a conflict
    same_as: tuple[str, ...] = ()


@dataclass(frozen=True)
class Keyframe:
    """A keyframe as a backend holds it (``id`` and ``seq``: the FAISS backend's row id and
    write sequence; 0 in Qdrant). ``descriptor``: the stored descriptor, on a search's
    matches (a second stage may score by part of it: :mod:`overlapmamba.service.ranking`);
    None elsewhere."""

    id: int
    keyframe_id: str
    robot_id: str
    session_id: str
    timestamp: float
    pose: list[float] | None
    content_hash: str
    seq: int
    created_at: float
    sensor: str | None = None  # the scan's sensor; None: not recorded (a descriptor, or older)
    descriptor: np.ndarray | None = field(default=None, compare=False, repr=False)

    def public(self) -> dict[str, Any]:
        return {
            "keyframe_id": self.keyframe_id,
            "robot_id": self.robot_id,
            "session_id": self.session_id,
            "timestamp": self.timestamp,
            "pose": self.pose,
            "sensor": self.sensor,
        }


@dataclass(frozen=True)
class Filters:
    """What a query leaves out (sessions, robots, its own recent past, a time window) and the
    largest descriptor distance it accepts."""

    exclude_session: str | None = None
    exclude_robot: str | None = None
    exclude_recent_s: float | None = None
    session_id: str | None = None  # the querying session, for exclude_recent_s
    robot_id: str | None = None  # its robot (a session belongs to one): None, any robot's
    timestamp: float | None = None  # the query's time, for exclude_recent_s
    time_from: float | None = None
    time_to: float | None = None
    max_match_distance: float | None = None

    def __post_init__(self) -> None:
        if self.exclude_recent_s is not None and (
            self.session_id is None or self.timestamp is None
        ):
            raise BadRequest(
                "exclude_recent_s needs the query's session_id and timestamp",
                code="missing_parameter",
            )
        start, end = self.time_from, self.time_to
        if start is not None and end is not None and start > end:
            raise BadRequest(
                f"time_from={start:g} is after time_to={end:g}: the window holds no time; "
                "allowed: time_from ≤ time_to",
                code="bad_request",
            )

    @property
    def restricts_rows(self) -> bool:
        return any(
            v is not None
            for v in (
                self.exclude_session,
                self.exclude_robot,
                self.exclude_recent_s,
                self.time_from,
                self.time_to,
            )
        )


@dataclass(frozen=True)
class Match:
    keyframe: Keyframe
    similarity: float
    distance: float
    yaw_deg: float | None
    yaw_confidence: float | None
    # None: not verified (not asked, or beyond the first verify.candidates)
    verification: Verdict | None = None
    score: float | None = (
        None  # the re-ranking score (overlapmamba.service.ranking); None: not re-ranked
    )

    @property
    def relative_pose(self) -> np.ndarray | None:
        return None if self.verification is None else self.verification.relative_pose

    def public(self) -> dict[str, Any]:
        pose = self.relative_pose
        return {
            **self.keyframe.public(),
            "distance": self.distance,
            "similarity": self.similarity,
            "yaw_deg": self.yaw_deg,
            "yaw_confidence": self.yaw_confidence,
            "score": self.score,
            "relative_pose": None if pose is None else [float(x) for x in pose.reshape(-1)],
            "verification": None if self.verification is None else self.verification.public(),
        }


@dataclass(frozen=True)
class InsertResult:
    keyframe: Keyframe
    created: bool


def content_hash(kind: str, payload: bytes, meta: dict[str, Any]) -> str:
    h = hashlib.sha256(kind.encode())
    h.update(payload)
    h.update(json.dumps(meta, sort_keys=True).encode())
    return h.hexdigest()


YAW_LIMIT = float(np.finfo(np.float16).max)  # yaw features are stored as float16
UNIT_TOLERANCE = 1e-3  # float32 descriptors from the encoder are unit to ~1e-7


def check_rows(rows: list[NewKeyframe], dim: int) -> list[str]:
    """Shapes right, unit norm, and no keyframe id twice with different content → the distinct
    ids. Descriptors arrive normalised (the encoder's graph ends in an L2 normalisation; a
    client's descriptor is normalised once, by ``check_descriptor``): a backend stores
    and compares them as they are, and refuses one that is not a unit vector."""
    for r in rows:
        if r.descriptor.shape != (dim,):
            raise BadRequest(f"descriptor has shape {r.descriptor.shape}; need ({dim},)")
        norm = float(np.linalg.norm(r.descriptor))
        if not abs(norm - 1.0) <= UNIT_TOLERANCE:
            raise BadRequest(
                f"descriptor of keyframe {r.keyframe_id!r} has norm {norm:.6g}; allowed: a unit "
                f"vector (norm within {UNIT_TOLERANCE} of 1)"
            )
    seen: dict[str, str] = {}
    for r in rows:
        if seen.setdefault(r.keyframe_id, r.content_hash) != r.content_hash:
            raise Conflict(
                f"keyframe {r.keyframe_id!r} appears twice in the request with different content",
                code="keyframe_conflict",
                keyframe_id=r.keyframe_id,
            )
    return list(seen)


def parse_pose(text: str | None) -> list[float] | None:
    if text is None or text == "":
        return None
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    return check_pose(values, text)


def check_pose(values: list[float], text: object = None) -> list[float]:
    """7 finite numbers with a non-zero quaternion → the pose with a unit quaternion."""
    shown = values if text is None else text
    if len(values) != 7 or not all(math.isfinite(v) for v in values):
        raise BadRequest(f"pose {shown!r} is not valid; allowed: {POSE_FORMAT}", code="bad_pose")
    q = np.array(values[3:], dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if not 1e-6 < norm < 1e6:
        raise BadRequest(
            f"pose {shown!r} has a quaternion of norm {norm:.3g}; allowed: {POSE_FORMAT}",
            code="bad_pose",
        )
    return [float(v) for v in values[:3]] + [float(v) for v in q / norm]


def check_descriptor(values: Sequence[float] | np.ndarray, dim: int) -> np.ndarray:
    d = np.asarray(values, dtype=np.float64)
    if d.shape != (dim,):
        raise Unprocessable(
            f"descriptor has {d.size} values; allowed: exactly {dim}",
            code="bad_descriptor",
            dim=dim,
        )
    if not np.isfinite(d).all():
        raise Unprocessable("descriptor has NaN or infinite values", code="bad_descriptor")
    norm = float(np.linalg.norm(d))
    if not 1e-6 < norm < 1e6:
        raise Unprocessable(
            f"descriptor has norm {norm:.3g}; allowed: a non-zero vector (norm within "
            "1e-6 to 1e6), which is taken to unit length",
            code="bad_descriptor",
        )
    return (d / norm).astype(np.float32)


class DescriptorKeyframe(Protocol):
    """A keyframe sent as a precomputed descriptor (the batch route's items have these)."""

    keyframe_id: str
    robot_id: str
    session_id: str
    timestamp: float
    pose: list[float] | None
    descriptor: list[float]
    yaw_features: list[list[float]] | None
    sensor: str | None


def _batch_pose(pose: list[float] | None, i: int) -> list[float] | None:
    """A batch row's pose, checked; a bad one is named by its row (``keyframes[i]``)."""
    if not pose:
        return None
    try:
        return check_pose(pose)
    except BadRequest as err:
        err.message = f"keyframes[{i}]: {err.message}"
        err.detail = {**err.detail, "index": i}
        raise


def descriptor_keyframe(
    k: DescriptorKeyframe, i: int, dim: int, yaw_shape: tuple[int, int]
) -> NewKeyframe:
    """The ``i``-th keyframe of a batch, checked (descriptor of ``dim`` values, normalised;
    yaw features of ``yaw_shape``, finite; pose) and content-hashed → a row to insert."""
    try:
        desc = check_descriptor(k.descriptor, dim)
    except Unprocessable as err:
        err.message = f"keyframes[{i}]: {err.message}"
        raise
    yaw = None
    if k.yaw_features is not None:
        try:
            yaw = np.asarray(k.yaw_features, dtype=np.float32)
        except ValueError:  # ragged rows
            yaw = np.zeros(0, np.float32)
        # the store keeps them as float16: a value past its range (±65504) would come back
        # infinite and make every re-ranked score with this keyframe NaN (no closure, ever)
        with np.errstate(over="ignore"):
            stored = yaw.astype(np.float16)
        if yaw.shape != yaw_shape or not np.isfinite(stored).all():
            raise Unprocessable(
                f"keyframes[{i}].yaw_features has shape {yaw.shape}; allowed: {yaw_shape}, "
                f"finite and within ±{YAW_LIMIT:g} (they are stored as float16)",
                code="bad_yaw_features",
            )
    pose = _batch_pose(k.pose, i)
    meta: dict[str, Any] = {
        "robot": k.robot_id,
        "session": k.session_id,
        "timestamp": k.timestamp,
        "pose": pose,  # as stored and returned, so that a row sent back as read is the same
    }
    if k.sensor is not None:  # a keyframe that names none keeps the hash it always had
        meta["sensor"] = k.sensor
    payload = desc.tobytes() + (b"" if yaw is None else yaw.astype(np.float16).tobytes())
    sent = content_hash("descriptor", payload, {**meta, "pose": k.pose})  # before 2026-12-04
    return NewKeyframe(
        keyframe_id=k.keyframe_id,
        robot_id=k.robot_id,
        session_id=k.session_id,
        timestamp=k.timestamp,
        pose=pose,
        descriptor=desc,
        yaw=yaw,
        content_hash=content_hash("descriptor", payload, meta),
        sensor=k.sensor,
        same_as=(sent,),
    )
