"""The durable store of one map: SQLite in WAL mode, the source of truth.

Every write is one transaction, committed (``synchronous=FULL``: fsynced) before the caller
acknowledges it. Each write takes the next value of the map's sequence number ``seq``;
an insert stamps its row with it, a delete stamps ``deleted_seq`` on the row and keeps it as
a tombstone, so "everything after seq S" — what a FAISS snapshot at S is missing — is two
indexed range scans. Tombstones older than the newest snapshot are purged.

Row ids (``INTEGER PRIMARY KEY AUTOINCREMENT``) are never reused; they are the FAISS ids.

    descriptor  (D,) float32 blob, unit norm — exactly what the encoder gave and the index
                holds. float16 would save 512 B per keyframe and move a descriptor by ~3e-4
                (the validation metrics do not change: benchmarks/loop_threshold.py); the
                store keeps the exact value, the index and the answers never differ
    yaw         (C, W) float16 blob, or NULL when a batch insert sent none (the yaw comes
                from a correlation peak; float16 does not move it)
    geometry    the keyframe's compact geometry (:mod:`overlapmamba.core.geometry`, ≈ 7 KB), or NULL
                for a keyframe inserted as a bare descriptor or into a map that keeps none.
                Written in the same transaction as the descriptor: as durable as it.

    sensor      the sensor of the scan a keyframe came from (a name; NULL: not recorded).

Schema 2 added ``geometry``, schema 3 ``sensor``; an older store gains the columns when
opened for writing.
"""

from __future__ import annotations

import json
import sqlite3
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from overlapmamba.service.backends.faiss.sqlfile import (
    READABLE_VERSIONS,
    SCHEMA,
    SCHEMA_VERSION,
    Connections,
    StoreError,
    holds_store,
    undo,
)
from overlapmamba.service.domain import Keyframe, NewKeyframe

_KF_COLUMNS = (
    "id, keyframe_id, robot_id, session_id, timestamp, pose, content_hash, seq, created_at, sensor"
)
_KF_WIDTH = 10


def _keyframe(row: tuple[Any, ...]) -> Keyframe:
    return Keyframe(
        id=row[0],
        keyframe_id=row[1],
        robot_id=row[2],
        session_id=row[3],
        timestamp=row[4],
        pose=json.loads(row[5]) if row[5] else None,
        content_hash=row[6],
        seq=row[7],
        created_at=row[8],
        sensor=row[9],
    )


def to_f16(features: np.ndarray) -> np.ndarray:
    return np.asarray(features, dtype=np.float16)


def index_vector(blob: bytes) -> np.ndarray:
    return np.frombuffer(blob, dtype=np.float32).copy()


# written into data_dir/maps/.import-<id> once an imported store is whole and on disk
# (overlapmamba.service.backup; FaissBackend.load_all finishes such an import)
IMPORTED_MARK = "imported"


class Store:
    def __init__(self, path: Path, *, readonly: bool = False, new: bool = False) -> None:
        """``readonly``: only read (no schema script, no writes; `overlapmamba doctor`).
        ``new``: create the store (only a map being created does); any other opening
        refuses a file that is missing or holds no store (emptied, overwritten) rather
        than write a new schema over what is left of it."""
        self.path = Path(path)
        self.readonly = readonly
        if readonly:
            if not self.path.is_file():
                raise StoreError(f"{path} does not exist")
            self._file = Connections(self.path, readonly=True)
            version = self.get_meta("schema_version")
            if version is None or int(version) not in READABLE_VERSIONS:
                raise StoreError(
                    f"{path}: schema version {version}; this code reads {READABLE_VERSIONS}"
                )
            return
        if not new:
            self._check_exists()
        self._file = Connections(self.path, create=new)
        with self._file.writer:
            self._file.writer.executescript(SCHEMA)
        version = self.get_meta("schema_version")
        if version is None:
            self.set_meta(schema_version=SCHEMA_VERSION, seq=0)
        elif int(version) in (1, 2):
            self._migrate(int(version))
        elif int(version) != SCHEMA_VERSION:
            raise StoreError(f"{path}: schema version {version}; this code reads {SCHEMA_VERSION}")

    def _check_exists(self) -> None:
        if not self.path.is_file():
            raise StoreError(f"{self.path} does not exist")
        if not holds_store(self.path):
            raise StoreError(
                f"{self.path} holds no map store (no schema version: emptied or overwritten); "
                "nothing was written to it"
            )

    def _migrate(self, version: int) -> None:
        """Add the columns later schemas have (NULL for every existing keyframe), in one
        transaction."""
        added = {2: "geometry BLOB", 3: "sensor TEXT"}
        with self._file.write_lock:
            con = self._file.writer
            con.execute("BEGIN IMMEDIATE")
            try:
                for step in range(version + 1, SCHEMA_VERSION + 1):
                    con.execute(f"ALTER TABLE keyframes ADD COLUMN {added[step]}")
                con.execute(
                    "INSERT OR REPLACE INTO meta(key, value) VALUES ('schema_version', ?)",
                    (str(SCHEMA_VERSION),),
                )
                con.execute("COMMIT")
            except BaseException as err:
                undo(con, err)
                raise

    def close(self) -> None:
        self._file.close()

    # ---- meta -----------------------------------------------------------------------------

    def get_meta(self, key: str) -> str | None:
        rows = self._file.rows("SELECT value FROM meta WHERE key = ?", (key,))
        return rows[0][0] if rows else None

    def set_meta(self, **values: Any) -> None:
        with self._file.write_lock:
            self._file.writer.execute("BEGIN IMMEDIATE")
            try:
                self._file.writer.executemany(
                    "INSERT OR REPLACE INTO meta(key, value) VALUES (?, ?)",
                    [(k, v if isinstance(v, str) else json.dumps(v)) for k, v in values.items()],
                )
                self._file.writer.execute("COMMIT")
            except BaseException as err:
                undo(self._file.writer, err)
                raise

    @property
    def last_seq(self) -> int:
        return int(self.get_meta("seq") or 0)

    # ---- writes ---------------------------------------------------------------------------

    def insert(self, rows: list[NewKeyframe]) -> tuple[list[int], int]:
        """Insert rows in one committed transaction → (their ids, the new seq)."""
        now = time.time()
        with self._file.write_lock:
            con = self._file.writer
            con.execute("BEGIN IMMEDIATE")
            try:
                seq = int(con.execute("SELECT value FROM meta WHERE key='seq'").fetchone()[0]) + 1
                ids = []
                for r in rows:
                    yaw = None if r.yaw is None else to_f16(r.yaw)
                    cur = con.execute(
                        "INSERT INTO keyframes(keyframe_id, robot_id, session_id, timestamp, "
                        "pose, descriptor, yaw, yaw_shape, content_hash, seq, created_at, "
                        "geometry, sensor) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                        (
                            r.keyframe_id,
                            r.robot_id,
                            r.session_id,
                            r.timestamp,
                            None if r.pose is None else json.dumps(r.pose),
                            np.asarray(r.descriptor, dtype=np.float32).tobytes(),
                            None if yaw is None else yaw.tobytes(),
                            None if yaw is None else json.dumps(list(yaw.shape)),
                            r.content_hash,
                            seq,
                            now,
                            r.geometry,
                            r.sensor,
                        ),
                    )
                    ids.append(int(cur.lastrowid or 0))
                con.execute("UPDATE meta SET value = ? WHERE key = 'seq'", (str(seq),))
                con.execute("COMMIT")
            except BaseException as err:
                undo(con, err)
                raise
        return ids, seq

    def delete(self, keyframe_id: str) -> int | None:
        """Tombstone one keyframe → its id, or None if there is no such live keyframe."""
        with self._file.write_lock:
            con = self._file.writer
            con.execute("BEGIN IMMEDIATE")
            try:
                row = con.execute(
                    "SELECT id FROM keyframes WHERE keyframe_id = ?", (keyframe_id,)
                ).fetchone()
                if row is None:
                    con.execute("ROLLBACK")
                    return None
                seq = int(con.execute("SELECT value FROM meta WHERE key='seq'").fetchone()[0]) + 1
                con.execute(
                    "UPDATE keyframes SET keyframe_id = NULL, deleted_keyframe_id = ?, "
                    "deleted_seq = ? WHERE id = ?",
                    (keyframe_id, seq, row[0]),
                )
                con.execute("UPDATE meta SET value = ? WHERE key = 'seq'", (str(seq),))
                con.execute("COMMIT")
            except BaseException as err:
                undo(con, err)
                raise
        return int(row[0])

    def purge_tombstones(self, upto_seq: int) -> int:
        """Drop tombstones that a durable snapshot at ``upto_seq`` already reflects."""
        with self._file.write_lock:
            cur = self._file.writer.execute(
                "DELETE FROM keyframes WHERE deleted_seq IS NOT NULL AND deleted_seq <= ?",
                (upto_seq,),
            )
        return cur.rowcount

    # ---- reads ----------------------------------------------------------------------------

    def count(self) -> int:
        return int(
            self._file.rows("SELECT COUNT(*) FROM keyframes WHERE keyframe_id IS NOT NULL")[0][0]
        )

    def problems(self, limit: int = 5) -> list[str]:
        """What SQLite's ``quick_check`` finds wrong with the file (every page read, the rows
        a start would replay included); empty when it is sound."""
        try:
            found = [r[0] for r in self._file.rows(f"PRAGMA quick_check({int(limit)})")]
        except sqlite3.DatabaseError as err:  # a page it cannot even parse
            return [str(err)]
        return [] if found == ["ok"] else found

    def census(self, at_seq: int) -> tuple[int, int, int]:
        """(last seq, live keyframes, keyframes alive at ``at_seq``), read in one
        transaction: one consistent view even while a service writes."""
        with self._file.reading() as con:
            con.execute("BEGIN")
            try:
                row = con.execute("SELECT value FROM meta WHERE key = 'seq'").fetchone()
                live = con.execute(
                    "SELECT COUNT(*) FROM keyframes WHERE keyframe_id IS NOT NULL"
                ).fetchone()[0]
                at = con.execute(
                    "SELECT COUNT(*) FROM keyframes WHERE seq <= ? "
                    "AND (deleted_seq IS NULL OR deleted_seq > ?)",
                    (at_seq, at_seq),
                ).fetchone()[0]
            finally:
                con.execute("COMMIT")
        return int(row[0]) if row else 0, int(live), int(at)

    def get(self, keyframe_id: str) -> Keyframe | None:
        rows = self._file.rows(
            f"SELECT {_KF_COLUMNS} FROM keyframes WHERE keyframe_id = ?", (keyframe_id,)
        )
        return _keyframe(rows[0]) if rows else None

    def get_many(self, keyframe_ids: list[str]) -> dict[str, Keyframe]:
        out: dict[str, Keyframe] = {}
        for start in range(0, len(keyframe_ids), 500):
            chunk = keyframe_ids[start : start + 500]
            marks = ",".join("?" * len(chunk))
            for row in self._file.rows(
                f"SELECT {_KF_COLUMNS} FROM keyframes WHERE keyframe_id IN ({marks})", chunk
            ):
                kf = _keyframe(row)
                out[kf.keyframe_id] = kf
        return out

    def by_ids(self, ids: list[int]) -> dict[int, tuple[Keyframe, np.ndarray | None]]:
        """Live keyframes, each with its descriptor (``Keyframe.descriptor``), and their yaw
        features (C, W) as stored (float16), by row id."""
        if not ids:
            return {}
        marks = ",".join("?" * len(ids))
        out = {}
        for row in self._file.rows(
            f"SELECT {_KF_COLUMNS}, yaw, yaw_shape, descriptor FROM keyframes "
            f"WHERE id IN ({marks}) AND keyframe_id IS NOT NULL",
            ids,
        ):
            kf = replace(_keyframe(row[:_KF_WIDTH]), descriptor=index_vector(row[_KF_WIDTH + 2]))
            yaw = None
            blob, shape_text = row[_KF_WIDTH], row[_KF_WIDTH + 1]
            if blob is not None:
                shape = tuple(json.loads(shape_text))
                yaw = np.frombuffer(blob, dtype=np.float16).reshape(shape)
            out[kf.id] = (kf, yaw)
        return out

    def geometry(self, keyframe_ids: list[str]) -> dict[str, bytes]:
        """The geometry blobs of those live keyframes that have one."""
        if not keyframe_ids:
            return {}
        marks = ",".join("?" * len(keyframe_ids))
        rows = self._file.rows(
            f"SELECT keyframe_id, geometry FROM keyframes WHERE keyframe_id IN ({marks}) "
            "AND geometry IS NOT NULL",
            keyframe_ids,
        )
        return {r[0]: bytes(r[1]) for r in rows}

    def descriptor(self, keyframe_id: str) -> np.ndarray | None:
        rows = self._file.rows(
            "SELECT descriptor FROM keyframes WHERE keyframe_id = ?", (keyframe_id,)
        )
        return index_vector(rows[0][0]) if rows else None

    def live_rows(
        self, after_seq: int = 0, chunk: int = 20_000, *, upto_seq: int | None = None
    ) -> Iterator[tuple[np.ndarray, np.ndarray, list[tuple[str, str, float]]]]:
        """Rows inserted after ``after_seq`` (and up to ``upto_seq``) that are live — or were
        deleted only after ``upto_seq`` — in chunks:
        ids (n,) int64, vectors (n, D) float32, [(robot, session, timestamp)]."""
        args: tuple[int, ...]
        if upto_seq is None:
            where, args = "seq > ? AND keyframe_id IS NOT NULL", (after_seq,)
        else:
            where = "seq > ? AND seq <= ? AND (deleted_seq IS NULL OR deleted_seq > ?)"
            args = (after_seq, upto_seq, upto_seq)
        with self._file.reading() as con:
            cur = con.execute(
                "SELECT id, descriptor, robot_id, session_id, timestamp FROM keyframes "
                f"WHERE {where} ORDER BY id",
                args,
            )
            while rows := cur.fetchmany(chunk):
                ids = np.array([r[0] for r in rows], dtype=np.int64)
                vecs = np.stack([index_vector(r[1]) for r in rows])
                yield ids, vecs, [(r[2], r[3], r[4]) for r in rows]

    def live_meta(
        self, chunk: int = 50_000
    ) -> Iterator[tuple[np.ndarray, list[tuple[str, str, float]]]]:
        """Every live row's id and (robot, session, timestamp), without the descriptors."""
        with self._file.reading() as con:
            cur = con.execute(
                "SELECT id, robot_id, session_id, timestamp FROM keyframes "
                "WHERE keyframe_id IS NOT NULL ORDER BY id"
            )
            while rows := cur.fetchmany(chunk):
                yield np.array([r[0] for r in rows], np.int64), [(r[1], r[2], r[3]) for r in rows]

    def deleted_after(self, after_seq: int) -> np.ndarray:
        rows = self._file.rows(
            "SELECT id FROM keyframes WHERE deleted_seq > ? AND seq <= ?", (after_seq, after_seq)
        )
        return np.array([r[0] for r in rows], dtype=np.int64)

    def last_keyframe(self, robot_id: str, session_id: str) -> Keyframe | None:
        rows = self._file.rows(
            f"SELECT {_KF_COLUMNS} FROM keyframes WHERE robot_id = ? AND session_id = ? AND "
            # of equal times, the one written last, then the greatest id: as Qdrant's map
            "keyframe_id IS NOT NULL ORDER BY timestamp DESC, created_at DESC, keyframe_id DESC "
            "LIMIT 1",
            (robot_id, session_id),
        )
        return _keyframe(rows[0]) if rows else None

    def positions(self, limit: int) -> list[tuple[str, float, float]]:
        """(robot_id, x, y) of the latest ``limit`` keyframes with a pose."""
        rows = self._file.rows(
            "SELECT robot_id, pose FROM keyframes WHERE keyframe_id IS NOT NULL AND pose IS NOT "
            "NULL ORDER BY timestamp DESC LIMIT ?",
            (int(limit),),
        )
        out = []
        for robot, pose in rows:
            xyz = json.loads(pose)
            out.append((str(robot), float(xyz[0]), float(xyz[1])))
        return out

    def backup(self, dest: Path) -> int:
        """A consistent copy, safe while the service writes (SQLite's online backup); the
        live keyframes the copy holds (not the store's by then)."""
        target = sqlite3.connect(dest)
        try:
            with self._file.reading() as con:
                con.backup(target)
            # a file of its own, not a write-ahead log's: it opens read-only anywhere (a
            # store opened on it for writing goes back to WAL)
            target.execute("PRAGMA journal_mode=DELETE")
            sql = "SELECT COUNT(*) FROM keyframes WHERE keyframe_id IS NOT NULL"
            return int(target.execute(sql).fetchone()[0])
        finally:
            target.close()
