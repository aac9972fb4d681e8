"""What a map is to the rest of the service, whichever engine holds its keyframes: the
:class:`PlaceMap` and :class:`MapBackend` protocols, and the rules every backend applies
the same way (write-once ids, one result per requested row, matches with their yaw).

Routes and :mod:`overlapmamba.service.places` see only these protocols; the query semantics
(filters, distances, yaw, idempotent inserts) are defined here and in
:mod:`overlapmamba.service.domain` once and checked against both engines by
``tests/test_backends.py``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Any, Protocol, TypeVar

import numpy as np

from overlapmamba.core.sensors.mount import Mount
from overlapmamba.core.yaw import Spectrum, as_spectra, estimate_yaw
from overlapmamba.service.domain import Filters, InsertResult, Keyframe, Match, NewKeyframe
from overlapmamba.service.errors import Conflict, NotFound

T = TypeVar("T")


def map_not_found(map_id: str) -> NotFound:
    """The one answer for a map that does not exist (404, ``map_not_found``)."""
    return NotFound(
        f"map {map_id!r} does not exist; create it with PUT /v1/maps/{map_id}",
        code="map_not_found",
        map_id=map_id,
    )


def check_same_settings(
    m: PlaceMap,
    keep_geometry: bool | None,
    sensor: str | None,
    mount: Mount | None = None,
    kind: str | None = None,
) -> None:
    """Creating an existing map again: an index kind, geometry, sensor or mount setting, when
    given, must match (409)."""
    if kind is not None and m.kind != kind:
        raise Conflict(
            f"map {m.map_id!r} exists with index {m.kind!r}, not {kind!r}",
            code="map_conflict",
            index=m.kind,
        )
    if keep_geometry is not None and m.keep_geometry != keep_geometry:
        raise Conflict(
            f"map {m.map_id!r} exists with keep_geometry={str(m.keep_geometry).lower()}; "
            "the setting is fixed when a map is created",
            code="map_conflict",
            keep_geometry=m.keep_geometry,
        )
    if sensor is not None and m.sensor != sensor:
        raise Conflict(
            f"map {m.map_id!r} exists with sensor {m.sensor!r}, not {sensor!r}; a map's "
            "sensor is fixed when it is created (scans of other sensors name theirs)",
            code="map_conflict",
            sensor=m.sensor,
        )
    if mount is not None and m.mount != mount:
        held = "none" if m.mount is None else m.mount.text()
        raise Conflict(
            f"map {m.map_id!r} exists with mount {held}, not {mount.text()}; a map's "
            "mount is fixed when it is created (scans from elsewhere name theirs)",
            code="map_conflict",
            mount=None if m.mount is None else m.mount.key(),
        )


def check_existing(rows: list[NewKeyframe], existing: dict[str, Keyframe]) -> list[NewKeyframe]:
    """Keyframe ids are write-once: a known id with other content refuses the whole request
    (409). → the rows still to write, each id once."""
    for r in rows:
        old = existing.get(r.keyframe_id)
        if old is not None and old.content_hash not in (r.content_hash, *r.same_as):
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
    found: Iterable[tuple[float, Keyframe, np.ndarray | Spectrum | None]],
    yaw: np.ndarray | None,
    max_match_distance: float | None,
    yaw_k: int | None = None,
) -> list[Match]:
    """Hits (L2 distance, keyframe, its yaw features (C, W) — or their :class:`Spectrum`, as
    a row cache keeps them — or None), nearest first → matches, with the relative yaw for
    those of the first ``yaw_k`` (all when None) whose features the query's can be
    correlated with. (A caller that fetches a runner-up only for its distance saves its
    correlation: a sixth of the search stage at k = 5.)"""
    hits = [h for h in found if max_match_distance is None or h[0] <= max_match_distance]
    yaws: dict[int, tuple[float, float]] = {}
    with_yaw = [j for j, h in enumerate(hits[:yaw_k]) if h[2] is not None]
    if yaw is not None and with_yaw:
        refs = as_spectra([r for j in with_yaw if (r := hits[j][2]) is not None])
        C, W = yaw.shape
        if all(r.width == W and r.bins.shape[0] == C for r in refs):
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
    worker thread. A map deleted meanwhile answers :class:`overlapmamba.service.errors.NotFound`."""

    map_id: str
    model_id: str
    dim: int
    kind: str  # the index kind asked for: auto, flat (exact) or ivf (approximate)
    keep_geometry: bool  # keyframes inserted from scans keep their compact geometry
    sensor: str | None  # the sensor of scans that name none; None: the model's own
    mount: Mount | None  # where the sensor of scans that name none sits; None: not said

    @property
    def count(self) -> int: ...  # live keyframes the index holds

    # deleted (or closed) since this handle was opened, in this process: a request that
    # ran on it records no statistics (they would bring back what its deletion forgot)
    @property
    def retired(self) -> bool: ...

    def insert(self, rows: list[NewKeyframe]) -> list[InsertResult]: ...

    def delete(self, keyframe_id: str) -> None: ...

    def get(self, keyframe_id: str) -> Keyframe | None: ...

    def geometry(self, keyframe_ids: list[str]) -> dict[str, bytes]: ...  # those that have one

    # the latest keyframe of the robot's session (its clock and odometry frame)
    def last_keyframe(self, robot_id: str, session_id: str) -> Keyframe | None: ...

    # (robot_id, x, y) of keyframes that have a pose: the latest ``limit`` by timestamp
    def positions(self, limit: int) -> list[tuple[str, float, float]]: ...

    def search(
        self,
        descriptor: np.ndarray,
        k: int,
        filters: Filters,
        yaw: np.ndarray | None = None,
        *,
        yaw_k: int | None = None,
        descriptors: bool = False,
    ) -> list[Match]: ...  # relative yaw for the first yaw_k matches (all when None); with

    # descriptors, each match's keyframe carries its stored descriptor (a second stage may
    # score by part of it: overlapmamba.service.ranking)

    def info(self) -> dict[str, Any]: ...

    def snapshot(self) -> dict[str, Any]: ...

    def maintain(self) -> None: ...  # after writes: background upkeep when due


class MapBackend(Protocol):
    """Every map of one engine."""

    name: str
    failed: dict[str, str]  # map id -> why it cannot be served

    def load_all(self) -> None: ...

    def get(self, map_id: str) -> PlaceMap: ...

    # The map, or get's error, when the answer needs no disk or network (an event loop may
    # call it); None when only get can tell.
    def get_nowait(self, map_id: str) -> PlaceMap | None: ...

    def create(
        self,
        map_id: str,
        kind: str | None,
        keep_geometry: bool | None = None,
        sensor: str | None = None,
        mount: Mount | None = None,
    ) -> tuple[PlaceMap, bool]: ...

    def delete(self, map_id: str) -> None: ...

    def snapshot_list(self) -> Sequence[PlaceMap]: ...

    def describe(self) -> dict[str, Any]: ...  # where the maps live, for logs and readyz
    def row_cache_info(self) -> dict[str, int] | None: ...  # its row cache (rows.py), if any

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
