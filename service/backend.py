"""What a map is to the rest of the service, whichever engine holds its keyframes.

Two implementations of one interface:

    faiss   service.maps     SQLite store + FAISS index in the data folder; embedded, the
                             default. The process owns its maps (one per data folder).
    qdrant  service.qdrant   one Qdrant collection per map; durability, replication and
                             sharding are Qdrant's. The process keeps no state, so any number
                             of replicas can serve one Qdrant cluster.

Routes and :mod:`service.core` see only :class:`PlaceMap` and :class:`MapBackend`; the query
semantics (filters, distances, yaw, idempotent inserts) are defined here once and checked
against both by ``tests/test_backends.py``.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

import numpy as np

from lidar_core.yaw import estimate_yaw
from service.errors import BadRequest, Conflict, NotFound
from service.settings import Settings
from service.store import Keyframe, NewKeyframe
from service.verify import Verdict

T = TypeVar("T")


@dataclass(frozen=True)
class Filters:
    exclude_session: str | None = None
    exclude_robot: str | None = None
    exclude_recent_s: float | None = None
    session_id: str | None = None  # the querying session, for exclude_recent_s
    timestamp: float | None = None  # the query's time, for exclude_recent_s
    time_from: float | None = None
    time_to: float | None = None
    max_distance: float | None = None

    def __post_init__(self) -> None:
        if self.exclude_recent_s is not None and (
            self.session_id is None or self.timestamp is None
        ):
            raise BadRequest(
                "exclude_recent_s needs the query's session_id and timestamp",
                code="missing_parameter",
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
    verification: Verdict | None = None  # None: not verified (not asked, or beyond verify.k)

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


UNIT_TOLERANCE = 1e-3  # float32 descriptors from the encoder are unit to ~1e-7


def check_rows(rows: list[NewKeyframe], dim: int) -> list[str]:
    """Shapes right, unit norm, and no keyframe id twice with different content → the distinct
    ids. Descriptors arrive normalised (the encoder's graph ends in an L2 normalisation; a
    client's descriptor is normalised once, by ``core.check_descriptor``): a backend stores
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


def check_same_geometry(m: PlaceMap, keep_geometry: bool | None) -> None:
    """Creating an existing map again: a geometry setting, when given, must match (409)."""
    if keep_geometry is not None and m.keep_geometry != keep_geometry:
        raise Conflict(
            f"map {m.map_id!r} exists with keep_geometry={str(m.keep_geometry).lower()}; "
            "the setting is fixed when a map is created",
            code="map_conflict",
            keep_geometry=m.keep_geometry,
        )


def check_existing(rows: list[NewKeyframe], existing: dict[str, Keyframe]) -> list[NewKeyframe]:
    """Keyframe ids are write-once: a known id with other content refuses the whole request
    (409). → the rows still to write, each id once."""
    for r in rows:
        old = existing.get(r.keyframe_id)
        if old is not None and old.content_hash != r.content_hash:
            raise Conflict(
                f"keyframe {r.keyframe_id!r} already exists with different content; "
                "keyframe ids are write-once (DELETE it first to replace it)",
                code="keyframe_conflict",
                keyframe_id=r.keyframe_id,
            )
    new: list[NewKeyframe] = []
    queued: set[str] = set()
    for r in rows:
        if r.keyframe_id not in existing and r.keyframe_id not in queued:
            queued.add(r.keyframe_id)
            new.append(r)
    return new


def insert_results(
    rows: list[NewKeyframe], existing: dict[str, Keyframe], created: dict[str, Keyframe]
) -> list[InsertResult]:
    """One result per requested row, in order; a repeated id in one request is created once."""
    existing, created = dict(existing), dict(created)
    out = []
    for r in rows:
        if r.keyframe_id in existing:
            out.append(InsertResult(existing[r.keyframe_id], created=False))
        else:
            out.append(InsertResult(created.pop(r.keyframe_id), created=True))
            existing[r.keyframe_id] = out[-1].keyframe
    return out


def build_matches(
    found: Iterable[tuple[float, Keyframe, np.ndarray | None]],
    yaw: np.ndarray | None,
    max_distance: float | None,
) -> list[Match]:
    """Hits (L2 distance, keyframe, its yaw features (C, W) or None), nearest first → matches,
    with the relative yaw for those whose features the query's can be correlated with."""
    hits = [h for h in found if max_distance is None or h[0] <= max_distance]
    yaws: dict[int, tuple[float, float]] = {}
    with_yaw = [j for j, h in enumerate(hits) if h[2] is not None]
    if yaw is not None and with_yaw:
        refs = np.stack([hits[j][2] for j in with_yaw])  # type: ignore[misc]  # (K, C, W)
        if refs.shape[1:] == yaw.shape:
            deg, conf = estimate_yaw(yaw, refs)
            yaws = {j: (float(d), float(c)) for j, d, c in zip(with_yaw, deg, conf, strict=True)}
    out = []
    for j, (dist, kf, _) in enumerate(hits):
        y = yaws.get(j)
        out.append(
            Match(
                keyframe=kf,
                similarity=1.0 - dist * dist / 2.0,
                distance=dist,
                yaw_deg=None if y is None else y[0],
                yaw_confidence=None if y is None else y[1],
            )
        )
    return out


class PlaceMap(Protocol):
    """One map of keyframes. Every method may block (disk or network): call it from a
    worker thread. A map deleted meanwhile answers :class:`service.errors.NotFound`."""

    map_id: str
    model_id: str
    dim: int
    kind: str  # the index kind asked for: auto, flat (exact) or ivf (approximate)
    keep_geometry: bool  # keyframes inserted from scans keep their compact geometry

    @property
    def count(self) -> int: ...  # live keyframes the index holds

    def insert(self, rows: list[NewKeyframe]) -> list[InsertResult]: ...

    def delete(self, keyframe_id: str) -> None: ...

    def get(self, keyframe_id: str) -> Keyframe | None: ...

    def geometry(self, keyframe_ids: list[str]) -> dict[str, bytes]: ...  # those that have one

    def last_keyframe(self, robot_id: str) -> Keyframe | None: ...

    # (robot_id, x, y) of keyframes that have a pose: the latest ``limit`` by timestamp
    def positions(self, limit: int) -> list[tuple[str, float, float]]: ...

    def search(
        self, descriptor: np.ndarray, k: int, filters: Filters, yaw: np.ndarray | None = None
    ) -> list[Match]: ...

    def info(self) -> dict[str, Any]: ...

    def snapshot(self) -> dict[str, Any]: ...

    def maintain(self) -> None: ...  # after writes: background upkeep when due


class MapBackend(Protocol):
    """Every map of one engine."""

    name: str
    failed: dict[str, str]  # map id -> why it cannot be served

    def load_all(self) -> None: ...

    def get(self, map_id: str) -> PlaceMap: ...

    def create(
        self, map_id: str, kind: str | None, keep_geometry: bool | None = None
    ) -> tuple[PlaceMap, bool]: ...

    def delete(self, map_id: str) -> None: ...

    def snapshot_list(self) -> Sequence[PlaceMap]: ...

    def describe(self) -> dict[str, Any]: ...  # where the maps live, for logs and readyz

    def close(self, *, snapshot: bool = True) -> None: ...


def each_map(backend: MapBackend, fn: Callable[[PlaceMap], T]) -> dict[str, T]:
    """``fn`` of every map, by id, skipping maps deleted between the listing and the call."""
    out: dict[str, T] = {}
    for m in backend.snapshot_list():
        try:
            out[m.map_id] = fn(m)
        except NotFound:
            continue
    return out


def open_backend(settings: Settings, *, model_id: str, dim: int) -> MapBackend:
    """The configured engine's maps (not yet loaded: call ``load_all``)."""
    if settings.index.backend == "qdrant":
        from service.qdrant import QdrantBackend

        return QdrantBackend(settings.qdrant, settings.index, model_id=model_id, dim=dim)
    from service.maps import MapRegistry

    return MapRegistry(settings.data_dir, settings.index, model_id=model_id, dim=dim)
