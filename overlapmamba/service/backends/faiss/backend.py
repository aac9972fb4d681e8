"""The ``faiss`` backend: every map under ``data_dir/maps``, opened at start-up.

    data_dir/maps/<map_id>/        one :class:`~overlapmamba.service.backends.faiss.map.FaissMap`
    data_dir/maps/.create-<id>     a map being created (renamed into place when whole)
    data_dir/maps/.trash-<id>-<t>  a deleted map on its way out
    data_dir/maps/.import-<id>     an imported map (``overlapmamba import-map``) before it
                                   moves into place; complete once it holds IMPORTED_MARK

Debris of an interrupted create, delete or import is removed at start-up, except a complete
import whose map folder is missing (the crash fell between its two renames): it is moved into
place, so the import is finished rather than both copies lost.
"""

from __future__ import annotations

import logging
import os
import shutil
import threading
import time
from pathlib import Path
from typing import Any

from overlapmamba.core.sensors.mount import Mount
from overlapmamba.service.backends.base import check_same_settings, map_not_found
from overlapmamba.service.backends.faiss.index import set_threads
from overlapmamba.service.backends.faiss.map import FaissMap
from overlapmamba.service.backends.faiss.sqlfile import fsync_dir
from overlapmamba.service.backends.faiss.store import IMPORTED_MARK
from overlapmamba.service.backends.rows import RowCache
from overlapmamba.service.domain import MAP_ID, check_map_id
from overlapmamba.service.errors import Unavailable
from overlapmamba.service.settings import IndexSettings

log = logging.getLogger("overlapmamba.service")
# how long (s) a create waits for a deletion of the same map id to move its folder away (that
# waits for the map's writes and snapshot in progress) before answering 503 map_busy
DELETE_WAIT_S = 60.0


class FaissBackend:
    """Every map under ``data_dir/maps``, opened at start-up (the ``faiss`` backend)."""

    name = "faiss"

    def __init__(self, root: Path, settings: IndexSettings, *, model_id: str, dim: int) -> None:
        self.root = Path(root) / "maps"
        self.settings = settings
        self.model_id = model_id
        self.dim = dim
        self.maps: dict[str, FaissMap] = {}
        self.failed: dict[str, str] = {}  # map id -> why it could not be opened
        self._lock = threading.Lock()
        # map id -> set once its deletion has moved its folder away: until then a create of
        # the same id waits, or it would take the folder the deletion is about to move
        self._deleting: dict[str, threading.Event] = {}
        set_threads(settings.threads)
        # the keyframes searched last, with their yaw spectra, for every map (rows.py)
        self.row_cache = RowCache(settings.row_cache_mb * 2**20)

    def load_all(self) -> None:
        """Open every map. One that cannot be opened (a damaged store) is logged and listed
        in ``failed`` — the other maps still serve; its files are left untouched."""
        self.root.mkdir(parents=True, exist_ok=True)
        self._finish_imports()
        for folder in sorted(self.root.iterdir()):
            if folder.is_dir() and MAP_ID.fullmatch(folder.name):
                if not (folder / "store.sqlite").exists():
                    continue
                try:
                    self.maps[folder.name] = FaissMap.open(
                        folder.name, folder, self.settings, rows=self.row_cache
                    )
                except Exception as err:
                    log.exception("map %s cannot be opened; it is not served", folder.name)
                    self.failed[folder.name] = f"{type(err).__name__}: {err}"
            elif folder.name.startswith((".trash-", ".import-", ".create-")):
                shutil.rmtree(folder, ignore_errors=True)

    def _finish_imports(self) -> None:
        """An import cut off after moving the old map away and before moving the new one in
        leaves only ``.import-<id>`` (complete) and ``.trash-<id>-…``: move the import in."""
        for folder in sorted(self.root.glob(".import-*")):
            map_id = folder.name.removeprefix(".import-")
            target = self.root / map_id
            complete = (folder / IMPORTED_MARK).exists()
            if MAP_ID.fullmatch(map_id) and complete and not target.exists():
                os.replace(folder, target)
                (target / IMPORTED_MARK).unlink()
                fsync_dir(self.root)
                log.warning("map %s: finished an import cut off at start-up", map_id)

    def describe(self) -> dict[str, Any]:
        return {"backend": self.name, "data_dir": str(self.root.parent), "maps": len(self.maps)}

    def row_cache_info(self) -> dict[str, int] | None:
        return self.row_cache.info()

    def get(self, map_id: str) -> FaissMap:
        check_map_id(map_id)
        m = self.maps.get(map_id)
        if m is None and map_id in self.failed:
            store = self.root / map_id / "store.sqlite"
            raise Unavailable(
                f"map {map_id!r} exists but could not be opened: {self.failed[map_id]}. "
                f"Its store is {store}: `overlapmamba doctor` checks it; restore it from a "
                f"backup with `overlapmamba import-map {map_id} BACKUP --replace` (the service "
                "stopped)",
                code="map_unavailable",
            )
        if m is None:
            raise map_not_found(map_id)
        return m

    def get_nowait(self, map_id: str) -> FaissMap:
        """Every map is open in memory from start-up: :meth:`get` never blocks here."""
        return self.get(map_id)

    def create(
        self,
        map_id: str,
        kind: str | None,
        keep_geometry: bool | None = None,
        sensor: str | None = None,
        mount: Mount | None = None,
    ) -> tuple[FaissMap, bool]:
        """Create a map, or return the existing one when each setting is None or the same.
        While a map of that id is being deleted, wait for the deletion to finish first."""
        check_map_id(map_id)
        deadline = time.monotonic() + DELETE_WAIT_S
        while True:
            with self._lock:
                pending = self._deleting.get(map_id)
                if pending is None:
                    return self._create(map_id, kind, keep_geometry, sensor, mount)
            if not pending.wait(max(0.0, deadline - time.monotonic())):
                raise Unavailable(
                    f"map {map_id!r} is still being deleted after {DELETE_WAIT_S:g} s; try again",
                    code="map_busy",
                )

    def _create(
        self,
        map_id: str,
        kind: str | None,
        keep_geometry: bool | None,
        sensor: str | None,
        mount: Mount | None,
    ) -> tuple[FaissMap, bool]:
        """:meth:`create` with the lock held and no deletion of ``map_id`` under way."""
        if map_id in self.failed:
            self.get(map_id)  # raises: its files exist but cannot be opened
        m = self.maps.get(map_id)
        if m is not None:
            check_same_settings(m, keep_geometry, sensor, mount, kind)
            return m, False
        folder = self.root / map_id
        if (folder / "store.sqlite").exists():  # a map's files this service does not serve
            raise Unavailable(
                f"map {map_id!r} has its files at {folder} but is not served (a deletion "
                "that failed, or a copy put there while the service ran); restart the "
                "service to serve it, or move the folder away",
                code="map_unavailable",
            )
        if folder.exists():  # debris without a store (load_all skipped it): not a map
            shutil.rmtree(folder)
        m = FaissMap.create(
            map_id,
            folder,
            model_id=self.model_id,
            dim=self.dim,
            kind=kind or self.settings.kind,
            keep_geometry=True if keep_geometry is None else keep_geometry,
            sensor=sensor,
            mount=mount,
            settings=self.settings,
            rows=self.row_cache,
        )
        self.maps[map_id] = m
        return m, True

    def delete(self, map_id: str) -> None:
        with self._lock:
            m = self.get(map_id)
            del self.maps[map_id]
            done = self._deleting[map_id] = threading.Event()
        trash = self.root / f".trash-{map_id}-{time.time_ns()}"
        try:
            with m.retiring():  # after the writes, snapshot and rebuild under way
                try:
                    os.replace(m.folder, trash)
                except OSError:  # not moved (a busy mount): the map is where it was, served
                    self._reopen(map_id, m.folder)
                    raise
                fsync_dir(self.root)
        finally:
            with self._lock:
                del self._deleting[map_id]
            done.set()
        shutil.rmtree(trash, ignore_errors=True)

    def _reopen(self, map_id: str, folder: Path) -> None:
        """A map closed for a deletion that could not move its folder: served again (or, if
        it cannot be opened now, listed as failed, as at start-up)."""
        try:
            m = FaissMap.open(map_id, folder, self.settings, rows=self.row_cache)
        except Exception as err:
            log.exception("map %s: not deleted, and cannot be opened again", map_id)
            with self._lock:
                self.failed[map_id] = f"{type(err).__name__}: {err}"
            return
        with self._lock:
            self.maps[map_id] = m

    def snapshot_list(self) -> list[FaissMap]:
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
                with m.retiring():  # once the reads, writes and rebuild under way have ended
                    pass
