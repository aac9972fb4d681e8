"""The ``faiss`` backend: every map under ``data_dir/maps``, opened at start-up.

    data_dir/maps/<map_id>/        one :class:`~overlapmamba.service.backends.faiss.map.FaissMap`
    data_dir/maps/.create-<id>     a map being created (renamed into place when whole)
    data_dir/maps/.trash-<id>-<t>  a deleted map on its way out

Debris of an interrupted create, delete or import is removed at start-up.
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
from overlapmamba.service.backends.faiss.store import fsync_dir
from overlapmamba.service.domain import MAP_ID, check_map_id
from overlapmamba.service.errors import Conflict, Unavailable
from overlapmamba.service.settings import IndexSettings

log = logging.getLogger("overlapmamba.service")


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
                    self.maps[folder.name] = FaissMap.open(folder.name, folder, self.settings)
                except Exception as err:
                    log.exception("map %s cannot be opened; it is not served", folder.name)
                    self.failed[folder.name] = f"{type(err).__name__}: {err}"
            elif folder.name.startswith((".trash-", ".import-", ".create-")):
                shutil.rmtree(folder, ignore_errors=True)

    def describe(self) -> dict[str, Any]:
        return {"backend": self.name, "data_dir": str(self.root.parent), "maps": len(self.maps)}

    def get(self, map_id: str) -> FaissMap:
        check_map_id(map_id)
        m = self.maps.get(map_id)
        if m is None and map_id in self.failed:
            raise Unavailable(
                f"map {map_id!r} exists but could not be opened: {self.failed[map_id]}",
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
                check_same_settings(m, keep_geometry, sensor, mount)
                return m, False
            folder = self.root / map_id
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
                m.close()
