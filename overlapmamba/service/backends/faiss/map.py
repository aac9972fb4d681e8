"""One map of the ``faiss`` backend: a durable store, the FAISS index derived from it, and
the rules that join them.

    data_dir/maps/<map_id>/store.sqlite   the source of truth (:mod:`.store`)
    data_dir/maps/<map_id>/index.snap     FAISS index + the store seq it holds (:mod:`.snapshot`)

A write takes the map's write lock, commits to the store, then updates the index, so the
index never holds what the store does not, and ``applied_seq`` is exact. A crash between
the commit and the index update loses nothing: on start the snapshot is loaded and every
store change after its seq is replayed. Searches share a read lock and run concurrently.

Snapshots are written atomically (temporary file, fsync, rename, fsync of the folder), every
``snapshot_every`` writes, on shutdown, and on request.
"""

from __future__ import annotations

import contextlib
import json
import logging
import sqlite3
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from overlapmamba.core.sensors.mount import Mount
from overlapmamba.core.yaw import Spectrum
from overlapmamba.service.backends.base import build_matches, check_existing, insert_results
from overlapmamba.service.backends.faiss.columns import FilterColumns
from overlapmamba.service.backends.faiss.folder import make_map_folder
from overlapmamba.service.backends.faiss.index import VectorIndex, needs_rebuild, wants_ivf
from overlapmamba.service.backends.faiss.locks import RWLock
from overlapmamba.service.backends.faiss.snapshot import (
    SNAPSHOT_NAME,
    read_snapshot,
    write_snapshot,
)
from overlapmamba.service.backends.faiss.sqlfile import storage_full
from overlapmamba.service.backends.faiss.store import Store
from overlapmamba.service.backends.rows import RowCache
from overlapmamba.service.domain import (
    Filters,
    InsertResult,
    Keyframe,
    Match,
    NewKeyframe,
    check_rows,
)
from overlapmamba.service.errors import NotFound, Unavailable
from overlapmamba.service.settings import IndexSettings

log = logging.getLogger("overlapmamba.service")


class FaissMap:
    """One map: its store, the FAISS index derived from it, and the rules that join them."""

    def __init__(
        self,
        map_id: str,
        folder: Path,
        store: Store,
        index: VectorIndex,
        settings: IndexSettings,
        *,
        applied_seq: int,
        snapshot_seq: int,
        rows: RowCache | None = None,
    ) -> None:
        self.map_id = map_id
        self.folder = folder
        self.store = store
        self.index = index
        self.settings = settings
        self.applied_seq = applied_seq
        self.snapshot_seq = snapshot_seq
        self.lock = RWLock()
        self.columns = FilterColumns()
        # the keyframes searched last (shared by the backend's maps; none: keeps nothing)
        self.row_cache = rows or RowCache(0)
        self.token = self.row_cache.token()
        self._snapshot_lock = threading.Lock()
        self._maintenance = threading.Lock()
        self.closed = False
        # a write reached the store but not the index or the filter columns (it failed
        # between, e.g. out of memory): they are rebuilt from the store before any snapshot,
        # which would otherwise record the write as applied and a restart never replay it
        self.incomplete = False
        self.kind: str = store.get_meta("index_kind") or "flat"
        self.model_id: str = store.get_meta("model_id") or ""
        self.created_at = float(store.get_meta("created_at") or 0.0)
        self.dim = int(store.get_meta("dim") or index.dim)
        # maps made before the setting existed keep geometry for their new keyframes
        self.keep_geometry: bool = store.get_meta("keep_geometry") != "false"
        # maps made before sensors were named hold the model's own sensor's scans
        self.sensor: str | None = store.get_meta("sensor")
        mount = store.get_meta("mount")  # maps made before mounts were declared: none
        self.mount: Mount | None = None if mount is None else Mount(**json.loads(mount))

    # ---- opening and snapshots --------------------------------------------------------------

    @classmethod
    def create(
        cls,
        map_id: str,
        folder: Path,
        *,
        model_id: str,
        dim: int,
        kind: str,
        settings: IndexSettings,
        keep_geometry: bool = True,
        sensor: str | None = None,
        mount: Mount | None = None,
        rows: RowCache | None = None,
    ) -> FaissMap:
        meta = {
            "map_id": map_id,
            "model_id": model_id,
            "dim": dim,
            "index_kind": kind,
            "keep_geometry": "true" if keep_geometry else "false",
            "created_at": time.time(),
            **({} if sensor is None else {"sensor": sensor}),
            **({} if mount is None else {"mount": json.dumps(mount.key())}),
        }
        make_map_folder(map_id, folder, meta)
        return cls.open(map_id, folder, settings, rows=rows)

    @classmethod
    def open(
        cls, map_id: str, folder: Path, settings: IndexSettings, *, rows: RowCache | None = None
    ) -> FaissMap:
        """Load the snapshot (if any, and sound) and replay the store's newer changes."""
        store = Store(folder / "store.sqlite")
        dim = int(store.get_meta("dim") or 0)
        stale = (folder / SNAPSHOT_NAME).with_suffix(".snap.tmp")  # a write cut short
        stale.unlink(missing_ok=True)
        index, seq = read_snapshot(folder / SNAPSHOT_NAME, dim, settings)
        if index is not None and seq > store.last_seq:  # not this store's: rebuild from it
            log.warning(
                "map %s: its snapshot reflects writes up to %d, its store holds %d: rebuilt",
                map_id,
                seq,
                store.last_seq,
            )
            index, seq = None, 0
        replay_from = seq
        if index is None:
            index, replay_from = VectorIndex.flat(dim), 0
        m = cls(
            map_id, folder, store, index, settings, applied_seq=seq, snapshot_seq=seq, rows=rows
        )
        with m.lock.write():
            for ids, meta in store.live_meta():  # filter columns for every live row
                m.columns.add(ids, meta)
            added = 0
            for ids, vecs, _ in store.live_rows(replay_from):
                m.index.add(ids, vecs)
                added += len(ids)
            removed = m.index.remove(store.deleted_after(replay_from))
            m.applied_seq = store.last_seq
        if added or removed:
            log.info("map %s: replayed %d inserts, %d deletes", map_id, added, removed)
        if m.wants_rebuild():
            m.rebuild()
        return m

    def _use_ivf(self, n: int) -> bool:
        return wants_ivf(self.kind, n, self.settings.approximate_above)

    def wants_rebuild(self) -> bool:
        return self.incomplete or needs_rebuild(self.index, self._use_ivf(self.index.ntotal))

    def maintain(self) -> None:
        """After writes: rebuild or snapshot in a background thread when due (one at a time)."""
        due_rebuild = self.wants_rebuild()
        # A snapshot rewrites the whole index (1 GB at 1M keyframes): for big maps, wait for
        # 5 % of their size in writes; a restart replays at most that much from the store.
        every = max(self.settings.snapshot_every, self.index.ntotal // 20)
        due_snapshot = self.writes_since_snapshot >= every
        if not (due_rebuild or due_snapshot) or not self._maintenance.acquire(blocking=False):
            return

        def work() -> None:
            try:
                if due_rebuild:
                    self.rebuild()
                self.snapshot()
            except Exception:  # a failed derived-file write must not take the map down
                log.exception("map %s: background maintenance failed", self.map_id)
            finally:
                self._maintenance.release()

        threading.Thread(target=work, name=f"maintain-{self.map_id}", daemon=True).start()

    def rebuild(self) -> None:
        """Build the index this map's kind and size call for, from the store, then swap it in.
        Searches and writes go on meanwhile; the writes made during the build are applied
        under the write lock before the swap."""
        with self._snapshot_lock:  # no tombstone purge while rows are being read
            self._rebuild()

    def _rebuild(self) -> None:
        if self.closed:
            return
        with self.lock.read():
            seq = self.applied_seq
            repair = self.incomplete
        ids, vecs = [], []
        for i, v, _ in self.store.live_rows(0, upto_seq=seq):
            ids.append(i)
            vecs.append(v)
        all_ids = np.concatenate(ids) if ids else np.zeros(0, np.int64)
        all_vecs = np.concatenate(vecs) if vecs else np.zeros((0, self.dim), np.float32)
        if self._use_ivf(len(all_ids)):
            new = VectorIndex.ivf(all_vecs, nprobe=self.settings.ivf_nprobe)
        else:
            new = VectorIndex.flat(self.dim)
        new.add(all_ids, all_vecs)
        with self.lock.write():
            if self.closed:
                return
            for rows, v, _ in self.store.live_rows(seq):
                new.add(rows, v)
            new.remove(self.store.deleted_after(seq))
            if repair or self.incomplete:  # the filter columns too, from every live row
                # (``incomplete`` again: a write that failed during the build may have left
                # its row out of them, though the replay above put it in the index)
                columns = FilterColumns()
                for rows, meta in self.store.live_meta():
                    columns.add(rows, meta)
                self.columns = columns
            self.index = new
            self.applied_seq = self.store.last_seq
            self.incomplete = False
        log.info("map %s: index rebuilt as %s with %d vectors", self.map_id, new.kind, new.ntotal)

    def snapshot(self) -> dict[str, Any]:
        """Write the index and its seq atomically; then purge tombstones it reflects."""
        with self._snapshot_lock:
            for _ in range(3):
                if self.incomplete:
                    self._rebuild()
                with self.lock.read():
                    self.check_open()
                    # checked again under the lock: a write that failed since would leave its
                    # row out of an index recorded as holding every write up to ``seq``
                    if self.incomplete:
                        continue
                    seq = self.applied_seq
                    payload = self.index.serialize()
                    kind = self.index.kind
                    break
            else:
                raise Unavailable(
                    f"map {self.map_id!r}: its index update keeps failing, so no snapshot was "
                    "written (the store holds every write; see the log)"
                )
            try:
                path = write_snapshot(self.folder / SNAPSHOT_NAME, payload, seq, kind, self.dim)
            except OSError as err:
                what = f"map {self.map_id!r}'s snapshot was not written (the map serves on)"
                full = storage_full(err, what)
                if full is not None:
                    raise full from err
                raise
            self.snapshot_seq = seq
            size = path.stat().st_size  # here: a deletion after the lock moves the folder
            try:  # housekeeping: the snapshot is written whatever becomes of it
                purged = self.store.purge_tombstones(seq)
            except sqlite3.Error as err:  # e.g. a full disk: the next snapshot purges them
                log.warning(
                    "map %s: tombstones not purged after its snapshot: %s", self.map_id, err
                )
                purged = 0
        return {"seq": seq, "bytes": size, "purged_tombstones": purged}

    @contextlib.contextmanager
    def retiring(self) -> Iterator[None]:
        """Close the map once the writes, snapshot and rebuild under way have ended; the body
        then runs while nothing else can touch its folder (a deletion moves it away there,
        and a snapshot cut off by it cannot land in another map's folder of the same id)."""
        with self._snapshot_lock, self.lock.write():
            self.close()
            yield

    def close(self) -> None:
        """Under the write lock: requests that still hold this map then see it gone."""
        self.closed = True
        self.store.close()
        self.row_cache.drop(self.token)

    @property
    def retired(self) -> bool:
        return self.closed

    def check_open(self) -> None:
        if self.closed:
            raise NotFound(f"map {self.map_id!r} was deleted", code="map_not_found")

    # ---- writes -----------------------------------------------------------------------------

    def insert(self, rows: list[NewKeyframe]) -> list[InsertResult]:
        """Insert rows, idempotent on keyframe_id: a known id with the same content returns
        the stored keyframe; with other content the whole request is refused (409)."""
        ids_wanted = check_rows(rows, self.dim)
        with self.lock.write():
            self.check_open()
            existing = self.store.get_many(ids_wanted)
            new = check_existing(rows, existing)
            created: dict[str, Keyframe] = {}
            if new:
                ids, seq = self.store.insert(new)
                id_arr = np.array(ids, dtype=np.int64)
                with self._behind_on_failure():
                    vecs = np.stack([r.descriptor for r in new]).astype(np.float32)
                    self.index.add(id_arr, vecs)
                    meta = [(r.robot_id, r.session_id, r.timestamp) for r in new]
                    self.columns.add(id_arr, meta)
                self.applied_seq = seq
                created = self.store.get_many([r.keyframe_id for r in new])
        return insert_results(rows, existing, created)

    def delete(self, keyframe_id: str) -> None:
        with self.lock.write():
            self.check_open()
            row_id = self.store.delete(keyframe_id)
            if row_id is None:
                raise NotFound(
                    f"map {self.map_id!r} has no keyframe {keyframe_id!r}",
                    code="keyframe_not_found",
                )
            self.row_cache.discard(self.token, [row_id])
            ids = np.array([row_id], dtype=np.int64)
            with self._behind_on_failure():
                self.index.remove(ids)
                self.columns.remove(ids)
            self.applied_seq = self.store.last_seq

    @contextlib.contextmanager
    def _behind_on_failure(self) -> Iterator[None]:
        """Around a committed write's index and column updates: if they fail, the map is
        marked :attr:`incomplete` and rebuilt from the store in the background (or before the
        next snapshot, should that fail too); the error goes on to the caller."""
        try:
            yield
        except BaseException:
            self.incomplete = True
            with contextlib.suppress(Exception):  # the rebuild, once this write lock is let go
                self.maintain()
            log.error(
                "map %s: a stored write did not reach its index; rebuilt from the store",
                self.map_id,
            )
            raise

    @property
    def writes_since_snapshot(self) -> int:
        return self.applied_seq - self.snapshot_seq

    # ---- reads ------------------------------------------------------------------------------

    def search(
        self,
        descriptor: np.ndarray,
        k: int,
        filters: Filters,
        yaw: np.ndarray | None = None,
        *,
        yaw_k: int | None = None,
        descriptors: bool = False,  # the store gives them always: a local read, ≈1 KB a row
    ) -> list[Match]:
        q = np.asarray(descriptor, dtype=np.float32)  # unit norm (see check_rows)
        with self.lock.read():
            self.check_open()
            mask = self.columns.mask(filters)  # over the columns' rows, from their base
            dists, ids = self.index.search(q, k, mask, self.columns.base)
            wanted = [int(i) for i in ids]
            rows: dict[int, tuple[Keyframe, np.ndarray | Spectrum | None]]
            if yaw is None:
                rows = dict(self.store.by_ids(wanted))
            else:  # the correlated first yaw_k from the row cache, with their spectra
                rows = self.row_cache.read(self.token, wanted, yaw_k, self.store.by_ids)
        found = [
            (float(d), *rows[int(i)]) for d, i in zip(dists, ids, strict=True) if int(i) in rows
        ]
        return build_matches(found, yaw, filters.max_match_distance, yaw_k)

    @property
    def count(self) -> int:
        self.check_open()
        return self.index.ntotal

    # The store reads below hold the read lock as search does: a deletion closes the map
    # under the write lock, so a read either finishes first or finds the map gone (404),
    # never a store whose folder was moved away (500) or re-created under the same id.

    def get(self, keyframe_id: str) -> Keyframe | None:
        with self.lock.read():
            self.check_open()
            return self.store.get(keyframe_id)

    def geometry(self, keyframe_ids: list[str]) -> dict[str, bytes]:
        with self.lock.read():
            self.check_open()
            return self.store.geometry(keyframe_ids)

    def last_keyframe(self, robot_id: str, session_id: str) -> Keyframe | None:
        with self.lock.read():
            self.check_open()
            return self.store.last_keyframe(robot_id, session_id)

    def positions(self, limit: int) -> list[tuple[str, float, float]]:
        with self.lock.read():
            self.check_open()
            return self.store.positions(limit)

    def info(self) -> dict[str, Any]:
        with self.lock.read():
            self.check_open()
            keyframes = self.store.count()
        return {
            "map_id": self.map_id,
            "model_id": self.model_id,
            "backend": "faiss",
            "index": {
                "kind": self.kind,
                "active": self.index.kind,
                "nlist": self.index.nlist,
                "vectors": self.index.ntotal,
            },
            "keyframes": keyframes,
            "keep_geometry": self.keep_geometry,
            "sensor": self.sensor,
            "mount": None if self.mount is None else self.mount.key(),
            "seq": self.applied_seq,
            "snapshot_seq": self.snapshot_seq,
            "created_at": self.created_at,
        }
