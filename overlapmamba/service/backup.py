"""Backup and restore of maps: the store is the map, the index is rebuilt from it.

``export_map`` copies a map's SQLite store with SQLite's online backup, so it is consistent
even while the service writes. ``import_map`` installs such a copy as a map; it needs the
service stopped (it checks the data folder's lock), and the next start builds the index.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import sqlite3
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from overlapmamba.service.backends.faiss.store import (
    IMPORTED_MARK,
    READABLE_VERSIONS,
    Store,
    fsync_dir,
)
from overlapmamba.service.domain import check_map_id

LOCK_NAME = "service.lock"


class BackupError(RuntimeError):
    pass


@contextlib.contextmanager
def data_dir_lock(data_dir: Path) -> Iterator[None]:
    """Held by a running service: one process per data folder."""
    data_dir.mkdir(parents=True, exist_ok=True)
    fd = os.open(data_dir / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise BackupError(
                f"{data_dir} is in use by a running service (lock {data_dir / LOCK_NAME}); "
                "stop it first, or use another --data-dir"
            ) from None
        yield
    finally:
        os.close(fd)


def _map_folder(data_dir: Path, map_id: str) -> Path:
    check_map_id(map_id)
    return data_dir / "maps" / map_id


def export_map(data_dir: Path, map_id: str, out: Path) -> dict[str, Any]:
    folder = _map_folder(data_dir, map_id)
    if not (folder / "store.sqlite").is_file():
        raise BackupError(f"no map {map_id!r} under {data_dir}")
    if out.exists():
        raise BackupError(f"{out} exists; choose a new file")
    out.parent.mkdir(parents=True, exist_ok=True)
    store = Store(folder / "store.sqlite")
    try:
        tmp = out.with_name(out.name + ".tmp")
        copied = store.backup(tmp)  # what the file holds, whatever a service writes meanwhile
        os.replace(tmp, out)
        return {"map_id": map_id, "keyframes": copied, "bytes": out.stat().st_size}
    finally:
        store.close()


def import_map(data_dir: Path, map_id: str, src: Path, *, replace: bool = False) -> dict[str, Any]:
    folder = _map_folder(data_dir, map_id)
    if not src.is_file():
        raise BackupError(f"{src} does not exist")
    try:
        con = sqlite3.connect(f"file:{src}?mode=ro", uri=True)
        try:
            meta = dict(con.execute("SELECT key, value FROM meta").fetchall())
            count = con.execute(
                "SELECT COUNT(*) FROM keyframes WHERE keyframe_id IS NOT NULL"
            ).fetchone()[0]
        finally:
            con.close()
    except sqlite3.DatabaseError as err:
        raise BackupError(f"{src} is not a map export: {err}") from None
    if int(meta.get("schema_version", -1)) not in READABLE_VERSIONS:
        raise BackupError(
            f"{src} has store schema {meta.get('schema_version')}; this code reads "
            f"{READABLE_VERSIONS} (an older one is upgraded on import)"
        )
    with data_dir_lock(data_dir):
        if folder.exists() and not replace:
            raise BackupError(f"map {map_id!r} exists under {data_dir}; pass --replace")
        # The new map is complete, and marked so, before the old one moves: a crash at any
        # point leaves one of the two whole. Start-up clears the .import/.trash debris, and
        # finishes an import cut off between the two renames (IMPORTED_MARK, load_all).
        tmp = folder.with_name(f".import-{map_id}")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        shutil.copyfile(src, tmp / "store.sqlite")
        store = Store(tmp / "store.sqlite")
        store.set_meta(map_id=map_id)
        store.close()
        with open(tmp / "store.sqlite", "rb+") as f:
            os.fsync(f.fileno())
        (tmp / IMPORTED_MARK).touch()
        fsync_dir(tmp)
        trash = folder.with_name(f".trash-{map_id}-{time.time_ns()}")
        if folder.exists():
            os.replace(folder, trash)
        os.replace(tmp, folder)
        fsync_dir(folder.parent)
        (folder / IMPORTED_MARK).unlink()
        shutil.rmtree(trash, ignore_errors=True)
    return {"map_id": map_id, "keyframes": count, "model_id": meta.get("model_id")}
