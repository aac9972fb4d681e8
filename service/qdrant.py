"""The ``qdrant`` backend: each map is a Qdrant collection; the service keeps no state.

    collection   <qdrant.collection_prefix><map_id>, Euclidean distance over unit
                 descriptors (the same L2 the FAISS backend answers with); its metadata
                 holds the map's model id, dimension, index kind, whether it keeps
                 geometry, and its creation time
    point id     uuid5(keyframe_id): a retried insert lands on the same point
    payload      keyframe_id, robot_id, session_id (keyword indexes), timestamp (float
                 index), pose, content_hash, created_at, the yaw features (float16,
                 base64; not indexed) and the compact geometry (lidar_core.geometry,
                 base64; read only for the candidates a query verifies)

Writes are acknowledged after Qdrant has applied them (``wait=True``) with strong ordering,
and reads ask a majority of a shard's replicas, so a replica that answers next sees them.
Inserts are ``insert_only``: keyframe ids stay write-once even when two replicas race —
whichever lands second finds the first's content on re-reading and answers 409 if it
differs. A batch is checked whole before anything is written, but it is written in chunks:
unlike the FAISS backend's single transaction, such a race can refuse a batch after some of
its points landed (a retry of the same batch then completes it). Durability (WAL,
snapshots, replication) is Qdrant's; ``POST /v1/maps/{id}/snapshot`` asks Qdrant for a
collection snapshot.

Map kinds: ``flat`` searches exactly (and builds no HNSW graph); ``auto`` and ``ivf`` use
Qdrant's HNSW with ``qdrant.hnsw_ef`` candidates, filtered through the payload indexes.

``qdrant.path`` runs qdrant-client's embedded local mode instead of a server — the tests use
it. It searches exactly, keeps no payload indexes and has no snapshots; calls into it are
serialised, since it is not made for threads.
"""

from __future__ import annotations

import base64
import contextlib
import logging
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import numpy as np
from qdrant_client import QdrantClient, models
from qdrant_client.common.client_exceptions import ResourceExhaustedResponse
from qdrant_client.http.exceptions import ResponseHandlingException, UnexpectedResponse

from service.backend import (
    Filters,
    InsertResult,
    Match,
    build_matches,
    check_existing,
    check_rows,
    check_same_geometry,
    insert_results,
)
from service.errors import BadRequest, Conflict, NotFound, Overloaded, ServiceError, Unavailable
from service.schemas import check_map_id
from service.settings import IndexSettings, QdrantSettings
from service.store import Keyframe, NewKeyframe

log = logging.getLogger("overlapmamba.service")
T = TypeVar("T")

_NAMESPACE = uuid.UUID("6f0d1c2e-3a4b-5c6d-8e9f-0a1b2c3d4e5f")  # keyframe ids → point ids
_MARK = "overlapmamba_map"  # collection metadata key: this collection is one of our maps
_LEAN = models.PayloadSelectorExclude(exclude=["yaw", "geometry"])  # the keyframe only
_NO_GEOMETRY = models.PayloadSelectorExclude(exclude=["geometry"])
_FRESH_S = 5.0  # how long a replica trusts what it read about a map (others may delete it)
_CHUNK = 128  # points per upsert: ≈5 MB of JSON, well below Qdrant's 32 MB request limit
_INDEXES = {
    "robot_id": models.PayloadSchemaType.KEYWORD,
    "session_id": models.PayloadSchemaType.KEYWORD,
    "timestamp": models.PayloadSchemaType.FLOAT,  # range filters and order_by need it
}


def point_id(keyframe_id: str) -> str:
    return str(uuid.uuid5(_NAMESPACE, keyframe_id))


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
    }


def _keyframe(p: dict[str, Any]) -> Keyframe:
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
    )


def _yaw(p: dict[str, Any]) -> np.ndarray | None:
    if not p.get("yaw") or not p.get("yaw_shape"):
        return None
    raw = np.frombuffer(base64.b64decode(p["yaw"]), dtype=np.float16)
    return raw.reshape(p["yaw_shape"])


def _filter(f: Filters) -> models.Filter | None:
    """The query's exclusions as a Qdrant filter (the FAISS backend's masks, term by term)."""
    if not f.restricts_rows:
        return None
    must: list[Any] = []
    must_not: list[Any] = []
    if f.exclude_session is not None:
        must_not.append(_match("session_id", f.exclude_session))
    if f.exclude_robot is not None:
        must_not.append(_match("robot_id", f.exclude_robot))
    if f.exclude_recent_s is not None:
        assert f.session_id is not None and f.timestamp is not None  # Filters checked it
        recent = models.Range(gt=f.timestamp - f.exclude_recent_s)
        must_not.append(
            models.Filter(
                must=[
                    _match("session_id", f.session_id),
                    models.FieldCondition(key="timestamp", range=recent),
                ]
            )
        )
    if f.time_from is not None or f.time_to is not None:
        span = models.Range(gte=f.time_from, lte=f.time_to)
        must.append(models.FieldCondition(key="timestamp", range=span))
    return models.Filter(must=must or None, must_not=must_not or None)


def _match(key: str, value: str) -> models.FieldCondition:
    return models.FieldCondition(key=key, match=models.MatchValue(value=value))


class QdrantMap:
    def __init__(self, backend: QdrantBackend, map_id: str, meta: dict[str, Any]) -> None:
        self.backend = backend
        self.map_id = map_id
        self.collection = backend.collection(map_id)
        self.model_id: str = str(meta["model_id"])
        self.dim = int(meta["dim"])
        self.kind: str = str(meta["index_kind"])
        self.keep_geometry = bool(meta.get("keep_geometry", True))
        self.created_at = float(meta.get("created_at") or 0.0)
        self.checked = time.monotonic()
        self._write = backend.write_lock(map_id)  # read-check-write atomic in this replica

    def _call(self, fn: Callable[[QdrantClient], T]) -> T:
        return self.backend.call(fn, self.map_id)

    # ---- writes -----------------------------------------------------------------------------

    def insert(self, rows: list[NewKeyframe]) -> list[InsertResult]:
        wanted = check_rows(rows, self.dim)
        with self._write:
            existing = self._get_many(wanted)
            new = check_existing(rows, existing)
            created: dict[str, Keyframe] = {}
            if new:
                now = time.time()
                for start in range(0, len(new), _CHUNK):
                    self._upsert(new[start : start + _CHUNK], now)
                # insert_only never overwrites: read back what is stored now. Another
                # replica's concurrent insert of the same id may have landed first.
                stored = self._get_many([r.keyframe_id for r in new])
                for r in new:
                    kf = stored.get(r.keyframe_id)
                    if kf is None:  # deleted by someone else in between: report ours
                        kf = _keyframe(point_payload(r, now))
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
                kf = _keyframe(rec.payload or {})
                out[kf.keyframe_id] = kf
        return out

    def _retrieve(self, ids: list[str]) -> list[models.Record]:
        return self._call(
            lambda c: c.retrieve(
                self.collection, ids, with_payload=_LEAN, consistency=self.backend.consistency
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
                out[str(p["keyframe_id"])] = base64.b64decode(p["geometry"])
        return out

    def last_keyframe(self, robot_id: str) -> Keyframe | None:
        records, _ = self._call(
            lambda c: c.scroll(
                self.collection,
                scroll_filter=models.Filter(must=[_match("robot_id", robot_id)]),
                limit=1,
                order_by=models.OrderBy(key="timestamp", direction=models.Direction.DESC),
                with_payload=_LEAN,
                consistency=self.backend.consistency,
            )
        )
        return _keyframe(records[0].payload or {}) if records else None

    def positions(self, limit: int) -> list[tuple[str, float, float]]:
        records, _ = self._call(
            lambda c: c.scroll(
                self.collection,
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
        self, descriptor: np.ndarray, k: int, filters: Filters, yaw: np.ndarray | None = None
    ) -> list[Match]:
        q = np.asarray(descriptor, dtype=np.float32).tolist()  # unit norm (see check_rows)
        params = None
        if not self.backend.local:  # local mode is exact and warns about any parameter
            exact = self.kind == "flat"
            params = models.SearchParams(exact=exact, hnsw_ef=None if exact else self.backend.ef)
        result = self._call(
            lambda c: c.query_points(
                self.collection,
                query=q,
                limit=k,
                query_filter=_filter(filters),
                search_params=params,
                with_payload=_NO_GEOMETRY if yaw is not None else _LEAN,
                consistency=self.backend.consistency,
            )
        )
        found = [
            (float(p.score), _keyframe(p.payload or {}), _yaw(p.payload or {}))
            for p in result.points
        ]
        return build_matches(found, yaw, filters.max_distance)

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
            "seq": None,
            "snapshot_seq": None,
            "created_at": self.created_at,
        }


class QdrantBackend:
    """Maps as collections of one Qdrant deployment. Nothing is cached for long: another
    replica may create or delete maps at any time."""

    name = "qdrant"

    def __init__(
        self,
        qs: QdrantSettings,
        index: IndexSettings,
        *,
        model_id: str,
        dim: int,
        client: QdrantClient | None = None,
    ) -> None:
        """``client``: an already connected one to share (another process's, in tests)."""
        self.settings = qs
        self.index = index
        self.model_id = model_id
        self.dim = dim
        self.failed: dict[str, str] = {}  # a stateless replica has no maps of its own to fail
        self.local = qs.path is not None
        self.ef = qs.hnsw_ef
        self.ordering = None if self.local else models.WriteOrdering.STRONG
        self.consistency = None if self.local else models.ReadConsistencyType.MAJORITY
        self.where = str(qs.path) if self.local else str(qs.url)
        if client is not None:
            self.client = client
        elif self.local:
            assert qs.path is not None
            qs.path.mkdir(parents=True, exist_ok=True)
            self.client = QdrantClient(path=str(qs.path))
        else:
            self.client = QdrantClient(
                url=qs.url,
                api_key=qs.api_key.get_secret_value() if qs.api_key else None,
                timeout=max(1, round(qs.timeout_s)),
                check_compatibility=False,  # no network call before the service is up
            )
        self._serial = threading.RLock() if self.local else None
        self._maps: dict[str, QdrantMap] = {}
        self._create = threading.Lock()
        self._locks: dict[str, threading.Lock] = {}
        self._locks_lock = threading.Lock()  # not _create: create() holds that while opening

    def write_lock(self, map_id: str) -> threading.Lock:
        with self._locks_lock:
            return self._locks.setdefault(map_id, threading.Lock())

    def collection(self, map_id: str) -> str:
        return f"{self.settings.collection_prefix}{map_id}"

    @contextlib.contextmanager
    def _guard(self, map_id: str | None) -> Iterator[None]:
        """Qdrant's errors → the service's. A missing collection is a missing map (404).
        Qdrant overloaded (429) or failing (5xx), unreachable, or refusing our key is 503, so
        clients retry. Qdrant refusing a request as malformed (400, 422) is a bug of ours:
        500, not a retry loop."""
        lock = self._serial if self._serial is not None else contextlib.nullcontext()
        try:
            with lock:
                yield
        except ServiceError:
            raise
        except ResourceExhaustedResponse as err:
            raise Overloaded(
                f"Qdrant at {self.where} is overloaded: {err}", retry_after_s=err.retry_after_s
            ) from err
        except UnexpectedResponse as err:
            status = err.status_code or 0
            if status == 404 and map_id is not None:
                self._forget(map_id)
                raise NotFound(f"map {map_id!r} does not exist", code="map_not_found") from err
            if status == 429:
                raise Overloaded(f"Qdrant at {self.where} is overloaded") from err
            detail = err.content.decode(errors="replace")[:300] if err.content else ""
            if status in (400, 422):
                raise ServiceError(
                    f"Qdrant at {self.where} refused the request ({status}): {detail}",
                    code="index_rejected",
                ) from err
            raise Unavailable(
                f"Qdrant at {self.where} answered {status} {err.reason_phrase}: {detail}",
                code="index_unavailable",
            ) from err
        except ValueError as err:  # local mode's "Collection ... not found"
            if map_id is not None and "not found" in str(err):
                self._forget(map_id)
                raise NotFound(f"map {map_id!r} does not exist", code="map_not_found") from err
            raise
        except (ResponseHandlingException, OSError) as err:
            raise Unavailable(
                f"Qdrant at {self.where} is unreachable: {err}", code="index_unavailable"
            ) from err

    def call(self, fn: Callable[[QdrantClient], T], map_id: str | None = None) -> T:
        with self._guard(map_id):
            return fn(self.client)

    def _forget(self, map_id: str) -> None:
        self._maps.pop(map_id, None)

    # ---- the registry -----------------------------------------------------------------------

    def load_all(self) -> None:
        """Check that Qdrant answers (:class:`Unavailable` if not; the app retries). Maps are
        not loaded: they live in Qdrant and are looked up per request."""
        self.call(lambda c: c.get_collections())

    def _open(self, map_id: str) -> QdrantMap | None:
        name = self.collection(map_id)
        if not self.call(lambda c: c.collection_exists(name)):
            return None
        info = self.call(lambda c: c.get_collection(name), map_id)
        meta = info.config.metadata or {}
        if meta.get(_MARK) != 1 or meta.get("map_id") != map_id:
            # Not ours, or the map of a service with a longer prefix ("overlapmamba-v2-town"
            # is not this service's "v2-town").
            raise Conflict(
                f"Qdrant collection {name!r} exists but is not this service's map {map_id!r}; "
                "use another map id, or prefixes that are not prefixes of each other",
                code="map_conflict",
            )
        if not self.local:  # a creator that died before indexing leaves them missing
            schema = info.payload_schema or {}
            for field, kind in _INDEXES.items():
                if field not in schema:
                    self._payload_index(name, field, kind)
        return QdrantMap(self, map_id, meta)

    def get(self, map_id: str) -> QdrantMap:
        check_map_id(map_id)
        m = self._maps.get(map_id)
        if m is None or time.monotonic() - m.checked > _FRESH_S:
            m = self._open(map_id)
            if m is None:
                self._forget(map_id)
                raise NotFound(
                    f"map {map_id!r} does not exist; create it with PUT /v1/maps/{map_id}",
                    code="map_not_found",
                    map_id=map_id,
                )
            self._maps[map_id] = m
        return m

    def create(
        self, map_id: str, kind: str | None, keep_geometry: bool | None = None
    ) -> tuple[QdrantMap, bool]:
        check_map_id(map_id)
        with self._create:
            m = self._open(map_id)
            created = m is None
            if m is None:
                keep = True if keep_geometry is None else keep_geometry
                self._create_collection(map_id, kind or self.index.kind, keep)
                m = self._open(map_id)
                assert m is not None
            if kind is not None and m.kind != kind:
                raise Conflict(
                    f"map {map_id!r} exists with index {m.kind!r}, not {kind!r}",
                    code="map_conflict",
                    index=m.kind,
                )
            check_same_geometry(m, keep_geometry)
            self._maps[map_id] = m
            return m, created

    def _create_collection(self, map_id: str, kind: str, keep_geometry: bool) -> None:
        name = self.collection(map_id)
        q = self.settings
        meta = {
            _MARK: 1,
            "map_id": map_id,
            "model_id": self.model_id,
            "dim": self.dim,
            "index_kind": kind,
            "keep_geometry": keep_geometry,
            "created_at": time.time(),
        }
        hnsw = models.HnswConfigDiff(m=0) if kind == "flat" else None  # exact: no graph
        try:
            self.call(
                lambda c: c.create_collection(
                    name,
                    vectors_config=models.VectorParams(
                        size=self.dim, distance=models.Distance.EUCLID
                    ),
                    shard_number=q.shards,
                    replication_factor=q.replication_factor,
                    write_consistency_factor=q.write_consistency_factor,
                    hnsw_config=hnsw,
                    # the yaw features (≈38 KB a point) are read only for the top-k: on disk
                    on_disk_payload=True,
                    metadata=meta,
                )
            )
        except Unavailable:
            if self.call(lambda c: c.collection_exists(name)):
                return  # another replica created it first
            raise
        except ValueError:  # local mode: "already exists"
            if self.call(lambda c: c.collection_exists(name)):
                return
            raise
        if not self.local:  # local mode keeps no payload indexes (and warns)
            for field, schema in _INDEXES.items():
                self._payload_index(name, field, schema)
        log.info("map %s: created as Qdrant collection %s (%s)", map_id, name, kind)

    def _payload_index(self, name: str, field: str, schema: models.PayloadSchemaType) -> None:
        self.call(
            lambda c: c.create_payload_index(name, field, schema, wait=True, ordering=self.ordering)
        )

    def delete(self, map_id: str) -> None:
        self.get(map_id)  # 404 if it does not exist
        self.call(lambda c: c.delete_collection(self.collection(map_id)), map_id)
        self._forget(map_id)

    def snapshot_list(self) -> list[QdrantMap]:
        prefix = self.settings.collection_prefix
        out = []
        for name in self._names():
            map_id = name[len(prefix) :]
            with contextlib.suppress(NotFound, Conflict, BadRequest):  # gone, or not ours
                check_map_id(map_id)
                m = self._open(map_id)
                if m is not None:
                    self._maps[map_id] = m
                    out.append(m)
        return out

    def _names(self) -> list[str]:
        prefix = self.settings.collection_prefix
        names = [c.name for c in self.call(lambda c: c.get_collections()).collections]
        return sorted(n for n in names if n.startswith(prefix) and len(n) > len(prefix))

    def describe(self) -> dict[str, Any]:
        """One cheap call (readiness probes ask every few seconds)."""
        return {"backend": self.name, "qdrant": self.where, "maps": len(self._names())}

    def close(self, *, snapshot: bool = True) -> None:
        """Nothing of ours to flush: every acknowledged write is already in Qdrant."""
        with self._guard(None):
            self.client.close()
