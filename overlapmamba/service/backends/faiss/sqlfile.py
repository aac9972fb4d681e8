"""The SQLite file under a map's store (:mod:`overlapmamba.service.backends.faiss.store`):
its schema and the versions that can be read, how it is opened by path (a URI that keeps
the path whole, immutable where no writer can have it) and its connections (one writer,
pooled readers), how a new entry in a folder is made durable, and what a failed write
leaves (rolled back; a full disk named as one)."""

from __future__ import annotations

import contextlib
import errno
import os
import queue
import sqlite3
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from overlapmamba.service.errors import Unavailable

SCHEMA_VERSION = 3
READABLE_VERSIONS = (1, 2, 3)  # a read-only open (doctor) reads any
SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS keyframes (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    keyframe_id TEXT UNIQUE,
    deleted_keyframe_id TEXT,
    robot_id TEXT NOT NULL,
    session_id TEXT NOT NULL,
    timestamp REAL NOT NULL,
    pose TEXT,
    descriptor BLOB NOT NULL,
    yaw BLOB,
    yaw_shape TEXT,
    content_hash TEXT NOT NULL,
    seq INTEGER NOT NULL,
    deleted_seq INTEGER,
    created_at REAL NOT NULL,
    geometry BLOB,
    sensor TEXT
);
CREATE INDEX IF NOT EXISTS keyframes_seq ON keyframes(seq);
CREATE INDEX IF NOT EXISTS keyframes_deleted_seq ON keyframes(deleted_seq);
CREATE INDEX IF NOT EXISTS keyframes_robot_time ON keyframes(robot_id, timestamp)
    WHERE keyframe_id IS NOT NULL;
-- the overview's latest posed keyframes (positions): without it, each of the dashboard's
-- polls read and sorted the whole table under the map's read lock (0.3 s at 150,000 rows).
-- Made on open where missing; an index changes nothing an older reader reads.
CREATE INDEX IF NOT EXISTS keyframes_posed_time ON keyframes(timestamp)
    WHERE keyframe_id IS NOT NULL AND pose IS NOT NULL;
"""


def sqlite_uri(path: Path, mode: str) -> str:
    """SQLite's URI of ``path`` opened in ``mode`` (ro, rw): percent-encoded, so that a
    ``#`` or ``?`` in a folder's name is part of the path, not the URI's fragment or query
    (where SQLite would open, or create, another file).

    Read-only beside a folder this process may not write (a backup mount, another account's
    data folder), SQLite cannot make the shared-memory file a WAL-mode file is read with:
    such a file with neither a write-ahead log nor its shared memory beside it (its writer
    closed, or an export) is opened ``immutable``, as the file it then is; one a writer may
    have open is not (it could change under the reader), and SQLite's error names it."""
    path = Path(path).absolute()
    uri = f"{path.as_uri()}?mode={mode}"
    if mode == "ro" and not os.access(path.parent, os.W_OK):
        # no log and no shared memory: no writer has it open (a live service keeps both)
        wal, shm = (path.with_name(path.name + suffix) for suffix in ("-wal", "-shm"))
        if not wal.exists() and not shm.exists():
            uri += "&immutable=1"
    return uri


class StoreError(RuntimeError):
    """The store file is missing, of another schema, or of another model."""


class Connections:
    """A store file's connections: one writer, opened first (the only one that may create
    the file), its transactions taken under ``write_lock``; and readers, pooled, not one per
    thread: worker threads come and go, and a connection per thread that ever read would
    leak file descriptors. ``readonly``: the writer too only reads (`overlapmamba doctor`)."""

    def __init__(self, path: Path, *, readonly: bool = False, create: bool = False) -> None:
        self.path = Path(path)
        self.readonly = readonly
        self.pool: queue.SimpleQueue[sqlite3.Connection] = queue.SimpleQueue()
        self.write_lock = threading.Lock()
        self._pool_lock = threading.Lock()  # a reader's return against close()
        self._closed = False
        self.writer = self._connect(create=create)

    def _connect(self, *, create: bool = False) -> sqlite3.Connection:
        """A connection to the file; only the writer opened at start may create it (a
        reader's never re-creates a store whose map was deleted under it)."""
        if self.readonly:
            uri = sqlite_uri(self.path, "ro")
            con = sqlite3.connect(uri, uri=True, check_same_thread=False, isolation_level=None)
            con.execute("PRAGMA busy_timeout=10000")
            return con
        target = str(self.path) if create else sqlite_uri(self.path, "rw")
        con = sqlite3.connect(target, uri=not create, check_same_thread=False, isolation_level=None)
        con.execute("PRAGMA journal_mode=WAL")
        con.execute("PRAGMA synchronous=FULL")
        con.execute("PRAGMA busy_timeout=10000")
        return con

    @contextlib.contextmanager
    def reading(self) -> Iterator[sqlite3.Connection]:
        """A reader's connection, from the pool or new, back to the pool afterwards."""
        with self._pool_lock:
            if self._closed:
                raise StoreError(f"{self.path} is closed")
            try:
                con: sqlite3.Connection | None = self.pool.get_nowait()
            except queue.Empty:
                con = None
        if con is None:  # a close() from here on closes it on its return, below
            con = self._connect()
        try:
            yield con
        finally:
            # checked and returned as one step: a close() between them would leave this
            # connection pooled after it, open on a file its map may have deleted
            with self._pool_lock:
                if self._closed:
                    con.close()
                else:
                    self.pool.put(con)

    def rows(self, sql: str, args: Sequence[Any] = ()) -> list[Any]:
        with self.reading() as con:
            return con.execute(sql, args).fetchall()

    def close(self) -> None:
        with self.write_lock, self._pool_lock:
            self._closed = True
            while True:
                try:
                    self.pool.get_nowait().close()
                except queue.Empty:
                    break
            self.writer.close()


def holds_store(path: Path) -> bool:
    """Whether the file at ``path`` holds a store (a schema version), read without writing."""
    uri = sqlite_uri(path, "ro")
    try:
        with contextlib.closing(sqlite3.connect(uri, uri=True)) as con:
            sql = "SELECT value FROM meta WHERE key = 'schema_version'"
            return bool(con.execute(sql).fetchall())
    except sqlite3.OperationalError as err:
        if "no such table" not in str(err):
            raise
        return False


def fsync_dir(path: Path) -> None:
    """Make a rename or a new entry in ``path`` durable."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def undo(con: sqlite3.Connection, err: BaseException) -> None:
    """After a failed write: roll its transaction back, unless SQLite already has (it does
    so itself on a full disk or an I/O error, and a second ROLLBACK would raise in place of
    the first error). A full disk becomes an error that says so (503 storage_full), not a
    bare 500."""
    if con.in_transaction:
        con.execute("ROLLBACK")
    full = storage_full(err, "the map's store cannot grow")
    if full is not None:
        raise full from err


def storage_full(err: BaseException, what: str) -> Unavailable | None:
    """The 503 ``storage_full`` for an error that means the disk (or the quota) is full —
    SQLite's or the file system's — else None."""
    sqlite_full = isinstance(err, sqlite3.OperationalError) and "full" in str(err)
    if not sqlite_full and not (
        isinstance(err, OSError) and err.errno in (errno.ENOSPC, errno.EDQUOT)
    ):
        return None
    return Unavailable(  # freeing disk takes an operator: not a retry within the second
        f"{what}: {err}; free disk space under the data folder",
        code="storage_full",
        retry_after_s=30,
    )
