"""Maps: a durable store, the FAISS index derived from it, and the rules that join them.

    data_dir/maps/<map_id>/store.sqlite   the source of truth (:mod:`service.store`)
    data_dir/maps/<map_id>/index.snap     FAISS snapshot + the store seq it contains

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
import os
import shutil
import struct
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

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
from service.errors import Conflict, NotFound, Unavailable
from service.index import VectorIndex, ivf_lists, set_threads
from service.schemas import MAP_ID, check_map_id
from service.settings import IndexSettings
from service.store import Keyframe, NewKeyframe, Store, fsync_dir

log = logging.getLogger("overlapmamba.service")
SNAPSHOT_MAGIC = b"OMSNAP01"


class RWLock:
    """Many readers or one writer; a waiting writer blocks new readers (no starvation)."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._readers = 0
        self._writer = False
        self._waiting_writers = 0

    @contextlib.contextmanager
    def read(self) -> Iterator[None]:
        with self._cond:
            while self._writer or self._waiting_writers:
                self._cond.wait()
            self._readers += 1
        try:
            yield
        finally:
            with self._cond:
                self._readers -= 1
                if not self._readers:
                    self._cond.notify_all()

    @contextlib.contextmanager
    def write(self) -> Iterator[None]:
        with self._cond:
            self._waiting_writers += 1
            while self._writer or self._readers:
                self._cond.wait()
            self._waiting_writers -= 1
            self._writer = True
        try:
            yield
        finally:
            with self._cond:
                self._writer = False
                self._cond.notify_all()


class FilterColumns:
    """Per-row metadata by row id, for filter masks: robot, session, timestamp, alive."""

    def __init__(self) -> None:
        self.robot = np.zeros(0, np.int32)
        self.session = np.zeros(0, np.int32)
        self.ts = np.zeros(0, np.float64)
        self.alive = np.zeros(0, bool)
        self._codes: dict[str, int] = {}

    def code(self, value: str) -> int:
        return self._codes.setdefault(value, len(self._codes))

    def lookup(self, value: str) -> int:
        return self._codes.get(value, -1)

    def _grow(self, size: int) -> None:
        if size <= len(self.alive):
            return
        new = max(size, 2 * len(self.alive), 1024)
        for name in ("robot", "session", "ts", "alive"):
            old = getattr(self, name)
            arr = np.zeros(new, old.dtype)
            arr[: len(old)] = old
            setattr(self, name, arr)

    def add(self, ids: np.ndarray, meta: list[tuple[str, str, float]]) -> None:
        if not len(ids):
            return
        self._grow(int(ids.max()) + 1)
        self.robot[ids] = [self.code(m[0]) for m in meta]
        self.session[ids] = [self.code(m[1]) for m in meta]
        self.ts[ids] = [m[2] for m in meta]
        self.alive[ids] = True

    def remove(self, ids: np.ndarray) -> None:
        ids = ids[ids < len(self.alive)]
        self.alive[ids] = False


class Map:
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
        self._snapshot_lock = threading.Lock()
        self._maintenance = threading.Lock()
        self.closed = False
        self.kind: str = store.get_meta("index_kind") or "flat"
        self.model_id: str = store.get_meta("model_id") or ""
        self.created_at = float(store.get_meta("created_at") or 0.0)
        self.dim = int(store.get_meta("dim") or index.dim)
        # maps made before the setting existed keep geometry for their new keyframes
        self.keep_geometry: bool = store.get_meta("keep_geometry") != "false"

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
    ) -> Map:
        # Built in a temporary folder and renamed into place: a crash leaves either no map
        # or a whole one (load_all removes the debris), never a store without its metadata.
        tmp = folder.with_name(f".create-{map_id}")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        store = Store(tmp / "store.sqlite")
        store.set_meta(
            map_id=map_id,
            model_id=model_id,
            dim=dim,
            index_kind=kind,
            keep_geometry="true" if keep_geometry else "false",
            created_at=time.time(),
        )
        store.close()  # a lingering connection would checkpoint into the file later
        os.replace(tmp, folder)
        fsync_dir(folder.parent)
        return cls.open(map_id, folder, settings)

    @classmethod
    def open(cls, map_id: str, folder: Path, settings: IndexSettings) -> Map:
        """Load the snapshot (if any, and sound) and replay the store's newer changes."""
        store = Store(folder / "store.sqlite")
        dim = int(store.get_meta("dim") or 0)
        index, seq = read_snapshot(folder / "index.snap", dim, settings)
        replay_from = seq
        if index is None:
            index, replay_from = VectorIndex.flat(dim), 0
        m = cls(map_id, folder, store, index, settings, applied_seq=seq, snapshot_seq=seq)
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
        auto = self.kind == "auto" and n > self.settings.approximate_above
        return (self.kind == "ivf" or auto) and n >= 64  # IVF needs vectors to train on

    def wants_rebuild(self) -> bool:
        n = self.index.ntotal
        if not self._use_ivf(n):
            return self.index.kind != "flat"  # e.g. an IVF snapshot of a map now flat
        if self.index.kind != "ivf":
            return True
        return ivf_lists(n) >= 2 * self.index.nlist  # grown well past what it was sized for

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
            self.index = new
        log.info("map %s: index rebuilt as %s with %d vectors", self.map_id, new.kind, new.ntotal)

    def snapshot(self) -> dict[str, Any]:
        """Write the index and its seq atomically; then purge tombstones it reflects."""
        with self._snapshot_lock:
            with self.lock.read():
                self.check_open()
                seq = self.applied_seq
                payload = self.index.serialize()
                kind = self.index.kind
            header = json.dumps({"seq": seq, "kind": kind, "dim": self.dim}).encode()
            path = self.folder / "index.snap"
            tmp = path.with_suffix(".snap.tmp")
            with open(tmp, "wb") as f:
                f.write(SNAPSHOT_MAGIC + struct.pack("<I", len(header)) + header + payload)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
            fsync_dir(self.folder)
            self.snapshot_seq = seq
            purged = self.store.purge_tombstones(seq)
        return {"seq": seq, "bytes": path.stat().st_size, "purged_tombstones": purged}

    def close(self) -> None:
        """Under the write lock: requests that still hold this map then see it gone."""
        self.closed = True
        self.store.close()

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
                vecs = np.stack([r.descriptor for r in new]).astype(np.float32)
                self.index.add(id_arr, vecs)
                self.columns.add(id_arr, [(r.robot_id, r.session_id, r.timestamp) for r in new])
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
            ids = np.array([row_id], dtype=np.int64)
            self.index.remove(ids)
            self.columns.remove(ids)
            self.applied_seq = self.store.last_seq

    @property
    def writes_since_snapshot(self) -> int:
        return self.applied_seq - self.snapshot_seq

    # ---- reads ------------------------------------------------------------------------------

    def allowed(self, f: Filters) -> np.ndarray | None:
        if not f.restricts_rows:
            return None
        c = self.columns
        mask = c.alive.copy()
        if f.exclude_session is not None:
            mask &= c.session != c.lookup(f.exclude_session)
        if f.exclude_robot is not None:
            mask &= c.robot != c.lookup(f.exclude_robot)
        if f.exclude_recent_s is not None:
            assert f.session_id is not None and f.timestamp is not None  # Filters checked it
            own = c.session == c.lookup(f.session_id)
            mask &= ~(own & (c.ts > f.timestamp - f.exclude_recent_s))
        if f.time_from is not None:
            mask &= c.ts >= f.time_from
        if f.time_to is not None:
            mask &= c.ts <= f.time_to
        return mask

    def search(
        self, descriptor: np.ndarray, k: int, filters: Filters, yaw: np.ndarray | None = None
    ) -> list[Match]:
        q = np.asarray(descriptor, dtype=np.float32)  # unit norm (see check_rows)
        with self.lock.read():
            self.check_open()
            mask = self.allowed(filters)
            dists, ids = self.index.search(q, k, mask)
            rows = self.store.by_ids([int(i) for i in ids])
        found = [
            (float(d), *rows[int(i)]) for d, i in zip(dists, ids, strict=True) if int(i) in rows
        ]
        return build_matches(found, yaw, filters.max_distance)

    @property
    def count(self) -> int:
        self.check_open()
        return self.index.ntotal

    def get(self, keyframe_id: str) -> Keyframe | None:
        self.check_open()
        return self.store.get(keyframe_id)

    def geometry(self, keyframe_ids: list[str]) -> dict[str, bytes]:
        self.check_open()
        return self.store.geometry(keyframe_ids)

    def last_keyframe(self, robot_id: str) -> Keyframe | None:
        self.check_open()
        return self.store.last_keyframe(robot_id)

    def positions(self, limit: int) -> list[tuple[str, float, float]]:
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
            "seq": self.applied_seq,
            "snapshot_seq": self.snapshot_seq,
            "created_at": self.created_at,
        }


def read_snapshot(path: Path, dim: int, settings: IndexSettings) -> tuple[VectorIndex | None, int]:
    """(index, seq), or (None, 0) when there is no usable snapshot — the index is derived,
    so a missing or damaged snapshot costs a rebuild, never data."""
    if not path.exists():
        return None, 0
    try:
        data = path.read_bytes()
        if data[:8] != SNAPSHOT_MAGIC:
            raise ValueError("bad magic")
        (n,) = struct.unpack("<I", data[8:12])
        header = json.loads(data[12 : 12 + n])
        index = VectorIndex.deserialize(data[12 + n :], header["kind"], nprobe=settings.ivf_nprobe)
        if index.dim != dim:
            raise ValueError(f"dimension {index.dim}, map has {dim}")
        return index, int(header["seq"])
    except Exception as err:  # anything wrong with a derived file means: rebuild it
        log.warning("snapshot %s is unusable (%s); rebuilding the index from the store", path, err)
        return None, 0


class MapRegistry:
    """Every map under ``data_dir/maps``, opened at start-up (the ``faiss`` backend)."""

    name = "faiss"

    def __init__(self, root: Path, settings: IndexSettings, *, model_id: str, dim: int) -> None:
        self.root = Path(root) / "maps"
        self.settings = settings
        self.model_id = model_id
        self.dim = dim
        self.maps: dict[str, Map] = {}
        self.failed: dict[str, str] = {}  # map id -> why it could not be opened
        self._lock = threading.Lock()
        set_threads(settings.threads)

    def load_all(self) -> None:
        """Open every map. One that cannot be opened (a damaged store) is logged and listed
        in ``failed`` — the other maps still serve; its files are left untouched."""
        self.root.mkdir(parents=True, exist_ok=True)
        for folder in sorted(self.root.iterdir()):
            if folder.is_dir() and MAP_ID.fullmatch(folder.name):
                if not (folder / "store.sqlite").exists():
                    continue
                try:
                    self.maps[folder.name] = Map.open(folder.name, folder, self.settings)
                except Exception as err:
                    log.exception("map %s cannot be opened; it is not served", folder.name)
                    self.failed[folder.name] = f"{type(err).__name__}: {err}"
            elif folder.name.startswith((".trash-", ".import-", ".create-")):
                shutil.rmtree(folder, ignore_errors=True)

    def describe(self) -> dict[str, Any]:
        return {"backend": self.name, "data_dir": str(self.root.parent), "maps": len(self.maps)}

    def get(self, map_id: str) -> Map:
        check_map_id(map_id)
        m = self.maps.get(map_id)
        if m is None and map_id in self.failed:
            raise Unavailable(
                f"map {map_id!r} exists but could not be opened: {self.failed[map_id]}",
                code="map_unavailable",
            )
        if m is None:
            raise NotFound(
                f"map {map_id!r} does not exist; create it with PUT /v1/maps/{map_id}",
                code="map_not_found",
                map_id=map_id,
            )
        return m

    def create(
        self, map_id: str, kind: str | None, keep_geometry: bool | None = None
    ) -> tuple[Map, bool]:
        """Create a map, or return the existing one when each setting is None or the same."""
        check_map_id(map_id)
        with self._lock:
            if map_id in self.failed:
                self.get(map_id)  # raises: its files exist but cannot be opened
            m = self.maps.get(map_id)
            if m is not None:
                if kind is not None and m.kind != kind:
                    raise Conflict(
                        f"map {map_id!r} exists with index {m.kind!r}, not {kind!r}",
                        code="map_conflict",
                        index=m.kind,
                    )
                check_same_geometry(m, keep_geometry)
                return m, False
            folder = self.root / map_id
            if folder.exists():  # debris without a store (load_all skipped it): not a map
                shutil.rmtree(folder)
            m = Map.create(
                map_id,
                folder,
                model_id=self.model_id,
                dim=self.dim,
                kind=kind or self.settings.kind,
                keep_geometry=True if keep_geometry is None else keep_geometry,
                settings=self.settings,
            )
            self.maps[map_id] = m
            return m, True

    def delete(self, map_id: str) -> None:
        with self._lock:
            m = self.get(map_id)
            del self.maps[map_id]
        with m.lock.write():
            m.close()
            trash = self.root / f".trash-{map_id}-{time.time_ns()}"
            os.replace(m.folder, trash)
            fsync_dir(self.root)
        shutil.rmtree(trash, ignore_errors=True)

    def snapshot_list(self) -> list[Map]:
        with self._lock:
            return list(self.maps.values())

    def close(self, *, snapshot: bool = True) -> None:
        for m in self.snapshot_list():
            try:
                if snapshot and m.writes_since_snapshot:
                    m.snapshot()
            except Exception:  # the store is durable; a missing snapshot costs a replay
                log.exception("map %s: final snapshot failed", m.map_id)
            finally:
                m.close()
