"""One map of the ``qdrant`` backend: a Qdrant collection, read and written through its
backend's client (which maps Qdrant's errors to the service's)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
from qdrant_client import QdrantClient, models

from overlapmamba.core.sensors.mount import Mount
from overlapmamba.core.yaw import Spectrum
from overlapmamba.service.backends.base import (
    build_matches,
    check_existing,
    insert_results,
    map_not_found,
)
from overlapmamba.service.backends.qdrant.codec import (
    CHUNK,
    LEAN,
    NO_GEOMETRY,
    filter_of,
    geometry_of,
    keyframe_of,
    match_of,
    point_id,
    point_payload,
    yaw_of,
)
from overlapmamba.service.backends.rows import Row, with_spectra
from overlapmamba.service.domain import (
    Filters,
    InsertResult,
    Keyframe,
    Match,
    NewKeyframe,
    check_rows,
)
from overlapmamba.service.errors import Conflict, NotFound

if TYPE_CHECKING:
    from overlapmamba.service.backends.qdrant.backend import QdrantBackend

log = logging.getLogger("overlapmamba.service")
T = TypeVar("T")
TIES = 1000  # keyframes of one robot at one time read to break the tie (one a batch, at most)


class QdrantMap:
    def __init__(self, backend: QdrantBackend, map_id: str, meta: dict[str, Any]) -> None:
        self.backend = backend
        self.map_id = map_id
        self.collection = backend.collection(map_id)
        self.model_id: str = str(meta["model_id"])
        self.dim = int(meta["dim"])
        self.kind: str = str(meta["index_kind"])
        self.keep_geometry = bool(meta.get("keep_geometry", True))
        self.sensor: str | None = meta.get("sensor")
        mount = meta.get("mount")  # collections made before mounts were declared: none
        self.mount: Mount | None = None if mount is None else Mount(**mount)
        self.created_at = float(meta.get("created_at") or 0.0)
        self.checked = time.monotonic()
        self._write = backend.write_lock(map_id)  # read-check-write atomic in this replica
        self._deletions = backend.deletions(map_id)  # as of this handle's opening

    @property
    def retired(self) -> bool:
        return self.backend.deletions(self.map_id) != self._deletions

    def _check_live(self) -> None:
        """Under ``_write``: the map this handle opened was not deleted since (by this
        replica); its writes would land in a map created again under the same id."""
        if self.retired:
            raise map_not_found(self.map_id)

    def _call(self, fn: Callable[[QdrantClient], T]) -> T:
        return self.backend.call(fn, self.map_id)

    # ---- writes -----------------------------------------------------------------------------

    def insert(self, rows: list[NewKeyframe]) -> list[InsertResult]:
        wanted = check_rows(rows, self.dim)
        with self._write:
            self._check_live()
            existing = self._get_many(wanted)
            new = check_existing(rows, existing)
            created: dict[str, Keyframe] = {}
            if new:
                now = time.time()
                for start in range(0, len(new), CHUNK):
                    self._upsert(new[start : start + CHUNK], now)
                # insert_only never overwrites: read back what is stored now. Another
                # replica's concurrent insert of the same id may have landed first.
                stored = self._get_many([r.keyframe_id for r in new])
                for r in new:
                    kf = stored.get(r.keyframe_id)
                    if kf is None:  # deleted by someone else in between: report ours
                        kf = keyframe_of(point_payload(r, now))
                    check_existing([r], {r.keyframe_id: kf})
                    created[r.keyframe_id] = kf
        return insert_results(rows, existing, created)

    def _upsert(self, rows: list[NewKeyframe], now: float) -> None:
        batch = models.Batch(
            ids=[point_id(r.keyframe_id) for r in rows],
            vectors=[np.asarray(r.descriptor, dtype=np.float32).tolist() for r in rows],
            payloads=[point_payload(r, now) for r in rows],
        )
        self._call(
            lambda c: c.upsert(
                self.collection,
                batch,
                wait=True,
                ordering=self.backend.ordering,
                update_mode=models.UpdateMode.INSERT_ONLY,
            )
        )

    def delete(self, keyframe_id: str) -> None:
        with self._write:
            self._check_live()
            if self.get(keyframe_id) is None:
                raise NotFound(
                    f"map {self.map_id!r} has no keyframe {keyframe_id!r}",
                    code="keyframe_not_found",
                )
            selector = models.PointIdsList(points=[point_id(keyframe_id)])
            self._call(
                lambda c: c.delete(
                    self.collection, selector, wait=True, ordering=self.backend.ordering
                )
            )

    def maintain(self) -> None:
        """Nothing to do here: Qdrant's optimizers index, vacuum and flush on their own."""

    def snapshot(self) -> dict[str, Any]:
        if self.backend.local:
            raise Conflict(
                "Qdrant's local mode has no snapshots (each write is already on disk); a "
                "Qdrant server takes them",
                code="not_supported",
            )
        # Not waited for: a large collection's snapshot outlasts the request timeout, and
        # a retried request would start another. Qdrant lists it when done.
        self._call(lambda c: c.create_snapshot(self.collection, wait=False))
        return {"backend": "qdrant", "name": None, "bytes": None, "started": True}

    # ---- reads ------------------------------------------------------------------------------

    @property
    def count(self) -> int:
        return int(self._call(lambda c: c.count(self.collection, exact=True)).count)

    def _get_many(self, keyframe_ids: list[str]) -> dict[str, Keyframe]:
        out: dict[str, Keyframe] = {}
        for start in range(0, len(keyframe_ids), 500):
            ids = [point_id(k) for k in keyframe_ids[start : start + 500]]
            for rec in self._retrieve(ids):
                kf = keyframe_of(rec.payload or {})
                out[kf.keyframe_id] = kf
        return out

    def _retrieve(self, ids: list[str]) -> list[models.Record]:
        return self._call(
            lambda c: c.retrieve(
                self.collection, ids, with_payload=LEAN, consistency=self.backend.consistency
            )
        )

    def get(self, keyframe_id: str) -> Keyframe | None:
        return self._get_many([keyframe_id]).get(keyframe_id)

    def geometry(self, keyframe_ids: list[str]) -> dict[str, bytes]:
        records = self._call(
            lambda c: c.retrieve(
                self.collection,
                [point_id(k) for k in keyframe_ids],
                with_payload=["keyframe_id", "geometry"],
                consistency=self.backend.consistency,
            )
        )
        out = {}
        for rec in records:
            p = rec.payload or {}
            if p.get("geometry"):
                out[str(p["keyframe_id"])] = geometry_of(p)
        return out

    def last_keyframe(self, robot_id: str, session_id: str) -> Keyframe | None:
        """The latest keyframe of the robot's session; of equal times, the one written last,
        then the greatest id (as the FAISS store's): Qdrant orders by the time alone."""
        own = [match_of("robot_id", robot_id), match_of("session_id", session_id)]

        def latest(limit: int, at: float | None = None) -> list[Keyframe]:
            must: list[Any] = [*own]
            if at is not None:
                must.append(
                    models.FieldCondition(key="timestamp", range=models.Range(gte=at, lte=at))
                )
            records, _ = self._call(
                lambda c: c.scroll(
                    self.collection,
                    scroll_filter=models.Filter(must=must),
                    limit=limit,
                    order_by=models.OrderBy(key="timestamp", direction=models.Direction.DESC),
                    with_payload=LEAN,
                    consistency=self.backend.consistency,
                )
            )
            return [keyframe_of(r.payload or {}) for r in records]

        top = latest(2)
        if len(top) == 2 and top[0].timestamp == top[1].timestamp:  # a tie: all of that time
            top = latest(TIES, top[0].timestamp)
        return max(top, key=lambda k: (k.timestamp, k.created_at, k.keyframe_id), default=None)

    def positions(self, limit: int) -> list[tuple[str, float, float]]:
        records, _ = self._call(
            lambda c: c.scroll(
                self.collection,
                # the limit counts keyframes with a pose: those without one are filtered first
                scroll_filter=models.Filter(
                    must_not=[models.IsEmptyCondition(is_empty=models.PayloadField(key="pose"))]
                ),
                limit=int(limit),
                order_by=models.OrderBy(key="timestamp", direction=models.Direction.DESC),
                with_payload=models.PayloadSelectorInclude(include=["robot_id", "pose"]),
                consistency=self.backend.consistency,
            )
        )
        out = []
        for r in records:
            payload = r.payload or {}
            pose = payload.get("pose")
            if pose:
                out.append((str(payload.get("robot_id", "")), float(pose[0]), float(pose[1])))
        return out

    def search(
        self,
        descriptor: np.ndarray,
        k: int,
        filters: Filters,
        yaw: np.ndarray | None = None,
        *,
        yaw_k: int | None = None,
        descriptors: bool = False,
    ) -> list[Match]:
        q = np.asarray(descriptor, dtype=np.float32).tolist()  # unit norm (see check_rows)
        cache = self.backend.row_cache  # with it the yaw features come in a second, smaller call
        params = None
        if not self.backend.local:  # local mode is exact and warns about any parameter
            exact = self.kind == "flat"
            params = models.SearchParams(exact=exact, hnsw_ef=None if exact else self.backend.ef)
        result = self._call(
            lambda c: c.query_points(
                self.collection,
                query=q,
                limit=k,
                query_filter=filter_of(filters),
                search_params=params,
                with_payload=NO_GEOMETRY if yaw is not None and not cache.max_bytes else LEAN,
                with_vectors=descriptors,  # only when asked: hundreds of floats a point
                consistency=self.backend.consistency,
            )
        )
        found: list[tuple[float, Keyframe, np.ndarray | Spectrum | None]]
        if yaw is None or not cache.max_bytes:
            found = [
                (float(p.score), keyframe_of(p.payload or {}, p.vector), yaw_of(p.payload or {}))
                for p in result.points
            ]
        else:
            found = self._with_spectra(result.points, yaw_k)
        return build_matches(found, yaw, filters.max_match_distance, yaw_k)

    def _with_spectra(
        self, points: list[models.ScoredPoint], yaw_k: int | None
    ) -> list[tuple[float, Keyframe, np.ndarray | Spectrum | None]]:
        """Hits found without their yaw features: those of the first ``yaw_k`` whose spectra
        the row cache holds (by collection, keyframe id and content hash: the same content has
        the same features) take them from there; the others' features are fetched in one call,
        transformed and kept. A point deleted or written again between the two calls is
        answered without yaw this once and not kept."""
        cache, token = self.backend.row_cache, self.backend.row_token
        kfs = [keyframe_of(p.payload or {}, p.vector) for p in points]
        keys = [(self.collection, kf.keyframe_id, kf.content_hash) for kf in kfs]
        head = range(len(points) if yaw_k is None else min(yaw_k, len(points)))
        held = cache.get(token, [keys[j] for j in head])
        missing = [j for j in head if keys[j] not in held]
        made: dict[tuple[str, str, str], Row] = {}
        if missing:
            records = self._call(
                lambda c: c.retrieve(
                    self.collection,
                    [points[j].id for j in missing],
                    with_payload=["content_hash", "yaw", "yaw_shape"],
                    consistency=self.backend.consistency,
                )
            )
            got = {str(r.id): r.payload or {} for r in records}
            made = with_spectra(
                {
                    keys[j]: (kfs[j], yaw_of(payload))
                    for j in missing
                    if (payload := got.get(str(points[j].id), {})).get("content_hash")
                    == kfs[j].content_hash
                }
            )
            cache.put(token, made)
        rows: dict[tuple[str, str, str], Row] = {**held, **made}
        return [
            (float(p.score), kf, rows[key][1] if key in rows else None)
            for p, kf, key in zip(points, kfs, keys, strict=True)
        ]

    def info(self) -> dict[str, Any]:
        n = self.count
        return {
            "map_id": self.map_id,
            "model_id": self.model_id,
            "backend": "qdrant",
            "index": {
                "kind": self.kind,
                "active": "exact" if self.kind == "flat" or self.backend.local else "hnsw",
                "nlist": 0,
                "vectors": n,
                "collection": self.collection,
            },
            "keyframes": n,
            "keep_geometry": self.keep_geometry,
            "sensor": self.sensor,
            "mount": None if self.mount is None else self.mount.key(),
            "seq": None,
            "snapshot_seq": None,
            "created_at": self.created_at,
        }
