"""The ``qdrant`` backend: each map is a Qdrant collection; the service keeps no state.

    collection   <qdrant.collection_prefix><map_id>, Euclidean distance over unit
                 descriptors (the same L2 the FAISS backend answers with); its metadata
                 holds the map's model id, dimension, index kind, whether it keeps
                 geometry, its sensor and mount, and its creation time
    point id     uuid5(keyframe_id): a retried insert lands on the same point
    payload      keyframe_id, robot_id, session_id (keyword indexes), timestamp (float
                 index), pose, content_hash, created_at, the yaw features (float16,
                 base64; not indexed) and the compact geometry (overlapmamba.core.geometry,
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

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any, TypeVar
from urllib.parse import urlsplit, urlunsplit

from qdrant_client import QdrantClient, models
from qdrant_client.common.client_exceptions import ResourceExhaustedResponse
from qdrant_client.http.exceptions import ResponseHandlingException, UnexpectedResponse

from overlapmamba.core.sensors.mount import Mount
from overlapmamba.service.backends.base import check_same_settings, map_not_found
from overlapmamba.service.backends.qdrant.codec import FRESH_S, INDEXES, MARK
from overlapmamba.service.backends.qdrant.map import QdrantMap
from overlapmamba.service.backends.rows import RowCache
from overlapmamba.service.domain import MAP_ID, check_map_id
from overlapmamba.service.errors import (
    BadRequest,
    Conflict,
    NotFound,
    Overloaded,
    ServiceError,
    Unavailable,
)
from overlapmamba.service.settings import IndexSettings, QdrantSettings

log = logging.getLogger("overlapmamba.service")
T = TypeVar("T")


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
        # the yaw spectra of the keyframes searched last, by content (rows.py; QdrantMap.search)
        self.row_cache = RowCache(index.row_cache_mb * 2**20)
        self.row_token = self.row_cache.token()
        self.local = qs.path is not None
        self.ef = qs.hnsw_ef
        self.ordering = None if self.local else models.WriteOrdering.STRONG
        self.consistency = None if self.local else models.ReadConsistencyType.MAJORITY
        # where it is, for messages, logs and /readyz: never the credentials a URL may hold
        self.where = str(qs.path) if self.local else _without_credentials(str(qs.url))
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
        # map id → how many times this replica deleted it: a handle opened before a deletion
        # writes nothing after it (its writes would land in a map created again under the id)
        self._deletions: dict[str, int] = {}

    def deletions(self, map_id: str) -> int:
        return self._deletions.get(map_id, 0)

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
                raise map_not_found(map_id) from err
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
                raise map_not_found(map_id) from err
            if not self.local:  # a server's answer that is not Qdrant's JSON (a proxy's page)
                raise Unavailable(
                    f"Qdrant at {self.where} answered something that is not Qdrant's JSON: {err}",
                    code="index_unavailable",
                ) from err
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
        if meta.get(MARK) != 1 or meta.get("map_id") != map_id:
            # Not ours, or the map of a service with a longer prefix ("overlapmamba-v2-town"
            # is not this service's "v2-town").
            raise Conflict(
                f"Qdrant collection {name!r} exists but is not this service's map {map_id!r}; "
                "use another map id, or prefixes that are not prefixes of each other",
                code="map_conflict",
            )
        if not self.local:  # a creator that died before indexing leaves them missing
            schema = info.payload_schema or {}
            for field, kind in INDEXES.items():
                if field not in schema:
                    self._payload_index(name, field, kind)
        return QdrantMap(self, map_id, meta)

    def get(self, map_id: str) -> QdrantMap:
        m = self.get_nowait(map_id)
        if m is None:
            m = self._open(map_id)
            if m is None:
                self._forget(map_id)
                raise map_not_found(map_id)
            self._maps[map_id] = m
        return m

    def get_nowait(self, map_id: str) -> QdrantMap | None:
        """The map while its last look at the server is fresh; otherwise only :meth:`get`
        (which asks the server) can tell."""
        check_map_id(map_id)
        m = self._maps.get(map_id)
        return m if m is not None and time.monotonic() - m.checked <= FRESH_S else None

    def create(
        self,
        map_id: str,
        kind: str | None,
        keep_geometry: bool | None = None,
        sensor: str | None = None,
        mount: Mount | None = None,
    ) -> tuple[QdrantMap, bool]:
        check_map_id(map_id)
        with self._create:
            m = self._open(map_id)
            created = m is None
            if m is None:
                keep = True if keep_geometry is None else keep_geometry
                self._create_collection(map_id, kind or self.index.kind, keep, sensor, mount)
                m = self._open(map_id)
                assert m is not None
            check_same_settings(m, keep_geometry, sensor, mount, kind)
            self._maps[map_id] = m
            return m, created

    def _create_collection(
        self,
        map_id: str,
        kind: str,
        keep_geometry: bool,
        sensor: str | None,
        mount: Mount | None = None,
    ) -> None:
        name = self.collection(map_id)
        q = self.settings
        meta = {
            MARK: 1,
            "map_id": map_id,
            "model_id": self.model_id,
            "dim": self.dim,
            "index_kind": kind,
            "keep_geometry": keep_geometry,
            "sensor": sensor,
            "mount": None if mount is None else mount.key(),
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
            for field, schema in INDEXES.items():
                self._payload_index(name, field, schema)
        log.info("map %s: created as Qdrant collection %s (%s)", map_id, name, kind)

    def _payload_index(self, name: str, field: str, schema: models.PayloadSchemaType) -> None:
        self.call(
            lambda c: c.create_payload_index(name, field, schema, wait=True, ordering=self.ordering)
        )

    def delete(self, map_id: str) -> None:
        """As the FAISS backend's: a PUT of the same id meanwhile waits (then makes a new
        map), the writes under way in this replica end first, and a handle opened before
        writes nothing after (404). A map already gone (another replica's delete, or a
        second DELETE) is 404."""
        with self._create:
            self.get(map_id)  # 404 if it does not exist
            with self.write_lock(map_id):
                self._deletions[map_id] = self.deletions(map_id) + 1
                self._forget(map_id)
                dropped = self.call(lambda c: c.delete_collection(self.collection(map_id)), map_id)
        if dropped is False:
            raise map_not_found(map_id)

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
        maps = [
            n for n in self._names() if MAP_ID.fullmatch(n[len(self.settings.collection_prefix) :])
        ]
        return {"backend": self.name, "qdrant": self.where, "maps": len(maps)}

    def row_cache_info(self) -> dict[str, int] | None:
        return self.row_cache.info()

    def close(self, *, snapshot: bool = True) -> None:
        """Nothing of ours to flush: every acknowledged write is already in Qdrant."""
        with self._guard(None):
            self.client.close()


def _without_credentials(url: str) -> str:
    """``url`` with any ``user:password@`` replaced by ``***@``."""
    parts = urlsplit(url)
    if parts.username is None and parts.password is None:
        return url
    host = parts.hostname or ""
    if ":" in host:  # an IPv6 address
        host = f"[{host}]"
    netloc = f"***@{host}" + (f":{parts.port}" if parts.port is not None else "")
    return urlunsplit(parts._replace(netloc=netloc))
