"""Backup and restore of maps: the store is the map, the index is rebuilt from it.

``export_map`` copies a map's SQLite store with SQLite's online backup, so it is consistent
even while the service writes. ``import_map`` installs such a copy as a map; it needs the
service stopped (it checks the data folder's lock), and the next start builds the index.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import shutil
import sqlite3
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from overlapmamba.service.backends.faiss.sqlfile import (
    READABLE_VERSIONS,
    StoreError,
    fsync_dir,
    sqlite_uri,
)
from overlapmamba.service.backends.faiss.store import IMPORTED_MARK, Store
from overlapmamba.service.domain import check_map_id

log = logging.getLogger("overlapmamba.service")

LOCK_NAME = "service.lock"


class BackupError(RuntimeError):
    pass


LOCK_WAIT_S = 2.0  # a holder that lets go within this is waited for (doctor's probe)


@contextlib.contextmanager
def data_dir_lock(data_dir: Path, wait_s: float = LOCK_WAIT_S) -> Iterator[None]:
    """Held by a running service: one process per data folder. A lock held for a moment
    (``doctor`` takes it to see whether a service runs) is waited for up to ``wait_s``, so a
    service started at that moment is not refused."""
    try:
        data_dir.mkdir(parents=True, exist_ok=True)
        fd = os.open(data_dir / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as err:  # a file where the folder should be, no permission, …
        raise BackupError(
            f"cannot use {data_dir} as the data folder: {err.strerror or err}; allowed: a "
            "folder this process may write (--data-dir)"
        ) from None
    try:
        until = time.monotonic() + wait_s
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() >= until:
                    raise BackupError(
                        f"{data_dir} is in use by a running service (lock "
                        f"{data_dir / LOCK_NAME}); stop it first, or use another --data-dir"
                    ) from None
                time.sleep(0.05)
        yield
    finally:
        os.close(fd)


def _map_folder(data_dir: Path, map_id: str) -> Path:
    check_map_id(map_id)
    return data_dir / "maps" / map_id


def export_map(data_dir: Path, map_id: str, out: Path) -> dict[str, Any]:
    """Copy map ``map_id``'s store to ``out`` (a new file), read-only on the map: a copy
    killed halfway leaves ``<out>.tmp``, which the next export clears."""
    folder = _map_folder(data_dir, map_id)
    if not (folder / "store.sqlite").is_file():
        raise BackupError(f"no map {map_id!r} under {data_dir}")
    if out.exists():
        raise BackupError(f"{out} exists; choose a new file")
    tmp = out.with_name(out.name + ".tmp")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp.unlink(missing_ok=True)  # a cut-short export's: never a file anyone acknowledged
    except OSError as err:
        raise BackupError(f"cannot write {out}: {err.strerror or err}") from None
    try:
        store = Store(folder / "store.sqlite", readonly=True)
    except (StoreError, sqlite3.DatabaseError) as err:
        raise BackupError(
            f"map {map_id!r}'s store {folder / 'store.sqlite'} cannot be read: {err}; "
            "`overlapmamba doctor` says what is wrong with it"
        ) from None
    try:
        copied = store.backup(tmp)  # what the file holds, whatever a service writes meanwhile
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, out)
        fsync_dir(out.parent)  # the rename too: after a power cut the export is there
    except (OSError, sqlite3.Error) as err:
        tmp.unlink(missing_ok=True)
        raise BackupError(f"the copy of map {map_id!r} to {out} failed: {err}") from None
    finally:
        store.close()
    return {"map_id": map_id, "keyframes": copied, "bytes": out.stat().st_size}


def _check_backup(src: Path) -> dict[str, str]:
    """``src``'s metadata, once SQLite finds the whole file sound (``quick_check``: a
    truncated or partly overwritten copy can still count its keyframes)."""
    try:
        with contextlib.closing(sqlite3.connect(sqlite_uri(src, "ro"), uri=True)) as con:
            problems = [r[0] for r in con.execute("PRAGMA quick_check(5)").fetchall()]
            if problems != ["ok"]:
                raise BackupError(
                    f"{src} is damaged (SQLite's quick_check: {'; '.join(problems)[:300]}); "
                    "nothing was imported: export the map again"
                )
            meta = dict(con.execute("SELECT key, value FROM meta").fetchall())
    except sqlite3.DatabaseError as err:
        raise BackupError(f"{src} is damaged or not a map export: {err}") from None
    if int(meta.get("schema_version", -1)) not in READABLE_VERSIONS:
        raise BackupError(
            f"{src} has store schema {meta.get('schema_version')}; this code reads "
            f"{READABLE_VERSIONS} (an older one is upgraded on import)"
        )
    # a map's store names its model and dimension and counts its writes: without them the
    # service could not check it against its model, and its first insert would fail
    missing = [key for key in ("model_id", "dim", "seq") if not str(meta.get(key, "")).strip()]
    if missing or not str(meta["dim"]).isdigit() or not str(meta["seq"]).isdigit():
        raise BackupError(
            f"{src} is not a map export: its meta table lacks "
            f"{', '.join(missing) or 'a whole-number dim and seq'} (a map's store has "
            "model_id, dim and seq); nothing was imported"
        )
    return meta


def _as_the_owner(maps: Path) -> None:
    """Refuse to import as root into a maps folder another user owns (the service's): root's
    files there would be read-only to that service, which then refuses the map, and handing
    them over by path would let that user point root's chown and writes elsewhere (it may
    rename entries of its own folder at any time)."""
    owner = maps.stat().st_uid if maps.exists() else 0
    if os.geteuid() == 0 and owner != 0:
        raise BackupError(
            f"import-map runs as root, and {maps} belongs to user {owner} (the service's): "
            f"run it as that user (`sudo -u '#{owner}' overlapmamba import-map …`, `docker "
            f"run --user {owner} …`) so the map is the service's"
        )


def import_map(data_dir: Path, map_id: str, src: Path, *, replace: bool = False) -> dict[str, Any]:
    """Install the export ``src`` as map ``map_id`` (the service stopped). The copy is
    SQLite's own, so writes still in ``src``'s write-ahead log come along; the count
    reported is the copy's."""
    folder = _map_folder(data_dir, map_id)
    if not src.is_file():
        what = "is a folder" if src.is_dir() else "does not exist"
        raise BackupError(f"{src} {what}; allowed: a map's backup file (export-map writes one)")
    meta = _check_backup(src)
    _as_the_owner(folder.parent)
    with data_dir_lock(data_dir):
        if folder.exists() and not replace:
            raise BackupError(f"map {map_id!r} exists under {data_dir}; pass --replace")
        # The new map is complete, and marked so, before the old one moves: a crash at any
        # point leaves one of the two whole. Start-up clears the .import/.trash debris, and
        # finishes an import cut off between the two renames (IMPORTED_MARK, load_all).
        tmp = folder.with_name(f".import-{map_id}")
        shutil.rmtree(tmp, ignore_errors=True)
        try:
            tmp.mkdir(parents=True)
            source = Store(src, readonly=True)  # SQLite's backup: the -wal's writes too
            try:
                count = source.backup(tmp / "store.sqlite")  # the copy's live keyframes
            finally:
                source.close()
            store = Store(tmp / "store.sqlite")
            store.set_meta(map_id=map_id)
            store.close()
            with open(tmp / "store.sqlite", "rb+") as f:
                os.fsync(f.fileno())
        except (OSError, sqlite3.Error, StoreError) as err:
            shutil.rmtree(tmp, ignore_errors=True)
            raise BackupError(f"the import of {src} as map {map_id!r} failed: {err}") from None
        try:
            (tmp / IMPORTED_MARK).touch()
            fsync_dir(tmp)
        except OSError as err:  # not marked whole: the next start clears it, the map stays
            shutil.rmtree(tmp, ignore_errors=True)
            raise BackupError(f"the import of {src} as map {map_id!r} failed: {err}") from None
        trash = folder.with_name(f".trash-{map_id}-{time.time_ns()}")
        try:
            if folder.exists():
                os.replace(folder, trash)
        except OSError as err:  # the old map is where it was: this import is undone
            shutil.rmtree(tmp, ignore_errors=True)
            raise BackupError(
                f"the import of {src} as map {map_id!r} failed: the map in place could not "
                f"be moved away ({err}); it is as it was"
            ) from None
        try:
            os.replace(tmp, folder)
        except OSError as err:  # whole and marked, the old map away: a start finishes it
            raise BackupError(
                f"the import of {src} as map {map_id!r} was cut off while moving it in "
                f"({err}); the next start of the service finishes it (`overlapmamba doctor` "
                f"shows it): keep .import-{map_id} until then"
            ) from None
        try:  # done: what is left is housekeeping
            fsync_dir(folder.parent)
            (folder / IMPORTED_MARK).unlink()
        except OSError as err:
            log.warning("map %s: imported; its last housekeeping failed: %s", map_id, err)
        shutil.rmtree(trash, ignore_errors=True)
    return {"map_id": map_id, "keyframes": count, "model_id": meta.get("model_id")}
