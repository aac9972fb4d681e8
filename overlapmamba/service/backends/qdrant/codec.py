"""How the ``qdrant`` backend lays out a keyframe: point ids, payloads and the Qdrant
filters that query filters become (the FAISS backend's masks, term by term)."""

from __future__ import annotations

import base64
import uuid
from typing import Any

import numpy as np
from qdrant_client import models

from overlapmamba.service.domain import Filters, Keyframe, NewKeyframe

NAMESPACE = uuid.UUID("6f0d1c2e-3a4b-5c6d-8e9f-0a1b2c3d4e5f")  # keyframe ids → point ids
MARK = "overlapmamba_map"  # collection metadata key: this collection is one of our maps
LEAN = models.PayloadSelectorExclude(exclude=["yaw", "geometry"])  # the keyframe only
NO_GEOMETRY = models.PayloadSelectorExclude(exclude=["geometry"])
FRESH_S = 5.0  # how long a replica trusts what it read about a map (others may delete it)
CHUNK = 128  # points per upsert: ≈5 MB of JSON, well below Qdrant's 32 MB request limit
INDEXES = {
    "robot_id": models.PayloadSchemaType.KEYWORD,
    "session_id": models.PayloadSchemaType.KEYWORD,
    "timestamp": models.PayloadSchemaType.FLOAT,  # range filters and order_by need it
}


def point_id(keyframe_id: str) -> str:
    return str(uuid.uuid5(NAMESPACE, keyframe_id))


def point_payload(r: NewKeyframe, created_at: float) -> dict[str, Any]:
    yaw = None if r.yaw is None else np.asarray(r.yaw, dtype=np.float16)
    return {
        "keyframe_id": r.keyframe_id,
        "robot_id": r.robot_id,
        "session_id": r.session_id,
        "timestamp": float(r.timestamp),
        "pose": r.pose,
        "content_hash": r.content_hash,
        "created_at": created_at,
        "yaw": None if yaw is None else base64.b64encode(yaw.tobytes()).decode(),
        "yaw_shape": None if yaw is None else list(yaw.shape),
        "geometry": None if r.geometry is None else base64.b64encode(r.geometry).decode(),
        "sensor": r.sensor,
    }


def keyframe_of(p: dict[str, Any], vector: Any = None) -> Keyframe:
    """The keyframe of a payload; with the point's ``vector`` (a search asked for it), its
    descriptor too."""
    # Qdrant has no row ids or sequence numbers: both are the FAISS backend's bookkeeping.
    return Keyframe(
        id=0,
        keyframe_id=p["keyframe_id"],
        robot_id=p["robot_id"],
        session_id=p["session_id"],
        timestamp=float(p["timestamp"]),
        pose=p.get("pose"),
        content_hash=p["content_hash"],
        seq=0,
        created_at=float(p.get("created_at") or 0.0),
        sensor=p.get("sensor"),
        descriptor=np.asarray(vector, np.float32) if isinstance(vector, list) else None,
    )


def yaw_of(p: dict[str, Any]) -> np.ndarray | None:
    if not p.get("yaw") or not p.get("yaw_shape"):
        return None
    raw = np.frombuffer(base64.b64decode(p["yaw"]), dtype=np.float16)
    return raw.reshape(p["yaw_shape"])


def filter_of(f: Filters) -> models.Filter | None:
    """The query's exclusions as a Qdrant filter (the FAISS backend's masks, term by term)."""
    if not f.restricts_rows:
        return None
    must: list[Any] = []
    must_not: list[Any] = []
    if f.exclude_session is not None:
        must_not.append(match_of("session_id", f.exclude_session))
    if f.exclude_robot is not None:
        must_not.append(match_of("robot_id", f.exclude_robot))
    if f.exclude_recent_s is not None:
        assert f.session_id is not None and f.timestamp is not None  # Filters checked it
        recent = models.Range(gt=f.timestamp - f.exclude_recent_s)
        own = [match_of("session_id", f.session_id)]
        if f.robot_id is not None:  # another robot's session of the same name is not own
            own.append(match_of("robot_id", f.robot_id))
        must_not.append(
            models.Filter(must=[*own, models.FieldCondition(key="timestamp", range=recent)])
        )
    if f.time_from is not None or f.time_to is not None:
        span = models.Range(gte=f.time_from, lte=f.time_to)
        must.append(models.FieldCondition(key="timestamp", range=span))
    return models.Filter(must=must or None, must_not=must_not or None)


def match_of(key: str, value: str) -> models.FieldCondition:
    return models.FieldCondition(key=key, match=models.MatchValue(value=value))


def geometry_of(p: dict[str, Any]) -> bytes:
    return base64.b64decode(p["geometry"])
