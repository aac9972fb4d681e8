"""Service building blocks without HTTP: bodies, index vs brute force, store, maps, auth,
settings, micro-batcher."""

from __future__ import annotations

import asyncio
import contextlib
import gzip
import hashlib
import os
import struct
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import zstandard
from prometheus_client import generate_latest

from overlapmamba.core.errors import DataTooLargeError
from overlapmamba.service.auth import ROLE_ACTIONS, Action, Authenticator, hash_key
from overlapmamba.service.backends.faiss.backend import FaissBackend
from overlapmamba.service.backends.faiss.index import (
    VectorIndex,
    needs_rebuild,
    search_reference,
    wants_ivf,
)
from overlapmamba.service.backends.faiss.locks import RWLock
from overlapmamba.service.backends.faiss.store import Store
from overlapmamba.service.batcher import MicroBatcher
from overlapmamba.service.domain import Filters, NewKeyframe
from overlapmamba.service.errors import (
    BadRequest,
    Conflict,
    Forbidden,
    NotFound,
    Overloaded,
    PayloadTooLarge,
    Unauthorized,
    UnsupportedMediaType,
    lidar_status,
)
from overlapmamba.service.scans import ScanBody, decode_scan, decompress, scan_format
from overlapmamba.service.settings import AuthSettings, IndexSettings, Settings, load_settings

D = 32


def unit(rng: np.random.Generator, n: int, d: int = D) -> np.ndarray:
    x = rng.normal(size=(n, d)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def places(rng: np.random.Generator, n: int, d: int = D, per_place: int = 5) -> np.ndarray:
    centres = unit(rng, max(1, n // per_place), d)
    x = centres[rng.integers(0, len(centres), n)] + 0.08 * rng.normal(size=(n, d))
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def row(i: int, vec: np.ndarray, robot: str = "r1", session: str = "s1", ts: float | None = None):
    return NewKeyframe(
        keyframe_id=f"kf{i}",
        robot_id=robot,
        session_id=session,
        timestamp=float(i if ts is None else ts),
        pose=None,
        descriptor=vec,
        yaw=None,
        content_hash=hashlib.sha256(vec.tobytes()).hexdigest(),
    )


# ---- bodies ---------------------------------------------------------------------------------


def test_decompress_gzip_and_zstd_round_trip():
    data = np.arange(5000, dtype="<f4").tobytes()
    assert decompress(gzip.compress(data), "gzip", 1 << 20) == data
    assert decompress(zstandard.ZstdCompressor().compress(data), "zstd", 1 << 20) == data
    assert decompress(data, None, 1 << 20) == data


@pytest.mark.parametrize("enc", ["gzip", "zstd"])
def test_decompression_bomb_is_stopped_at_the_limit(enc):
    bomb_src = bytes(50 << 20)  # 50 MB of zeros → a few kB compressed
    body = (
        gzip.compress(bomb_src) if enc == "gzip" else zstandard.ZstdCompressor().compress(bomb_src)
    )
    assert len(body) < 1 << 20
    with pytest.raises(PayloadTooLarge, match="decompresses to more than"):
        decompress(body, enc, 1 << 20)


def test_bad_encodings_and_types_are_named():
    with pytest.raises(BadRequest, match="truncated"):
        decompress(gzip.compress(b"x" * 1000)[:-8], "gzip", 1 << 20)
    with pytest.raises(BadRequest, match="one gzip member"):
        decompress(gzip.compress(b"ab") + gzip.compress(b"cd"), "gzip", 1 << 20)
    frame = zstandard.ZstdCompressor().compress(bytes(range(256)) * 100)
    with pytest.raises(BadRequest, match="truncated"):  # a cut frame is not a shorter scan
        decompress(frame[: len(frame) // 2], "zstd", 1 << 20)
    with pytest.raises(BadRequest, match="one zstd frame"):
        decompress(frame + frame, "zstd", 1 << 20)
    # a frame that does not declare its size is counted as it decompresses: over the limit
    # is a bomb (413), like gzip's; within it, the body comes back whole
    unsized = zstandard.ZstdCompressor(write_content_size=False).compress(bytes(4 << 20))
    with pytest.raises(PayloadTooLarge, match="decompresses to more than 1048576 bytes"):
        decompress(unsized, "zstd", 1 << 20)
    assert decompress(unsized, "zstd", 4 << 20) == bytes(4 << 20)
    with pytest.raises(BadRequest, match="does not decompress"):
        decompress(b"not gzip", "gzip", 1 << 20)
    with pytest.raises(UnsupportedMediaType, match="allowed: identity, gzip, zstd"):
        decompress(b"x", "br", 1 << 20)
    with pytest.raises(UnsupportedMediaType, match="never a JSON list"):
        scan_format("application/json")
    assert scan_format("application/x-pcd; charset=binary") == "pcd"


# ---- index against brute force ------------------------------------------------------------------


def _recall(index: VectorIndex, vecs, ids, queries, k=10):
    hits = 0
    for q in queries:
        _, got = index.search(q, k)
        _, want = search_reference(vecs, ids, q, k)
        hits += len(set(got) & set(want))
    return hits / (k * len(queries))


def test_flat_index_is_exact_and_removes():
    rng = np.random.default_rng(0)
    vecs = places(rng, 2000)
    ids = rng.permutation(10_000)[:2000].astype(np.int64)
    index = VectorIndex.flat(D)
    index.add(ids, vecs)
    queries = places(rng, 20)
    for q in queries:
        sims, got = index.search(q, 10)
        ref_sims, want = search_reference(vecs, ids, q, 10)
        np.testing.assert_allclose(sims, ref_sims, rtol=1e-5, atol=1e-5)
        assert list(got) == list(want)
    gone = ids[:500]
    assert index.remove(gone) == 500
    for q in queries:
        _, got = index.search(q, 10)
        _, want = search_reference(vecs[500:], ids[500:], q, 10)
        assert list(got) == list(want)


def test_near_identical_descriptors_keep_their_distances():
    # Re-visits of one place can lie ~1e-3 apart: an inner-product index would measure
    # √(2 − 2·x·y) with ≈3e-4 of float32 cancellation error, 30 % of such a distance.
    rng = np.random.default_rng(7)
    base = unit(rng, 1, 256)[0]
    vecs = base + 1e-3 * rng.normal(size=(500, 256)) / np.sqrt(256)
    vecs = (vecs / np.linalg.norm(vecs, axis=1, keepdims=True)).astype(np.float32)
    ids = np.arange(500, dtype=np.int64)
    index = VectorIndex.flat(256)
    index.add(ids, vecs)
    for q in vecs[:20]:
        dist, got = index.search(q, 10)
        ref, want = search_reference(vecs, ids, q, 10)
        np.testing.assert_allclose(dist[1:], ref[1:], rtol=1e-3)
        assert list(got) == list(want)


def test_ivf_index_recall_and_deletes():
    rng = np.random.default_rng(1)
    vecs = places(rng, 5000)
    ids = np.arange(5000, dtype=np.int64)
    index = VectorIndex.ivf(vecs, nprobe=16)
    index.add(ids, vecs)
    # revisits: noisy views of stored places; their nearest keyframe is found
    queries = vecs[rng.integers(0, 5000, 50)] + 0.03 * rng.normal(size=(50, D)).astype(np.float32)
    queries /= np.linalg.norm(queries, axis=1, keepdims=True)
    for q in queries:
        assert index.search(q, 1)[1][0] == search_reference(vecs, ids, q, 1)[1][0]
    # probing every list is exhaustive, hence exact (recall/latency trade-off: benchmarks/)
    assert _recall(index, vecs, ids, queries) < 1.0 or index.nprobe >= index.nlist
    index.nprobe = index.nlist
    assert _recall(index, vecs, ids, queries) == 1.0
    index.nprobe = 16
    assert index.remove(ids[:1000]) == 1000
    assert index.ntotal == 4000
    for q in queries[:10]:
        _, got = index.search(q, 10)
        assert not set(got) & set(ids[:1000].tolist())
    copy = VectorIndex.deserialize(index.serialize(), "ivf", nprobe=16)
    for q in queries[:5]:
        assert list(copy.search(q, 10)[1]) == list(index.search(q, 10)[1])


@pytest.mark.parametrize("kind", ["flat", "ivf"])
def test_filtered_search_returns_k_whenever_k_are_eligible(kind):
    rng = np.random.default_rng(2)
    vecs = places(rng, 3000)
    ids = np.arange(3000, dtype=np.int64)
    index = VectorIndex.flat(D) if kind == "flat" else VectorIndex.ivf(vecs, nprobe=1)
    index.add(ids, vecs)
    q = vecs[0]
    allowed = np.zeros(3000, bool)
    far = np.argsort(vecs @ q)[:12]  # the 12 least similar: surely outside the probed list
    allowed[far] = True
    _sims, got = index.search(q, 10, allowed)
    _ref_sims, want = search_reference(vecs[far], ids[far], q, 10)
    assert len(got) == 10
    assert list(got) == list(want)
    _, got = index.search(q, 50, allowed)
    assert sorted(got) == sorted(far.tolist())  # k > eligible: every eligible one
    assert len(index.search(q, 5, np.zeros(3000, bool))[1]) == 0


def test_an_ivf_map_shrunk_by_deletes_still_returns_k():
    """Found in review: a map whose lists were sized for 3000 keyframes, 2900 of them deleted,
    probed a few mostly empty lists and answered an unfiltered query with fewer than k
    (only the filtered search was repeated over every list)."""
    rng = np.random.default_rng(4)
    vecs = places(rng, 3000)
    ids = np.arange(3000, dtype=np.int64)
    index = VectorIndex.ivf(vecs, nprobe=2)
    index.add(ids, vecs)
    assert index.remove(ids[100:]) == 2900
    for q in vecs[:20]:
        _, got = index.search(q, 50)
        _, want = search_reference(vecs[:100], ids[:100], q, 50)
        assert list(got) == list(want)


# ---- store and maps ------------------------------------------------------------------------


def test_store_sequences_tombstones_and_replay_queries(tmp_path):
    rng = np.random.default_rng(3)
    store = Store(tmp_path / "s.sqlite", new=True)
    vecs = unit(rng, 6)
    ids, seq = store.insert([row(i, vecs[i]) for i in range(4)])
    assert seq == 1 and len(set(ids)) == 4
    ids2, seq = store.insert([row(i, vecs[i]) for i in (4, 5)])
    assert seq == 2
    assert store.delete("kf1") == ids[1]
    assert store.delete("kf1") is None
    assert store.last_seq == 3 and store.count() == 5
    after1 = np.concatenate([i for i, _, _ in store.live_rows(1)])
    assert list(after1) == ids2
    assert list(store.deleted_after(1)) == [ids[1]]
    # a re-insert after delete gets a new row id: FAISS ids are never reused
    new_ids, _ = store.insert([row(1, vecs[0])])
    assert new_ids[0] not in ids + ids2
    assert store.purge_tombstones(3) == 1
    v = store.descriptor("kf0")
    np.testing.assert_allclose(v, vecs[0], atol=1e-7)
    store.close()


def test_a_read_returning_its_connection_as_the_store_closes_leaves_none_open(tmp_path):
    """A reader's connection goes back to the pool, or is closed, in one step against
    close(): a close() that ran between the reader's look and its return left the connection
    pooled after the close, open on a file its map may have deleted. Reads after close()
    are refused by name."""
    import queue
    import sqlite3
    import threading

    from overlapmamba.service.backends.faiss.sqlfile import StoreError

    store = Store(tmp_path / "s.sqlite", new=True)
    returned: list[sqlite3.Connection] = []
    closing = threading.Thread(target=store.close)

    class Pool:  # the store's pool, with close() started as a reader returns to it
        def __init__(self, pool) -> None:
            self.pool = pool

        def get_nowait(self) -> sqlite3.Connection:
            return self.pool.get_nowait()

        def put(self, con: sqlite3.Connection) -> None:
            if not returned:
                closing.start()
                closing.join(0.3)  # the old code let close() finish here, before the return
            returned.append(con)
            self.pool.put(con)

    store._file.pool = Pool(store._file.pool)  # type: ignore[assignment]
    assert store.get_meta("schema_version") is not None
    closing.join(5)
    assert not closing.is_alive() and len(returned) == 1
    with pytest.raises(queue.Empty):
        store._file.pool.get_nowait()  # nothing pooled after close()
    with pytest.raises(sqlite3.ProgrammingError, match="closed"):
        returned[0].execute("SELECT 1")  # closed with the store, not left open
    with pytest.raises(StoreError, match="is closed"):
        store.get_meta("schema_version")


def test_a_reader_never_creates_the_store_file_a_deletion_moved_away(tmp_path):
    """Only the writer opened at start may create the store's file: a reader's new
    connection to a store whose file went away (its map deleted under it) is an error, not
    a new empty database at the old path."""
    import queue
    import sqlite3

    store = Store(tmp_path / "s.sqlite", new=True)
    with contextlib.suppress(queue.Empty):
        while True:  # no pooled reader left: the next read opens a connection of its own
            store._file.pool.get_nowait().close()
    (tmp_path / "s.sqlite").rename(tmp_path / "moved.sqlite")
    with pytest.raises(sqlite3.OperationalError, match="unable to open"):
        store.get_meta("schema_version")
    assert not (tmp_path / "s.sqlite").exists()
    store.close()


def test_store_keeps_geometry_and_upgrades_a_schema_1_store(tmp_path):
    """Geometry is written with its row; a store of schema 1 (no geometry column) opens,
    gains the column in one step, keeps its rows, and reads as having no geometry."""
    import dataclasses
    import sqlite3

    from overlapmamba.service.backends.faiss.sqlfile import SCHEMA_VERSION

    rng = np.random.default_rng(4)
    vecs = unit(rng, 3)
    store = Store(tmp_path / "s.sqlite", new=True)
    store.insert([dataclasses.replace(row(0, vecs[0]), geometry=b"OMG1-blob"), row(1, vecs[1])])
    assert store.geometry(["kf0", "kf1", "nope"]) == {"kf0": b"OMG1-blob"}
    store.close()

    old = tmp_path / "old.sqlite"
    con = sqlite3.connect(old)
    con.executescript(
        "CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);"
        "CREATE TABLE keyframes (id INTEGER PRIMARY KEY AUTOINCREMENT, keyframe_id TEXT UNIQUE,"
        " deleted_keyframe_id TEXT, robot_id TEXT NOT NULL, session_id TEXT NOT NULL,"
        " timestamp REAL NOT NULL, pose TEXT, descriptor BLOB NOT NULL, yaw BLOB,"
        " yaw_shape TEXT, content_hash TEXT NOT NULL, seq INTEGER NOT NULL,"
        " deleted_seq INTEGER, created_at REAL NOT NULL);"
        "INSERT INTO meta VALUES ('schema_version', '1'), ('seq', '1');"
    )
    con.execute(
        "INSERT INTO keyframes(keyframe_id, robot_id, session_id, timestamp, descriptor, "
        "content_hash, seq, created_at) VALUES ('kf9', 'r1', 's1', 9.0, ?, 'h', 1, 0.0)",
        (vecs[2].tobytes(),),
    )
    con.commit()
    con.close()
    ro = Store(old, readonly=True)
    assert ro.count() == 1  # doctor reads schema 1 as it is
    ro.close()
    store = Store(old)
    assert store.get_meta("schema_version") == str(SCHEMA_VERSION) and store.count() == 1
    assert store.geometry(["kf9"]) == {}
    store.insert([dataclasses.replace(row(0, vecs[0]), geometry=b"g")])
    assert store.geometry(["kf0", "kf9"]) == {"kf0": b"g"}
    store.close()


def _registry(root: Path, **index: object) -> FaissBackend:
    r = FaissBackend(root, IndexSettings(**index), model_id="m1", dim=D)
    r.load_all()
    return r


def test_faiss_threads_follow_the_setting_and_bad_counts_are_refused(tmp_path):
    import faiss
    from pydantic import ValidationError

    before = faiss.omp_get_max_threads()
    try:
        _registry(tmp_path / "a", threads=2).close()
        assert faiss.omp_get_max_threads() == 2
        _registry(tmp_path / "b").close()  # the default: one thread per query
        assert faiss.omp_get_max_threads() == 1
    finally:
        faiss.omp_set_num_threads(before)
    for bad in (0, -1, 1000):
        with pytest.raises(ValidationError, match="threads"):
            IndexSettings(threads=bad)


def test_map_snapshot_and_replay_after_unsnapshotted_writes(tmp_path):
    rng = np.random.default_rng(4)
    vecs = unit(rng, 300)
    reg = _registry(tmp_path)
    m, created = reg.create("town", "flat")
    assert created and reg.create("town", "flat")[1] is False
    with pytest.raises(Conflict):
        reg.create("town", "ivf")
    m.insert([row(i, vecs[i]) for i in range(200)])
    assert m.snapshot()["seq"] == 1
    m.insert([row(i, vecs[i]) for i in range(200, 300)])  # after the snapshot
    m.delete("kf5")  # in the snapshot, deleted after it
    m.delete("kf250")  # inserted and deleted after it
    reg.close(snapshot=False)  # a crash: no final snapshot

    reg = _registry(tmp_path)
    m = reg.get("town")
    assert m.index.ntotal == m.store.count() == 298
    for i in (0, 199, 200, 299):
        (best,) = m.search(vecs[i], 1, Filters())
        assert best.keyframe.keyframe_id == f"kf{i}"
    for i in (5, 250):
        assert all(x.keyframe.keyframe_id != f"kf{i}" for x in m.search(vecs[i], 5, Filters()))
    # a damaged snapshot costs a rebuild, never data
    (m.folder / "index.snap").write_bytes(b"garbage")
    reg.close(snapshot=False)
    reg = _registry(tmp_path)
    assert reg.get("town").index.ntotal == 298
    reg.delete("town")
    assert not (tmp_path / "maps" / "town").exists()
    with pytest.raises(BadRequest, match="allowed"):
        reg.get("Bad Id")


def test_index_kind_policy():
    """Which index a map calls for: IVF for `ivf`, and for `auto` above its threshold, never
    under 64 vectors; an index of the other kind, or IVF grown to twice its lists, is rebuilt."""
    assert not wants_ivf("flat", 10_000, 400)
    assert wants_ivf("ivf", 64, 400) and not wants_ivf("ivf", 63, 400)
    assert not wants_ivf("auto", 400, 400) and wants_ivf("auto", 401, 400)
    assert not wants_ivf("auto", 63, 10)
    rng = np.random.default_rng(3)
    flat = VectorIndex.flat(8)
    assert not needs_rebuild(flat, ivf=False) and needs_rebuild(flat, ivf=True)
    vecs = places(rng, 400, d=8)
    ivf = VectorIndex.ivf(vecs)
    ivf.add(np.arange(400, dtype=np.int64), vecs)
    assert needs_rebuild(ivf, ivf=False) and not needs_rebuild(ivf, ivf=True)
    assert ivf.nlist == 10  # 400 // 39: 780 vectors want twice as many lists
    more = places(rng, 380, d=8)
    ivf.add(np.arange(400, 779, dtype=np.int64), more[:379])
    assert not needs_rebuild(ivf, ivf=True)
    ivf.add(np.array([779], dtype=np.int64), more[379:])
    assert needs_rebuild(ivf, ivf=True)


def test_auto_map_switches_to_ivf_and_keeps_deletes(tmp_path):
    rng = np.random.default_rng(5)
    vecs = places(rng, 600)
    reg = _registry(tmp_path, approximate_above=400, snapshot_every=10_000)
    m, _ = reg.create("big", "auto")
    m.insert([row(i, vecs[i]) for i in range(300)])
    assert not m.wants_rebuild()
    m.insert([row(i, vecs[i]) for i in range(300, 600)])
    assert m.wants_rebuild()
    m.rebuild()
    assert m.index.kind == "ivf" and m.index.ntotal == 600
    m.delete("kf7")
    assert m.index.ntotal == 599
    (best,) = m.search(vecs[8], 1, Filters())
    assert best.keyframe.keyframe_id == "kf8"
    m.snapshot()
    reg.close(snapshot=False)
    m = _registry(tmp_path, approximate_above=400).get("big")
    assert m.index.kind == "ivf" and m.index.ntotal == 599


def test_map_filters_and_idempotent_inserts(tmp_path):
    rng = np.random.default_rng(6)
    vecs = unit(rng, 40)
    m, _ = _registry(tmp_path).create("f", "flat")
    rows = [row(i, vecs[i], robot=f"r{i % 2}", session=f"s{i % 4}", ts=i) for i in range(40)]
    assert all(r.created for r in m.insert(rows))
    assert not any(r.created for r in m.insert(rows[:3]))  # same content: the original
    changed = row(0, vecs[1])
    with pytest.raises(Conflict, match="different content"):
        m.insert([row(99, vecs[0]), changed])
    assert m.store.get("kf99") is None  # nothing partial
    q = vecs[0]
    got = m.search(q, 40, Filters(exclude_robot="r0"))
    assert len(got) == 20 and {x.keyframe.robot_id for x in got} == {"r1"}
    got = m.search(q, 40, Filters(exclude_session="s1", time_from=10, time_to=29))
    assert len(got) == 15 and all(10 <= x.keyframe.timestamp <= 29 for x in got)
    got = m.search(q, 40, Filters(exclude_recent_s=10, session_id="s0", timestamp=39))
    assert not [x for x in got if x.keyframe.session_id == "s0" and x.keyframe.timestamp > 29]
    assert len(got) == 40 - 2  # s0 holds 0, 4, …, 36: only 32 and 36 are within 10 s of 39
    with pytest.raises(BadRequest, match="needs the query's session_id"):
        m.search(q, 5, Filters(exclude_recent_s=10))
    assert all(x.distance <= 1.0 for x in m.search(q, 40, Filters(max_match_distance=1.0)))


def test_small_ivf_maps_do_not_rebuild_after_every_write(tmp_path):
    rng = np.random.default_rng(8)
    vecs = places(rng, 500)
    m, _ = _registry(tmp_path).create("small", "ivf")
    rebuilds = 0
    for i in range(0, 500, 10):
        m.insert([row(j, vecs[j]) for j in range(i, i + 10)])
        if m.wants_rebuild():
            m.rebuild()
            rebuilds += 1
            assert not m.wants_rebuild()
    assert m.index.kind == "ivf" and rebuilds <= 6  # on doubling, not on every write


def test_a_deleted_map_refuses_requests_that_still_hold_it(tmp_path):
    rng = np.random.default_rng(9)
    reg = _registry(tmp_path)
    m, _ = reg.create("gone", "flat")
    m.insert([row(0, unit(rng, 1)[0])])
    reg.delete("gone")
    with pytest.raises(NotFound):
        m.search(unit(rng, 1)[0], 1, Filters())
    with pytest.raises(NotFound):
        m.insert([row(1, unit(rng, 1)[0])])
    m.rebuild()  # background maintenance on a deleted map does nothing


def test_store_reader_connections_are_pooled_not_per_thread(tmp_path):
    import threading

    store = Store(tmp_path / "s.sqlite", new=True)
    for _ in range(30):  # short-lived threads, as a thread pool makes them
        t = threading.Thread(target=store.count)
        t.start()
        t.join()
    assert store._file.pool.qsize() == 1
    store.close()


def test_rwlock_lets_readers_share_and_writers_exclude():
    """Two readers hold the lock at once; a writer waits for both and holds it alone; a
    reader arriving while a writer waits queues behind it (no writer starvation). Each wait
    is bounded, so a broken lock fails the test instead of hanging it."""
    import threading

    lock = RWLock()
    inside: list[str] = []
    both_in = threading.Barrier(2, timeout=5)

    def reader(name: str) -> None:
        with lock.read():
            inside.append(f"+{name}")
            both_in.wait()  # only passes if both readers are inside together
            inside.append(f"-{name}")

    readers = [threading.Thread(target=reader, args=(n,)) for n in ("r1", "r2")]
    for t in readers:
        t.start()
    for t in readers:
        t.join(5)
    assert not any(t.is_alive() for t in readers)
    assert sorted(inside[:2]) == ["+r1", "+r2"] and len(inside) == 4  # both in at once

    events: list[str] = []
    reader_in, writer_waiting = threading.Event(), threading.Event()

    def holder() -> None:
        with lock.read():
            reader_in.set()
            assert writer_waiting.wait(5)
            time.sleep(0.05)  # the writer is blocked behind this reader meanwhile
            events.append("reader out")

    def writer() -> None:
        assert reader_in.wait(5)
        writer_waiting.set()
        with lock.write():
            events.append("writer in")
            time.sleep(0.05)
            events.append("writer out")

    def late_reader() -> None:
        assert writer_waiting.wait(5)
        time.sleep(0.02)  # arrives while the writer waits: it must queue behind the writer
        with lock.read():
            events.append("late reader in")

    threads = [threading.Thread(target=f) for f in (holder, writer, late_reader)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(5)
    assert not any(t.is_alive() for t in threads), events
    assert events == ["reader out", "writer in", "writer out", "late reader in"]


def test_writers_that_follow_one_another_never_hold_a_reader_off():
    """Three clients inserting back to back: one writer was nearly always waiting, and any
    waiting writer kept readers out, so a snapshot, a rebuild or a search waited until the
    writes stopped (3.8 s of 4 in review). The readers queued behind a write go in before
    the next one."""
    import threading

    lock = RWLock()
    stop = threading.Event()
    writes = [0]

    def writer() -> None:
        while not stop.is_set():
            with lock.write():
                writes[0] += 1
                time.sleep(0.002)

    writers = [threading.Thread(target=writer) for _ in range(3)]
    for t in writers:
        t.start()
    waited: list[float] = []

    def reader() -> None:
        for _ in range(5):
            t0 = time.monotonic()
            with lock.read():
                waited.append(time.monotonic() - t0)
            time.sleep(0.01)

    try:
        time.sleep(0.1)
        searches = threading.Thread(target=reader)
        searches.start()
        searches.join(3)  # with the writers still writing
        alone = len(waited)
        before = writes[0]
        time.sleep(0.1)
        assert writes[0] > before  # and the writers go on
    finally:
        stop.set()
        for t in [*writers, searches]:
            t.join(5)
    assert alone == 5, waited  # every read done while the writers still wrote


# ---- auth and settings -----------------------------------------------------------------------


def test_roles_and_keys():
    keys = [
        {"name": n, "role": n, "sha256": hash_key(f"key-{n}")}
        for n in ("mapper", "viewer", "admin")
    ]
    keys.append({"name": "robot", "role": "robot", "sha256": hash_key("key-robot"), "maps": ["a"]})
    auth = Authenticator(AuthSettings.model_validate({"keys": keys}))
    with pytest.raises(Unauthorized):
        auth.identify(None)
    with pytest.raises(Unauthorized):
        auth.identify("nope")
    for role, actions in ROLE_ACTIONS.items():
        who = auth.identify(f"key-{role}")
        assert who.role == role
        for action in Action:
            if action in actions:
                auth.authorize(who, action, "a")
            else:
                with pytest.raises(Forbidden, match="allowed roles"):
                    auth.authorize(who, action, "a")
    with pytest.raises(Forbidden, match="may insert into maps"):
        auth.authorize(auth.identify("key-robot"), Action.INSERT, "b")
    assert Authenticator(AuthSettings()).identify(None).role == "admin"
    # one key under two names (and roles): which it gets would be the list's order
    twice = [*keys, {"name": "night", "role": "viewer", "sha256": hash_key("key-admin")}]
    with pytest.raises(ValueError, match="'admin' and 'night' have the same sha256"):
        AuthSettings.model_validate({"keys": twice})
    # maps on a mapper limits nothing: refused rather than trusted
    mapper = {"name": "m", "role": "mapper", "sha256": hash_key("m"), "maps": ["town"]}
    with pytest.raises(ValueError, match="maps applies to robot keys only"):
        AuthSettings.model_validate({"keys": [mapper]})
    mapper = {"name": "m", "role": "mapper", "sha256": hash_key("m"), "query_maps": ["town"]}
    with pytest.raises(ValueError, match="query_maps applies to robot keys only"):
        AuthSettings.model_validate({"keys": [mapper]})
    # without maps a robot may insert into, and so query, any map: query_maps would be void
    loose = {"name": "r", "role": "robot", "sha256": hash_key("r"), "query_maps": ["town"]}
    with pytest.raises(ValueError, match="allowed: query_maps with maps"):
        AuthSettings.model_validate({"keys": [loose]})


def test_a_robot_key_queries_only_its_maps_where_query_maps_says_so():
    """Two sites on one service: ``maps`` limited a robot's inserts, but it could query,
    observe and stream against any map (another site's keyframe poses). ``query_maps``
    limits those to the maps named and the ones it may insert into; unset, any map."""
    keys = [
        {"name": "open", "role": "robot", "sha256": hash_key("k-open"), "maps": ["a-live"]},
        {
            "name": "site-a",
            "role": "robot",
            "sha256": hash_key("k-a"),
            "maps": ["a-live"],
            "query_maps": ["a-base"],
        },
        {"name": "m", "role": "mapper", "sha256": hash_key("k-m")},
    ]
    auth = Authenticator(AuthSettings.model_validate({"keys": keys}))
    site_a, open_, mapper = (auth.identify(k) for k in ("k-a", "k-open", "k-m"))
    for m in ("a-base", "a-live"):
        auth.authorize(site_a, Action.ENCODE, m)
    with pytest.raises(Forbidden, match=r"may query maps \['a-base', 'a-live'\], not 'b'"):
        auth.authorize(site_a, Action.ENCODE, "b")
    auth.authorize(site_a, Action.ENCODE)  # a descriptor names no map
    for who in (open_, mapper):
        auth.authorize(who, Action.ENCODE, "b")
    with pytest.raises(Forbidden, match="may insert into maps"):
        auth.authorize(site_a, Action.INSERT, "a-base")


def test_settings_from_env_file_and_binding(tmp_path, monkeypatch):
    cfg = tmp_path / "s.toml"
    cfg.write_text("port = 9001\n[batching]\nmax_batch = 3\n[limits]\nmax_points = 5000\n")
    monkeypatch.setenv("OVERLAPMAMBA_BATCHING__MAX_WAIT_MS", "7")
    monkeypatch.delenv("OVERLAPMAMBA_CONFIG", raising=False)

    class Watched(dict):  # the process environment, every write recorded
        def __init__(self, *a):
            super().__init__(*a)
            self.writes: list[str] = []

        def __setitem__(self, k, v):
            self.writes.append(k)
            super().__setitem__(k, v)

        def __delitem__(self, k):
            self.writes.append(k)
            super().__delitem__(k)

    env = Watched(os.environ)
    monkeypatch.setattr(os, "environ", env)
    s = load_settings(cfg, host="127.0.0.1")
    assert (s.port, s.batching.max_batch, s.batching.max_wait_ms) == (9001, 3, 7.0)
    assert s.limits.max_points == 5000
    assert env.writes == []  # the file is read without writing the environment
    monkeypatch.undo()
    monkeypatch.setenv("OVERLAPMAMBA_BATCHING__MAX_WAIT_MS", "7")
    assert Settings().port != 9001  # and a later Settings() does not see it
    other = tmp_path / "o.toml"
    other.write_text("port = 9002\n")
    monkeypatch.setenv("OVERLAPMAMBA_CONFIG", str(other))
    assert load_settings(cfg).port == 9001 and Settings().port == 9002  # --config wins
    with pytest.raises(ValueError, match="does not exist"):
        load_settings(tmp_path / "missing.toml")
    with pytest.raises(ValueError, match="without API keys"):
        Settings(host="0.0.0.0").check_binding()
    Settings(host="0.0.0.0", insecure=True).check_binding()
    Settings(host="::1").check_binding()
    with pytest.raises(ValueError):
        Settings(batching={"max_batch": 0})
    # inf is a TOML literal: as a bound it would reach /readyz's JSON, as a timeout an int()
    inf = tmp_path / "inf.toml"
    inf.write_text("[verify]\nmax_rmse_m = inf\n")
    with pytest.raises(ValueError, match="verify.max_rmse_m"):
        load_settings(inf)
    monkeypatch.setenv("OVERLAPMAMBA_LIMITS__REQUEST_TIMEOUT_S", "inf")
    with pytest.raises(ValueError, match="limits.request_timeout_s"):
        Settings()
    monkeypatch.delenv("OVERLAPMAMBA_LIMITS__REQUEST_TIMEOUT_S")
    # a config named by the environment that is not there is an error, not the defaults
    monkeypatch.setenv("OVERLAPMAMBA_CONFIG", str(tmp_path / "typo.toml"))
    with pytest.raises(ValueError, match="typo.toml .*cannot be read"):
        Settings()
    monkeypatch.delenv("OVERLAPMAMBA_CONFIG")
    monkeypatch.setenv("OVERLAPMAMBA_SENSORS__FILES", "a.toml")  # not JSON: named, with how
    with pytest.raises(ValueError, match=r"OVERLAPMAMBA_SENSORS__FILES cannot be read.*JSON"):
        load_settings()
    monkeypatch.delenv("OVERLAPMAMBA_SENSORS__FILES")
    broken = tmp_path / "broken.toml"
    broken.write_text("[verify\nmin_fitness = 0.5\n")
    with pytest.raises(ValueError, match="broken.toml is not valid TOML"):
        load_settings(broken)


# ---- micro-batcher ---------------------------------------------------------------------------


def _encode(images: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    time.sleep(0.02)  # a real encoder takes time; batches fill meanwhile
    b = images.shape[0]
    yaw = images[:, 0, :2].copy()
    yaw[:, 0, 0] = offsets  # each row's offset, where the caller can see it
    return images.reshape(b, -1)[:, :4].copy(), yaw


def test_batcher_batches_concurrent_requests_in_order():
    async def main():
        sizes: Counter[int] = Counter()
        mb = MicroBatcher(
            _encode,
            max_batch=4,
            max_wait_ms=5,
            queue_size=64,
            on_batch=lambda n, _s: sizes.update([n]),
        )
        await mb.start()
        images = [np.full((1, 2, 3), i, np.float32) for i in range(12)]
        out = await asyncio.gather(*(mb.encode(x, i / 100) for i, x in enumerate(images)))
        await mb.stop()
        return out, sizes

    out, sizes = asyncio.run(main())
    for i, (desc, yaw) in enumerate(out):
        assert desc[0] == i  # every caller gets its own row back
        assert yaw[0, 0] == pytest.approx(i / 100)  # and its offset went with its image
    assert sum(k * v for k, v in sizes.items()) == 12
    assert max(sizes) > 1 and max(sizes) <= 4


def test_stopping_the_batcher_answers_every_scan_still_waiting():
    """At shutdown the scans in the batch cut off and those queued behind it are answered
    Unavailable at once, not left to wait out their callers' timeouts."""
    import threading

    from overlapmamba.service.errors import Unavailable

    release = threading.Event()

    def slow(images: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        release.wait(5)  # the batch under way when the service stops
        return _encode(images, offsets)

    async def main() -> list[BaseException | tuple[np.ndarray, np.ndarray]]:
        mb = MicroBatcher(slow, max_batch=1, max_wait_ms=1)
        await mb.start()
        image = np.zeros((1, 2, 3), np.float32)
        calls = [asyncio.create_task(mb.encode(image, timeout_s=30)) for _ in range(3)]
        await asyncio.sleep(0.1)  # one batch under way, two scans queued
        stopping = asyncio.create_task(mb.stop())
        await asyncio.sleep(0.1)
        release.set()  # the cut-off batch's thread ends; the pool shuts down
        await asyncio.wait_for(stopping, 10)
        return await asyncio.wait_for(asyncio.gather(*calls, return_exceptions=True), 5)

    t0 = time.monotonic()
    answers = asyncio.run(main())
    assert all(isinstance(a, Unavailable) for a in answers), answers
    assert time.monotonic() - t0 < 10


def test_stopping_the_batcher_answers_a_scan_whose_batch_is_still_filling():
    """A lane holds a scan while it waits (max_wait_ms) for another announced one: stopping
    then answers that scan Unavailable too, not after its caller's timeout."""
    from overlapmamba.service.errors import Unavailable

    async def main() -> BaseException | tuple[np.ndarray, np.ndarray]:
        mb = MicroBatcher(_encode, max_batch=4, max_wait_ms=20_000)
        await mb.start()
        with mb.incoming():  # another scan on its way: the lane's batch waits to fill
            call = asyncio.create_task(mb.encode(np.zeros((1, 2, 3), np.float32), timeout_s=30))
            await asyncio.sleep(0.1)
            await asyncio.wait_for(mb.stop(), 10)
        return (await asyncio.wait_for(asyncio.gather(call, return_exceptions=True), 5))[0]

    assert isinstance(asyncio.run(main()), Unavailable)


def test_batcher_waits_only_for_scans_on_their_way():
    """A lone scan is encoded at once; a batch waits (up to max_wait_ms) for a scan that
    another caller is still decoding, announced with incoming()."""

    async def main() -> tuple[list[int], list[int]]:
        sizes: list[int] = []
        mb = MicroBatcher(
            _encode, max_batch=4, max_wait_ms=2000, on_batch=lambda n, _s: sizes.append(n)
        )
        await mb.start()
        image = np.zeros((1, 2, 3), np.float32)

        async def late(announced: bool):  # a second scan that is ready 0.2 s later
            if announced:
                with mb.incoming():
                    await asyncio.sleep(0.2)
            else:
                await asyncio.sleep(0.2)
            return await mb.encode(image)

        await asyncio.gather(mb.encode(image), late(announced=False))
        alone = list(sizes)
        sizes.clear()
        await asyncio.gather(mb.encode(image), late(announced=True))
        await mb.stop()
        return alone, sizes

    alone, together = asyncio.run(main())
    assert alone == [1, 1]  # nobody announced: the first did not wait 2 s for the second
    assert together == [2]  # announced: the first waited for it


def test_batcher_refuses_beyond_its_queue_and_reports_errors():
    async def main():
        mb = MicroBatcher(_encode, max_batch=1, max_wait_ms=0, queue_size=2)
        await mb.start()
        res = await asyncio.gather(
            *(mb.encode(np.zeros((1, 2, 3), np.float32)) for _ in range(8)),
            return_exceptions=True,
        )
        await mb.stop()

        def broken(_: np.ndarray, __: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            raise RuntimeError("boom")

        mb2 = MicroBatcher(broken)
        await mb2.start()
        with pytest.raises(RuntimeError, match="boom"):
            await mb2.encode(np.zeros((1, 2, 3), np.float32))
        assert await asyncio.gather(mb2.encode(np.zeros((1, 2, 3))), return_exceptions=True)
        await mb2.stop()
        return res

    res = asyncio.run(main())
    overloaded = [r for r in res if isinstance(r, Overloaded)]
    assert overloaded and overloaded[0].headers["Retry-After"]
    assert any(isinstance(r, tuple) for r in res)


def test_a_compressed_pcd_that_inflates_past_the_decoded_limit_is_a_413():
    """The service's limits.max_decoded_bytes bounds what a PCD's own compression may build,
    as it bounds Content-Encoding: refused from the header, before pypcd4 inflates anything."""
    n, record = 200_000, 12 + 8 * 100
    header = (
        "VERSION 0.7\nFIELDS x y z pad\nSIZE 4 4 4 8\nTYPE F F F F\nCOUNT 1 1 1 100\n"
        f"WIDTH {n}\nHEIGHT 1\nPOINTS {n}\nDATA binary_compressed\n"
    ).encode()
    body = header + struct.pack("<II", 10, n * record) + b"\0" * 10
    limits = Settings().limits.model_copy(update={"max_decoded_bytes": 64 << 20})
    with pytest.raises(DataTooLargeError) as err:
        decode_scan(ScanBody(body, "application/x-pcd"), limits)
    assert lidar_status(err.value) == 413
    assert "allowed: at most 67108864 bytes" in str(err.value)


def test_filter_columns_let_go_of_robot_and_session_ids_no_live_row_uses():
    """A robot a mission, a session a run: ids that come and go must not grow the map's
    memory for ever. A code is held while a live row uses it, then given to the next id,
    and a filter on a gone id matches no live row."""
    from overlapmamba.service.backends.faiss.columns import FilterColumns

    c = FilterColumns()
    for i in range(3000):  # each row its own robot and session, inserted then deleted
        c.add(np.array([i]), [(f"robot-{i}", f"session-{i}", float(i))])
        c.remove(np.array([i]))
    assert c.codes == 0
    c.add(np.array([3000, 3001]), [("b", "s", 1.0), ("b", "s", 2.0)])
    assert c.lookup("robot-0") == -1 and c.codes == 2  # the recycled code is b's alone
    c.remove(np.array([3000]))
    assert c.lookup("b") >= 0  # row 3001 still uses it
    c.remove(np.array([3001]))
    c.remove(np.array([3001]))  # twice: let go once
    assert c.codes == 0 and not c.alive.any()
    c.add(np.array([5]), [("r", "s", 0.0)])
    c.add(np.array([5]), [("q", "s", 0.0)])  # a row written again gives back its old codes
    assert c.lookup("r") == -1 and c.codes == 2


def test_the_query_rate_over_the_last_minute_has_no_ceiling():
    """``queries_per_s_1m`` counted a window of the last 2,048 query times: past 2,048
    queries a minute it read 34.13 a second whatever the load, and the dashboard's rate
    line disagreed with its Δqueries/Δt. It counts queries a second over the minute."""
    import time

    from overlapmamba.service.stats import Stats

    s = Stats("m")
    for _ in range(6000):
        s.query("town", "r1", False)
    assert s.total.public()["queries_per_s_1m"] == pytest.approx(100.0)
    assert s.by_map["town"].public()["queries_per_s_1m"] == pytest.approx(100.0)
    c = s.by_map["town"]
    c.recent.clear()
    c.queried(time.time() - 120)  # two minutes ago: out of the minute
    c.queried(time.time() - 30)
    assert c.public()["queries_per_s_1m"] == pytest.approx(1 / 60)
    assert len(c.recent) == 1  # older seconds are dropped as newer ones come


def test_statistics_say_none_where_nothing_was_counted_and_follow_the_backend():
    """An empty window gave p50 = p99 = 0 ms and no query a loop-closure rate of 0 (the
    dashboard drew 0 ms lines, "0.0 %"); the first minute's query rate was divided by a
    whole minute. A replica beside others on one Qdrant kept a map's series and counts after
    another replica deleted it, and its keyframes gauge at its own last write."""
    import time

    from overlapmamba.service.stats import Stats

    s = Stats("m")
    fresh = s.public()
    assert fresh["latency_ms"]["total"] == {"p50": None, "p90": None, "p99": None, "n": 0}
    assert (
        fresh["loop_closure_rate"] is None and fresh["verification"]["registered_per_query"] is None
    )
    s.started = time.time() - 10  # ten seconds up, 30 queries: 3 a second, not 0.5
    for _ in range(30):
        s.query("town", "r1", True)
    assert s.public()["queries_per_s_1m"] == pytest.approx(3.0, rel=0.05)
    assert s.public()["loop_closure_rate"] == 1.0
    s.insert("gone", "r1")
    s.p_keyframes.labels("town").set(3)
    s.reconcile(s.known_maps(), {"town": 2})  # another replica deleted "gone" and a keyframe
    assert set(s.by_map) == {"town"}
    text = generate_latest(s.registry).decode()
    assert 'map="gone"' not in text and 'overlapmamba_map_keyframes{map="town"} 2.0' in text
    s.batch(256, 0.0)  # batching.max_batch allows 256: a bucket of its own, not +Inf only
    assert (
        'overlapmamba_encoder_batch_size_bucket{le="256.0"} 1.0'
        in generate_latest(s.registry).decode()
    )


def test_a_maps_statistics_give_its_own_latency():
    """``GET /v1/maps/{id}/stats`` gave the whole service's latency percentiles as if they
    were the map's: a slow map could not be told from a fast one. Each map keeps its own
    window; the service's holds every request, a map's only its own."""
    from overlapmamba.service.stats import Stats

    s = Stats("m")
    for _ in range(3):
        s.timings({"encode": 20.0, "total": 30.0}, "fast")
    s.timings({"encode": 20.0, "total": 900.0}, "slow")
    s.timings({"total": 10.0})  # a descriptor request: no map
    assert s.public("fast")["latency_ms"]["total"] == {
        "p50": 30.0,
        "p90": 30.0,
        "p99": 30.0,
        "n": 3,
    }
    assert s.public("slow")["latency_ms"]["total"]["p50"] == 900.0
    assert s.public()["latency_ms"]["total"]["n"] == 5
    assert s.public("fast")["latency_ms"]["verify"]["n"] == 0


def test_filter_columns_hold_the_live_rows_span_not_every_row_ever_written():
    """Row ids only grow, and the columns were indexed by them from 0: a map keeping its
    latest keyframes (insert new, delete old) grew 17 bytes a keyframe it ever held, for
    good, and every filtered search built a mask that long. The rows below the first live
    one are cut off; the masks a search gets still select the same rows."""
    from overlapmamba.service.backends.faiss.columns import FilterColumns

    c = FilterColumns()
    live: list[int] = []
    for cycle in range(60):  # 500 new rows a cycle, the oldest deleted: 1,000 kept
        new = np.arange(cycle * 500, cycle * 500 + 500)
        c.add(new, [(f"r{i % 3}", "s", float(i)) for i in new])
        live += list(new)
        if len(live) > 1000:
            c.remove(np.array(live[:500]))
            live = live[500:]
    assert len(c.alive) <= 8 * 1024, len(c.alive)  # 30,000 rows written
    assert c.base > 20_000 and c.base % 8 == 0
    got = np.flatnonzero(c.alive) + c.base
    np.testing.assert_array_equal(got, live)
    c.add(np.array([7]), [("r0", "s", 7.0)])  # an id below the base (after a full wipe)
    assert c.base <= 7 and c.alive[7 - c.base] and c.ts[7 - c.base] == 7.0
    np.testing.assert_array_equal(np.flatnonzero(c.alive) + c.base, [7, *live])


def test_a_filtered_search_selects_the_same_rows_whatever_the_columns_base():
    from overlapmamba.service.backends.faiss.index import VectorIndex

    rng = np.random.default_rng(0)
    vecs = unit(rng, 200)
    ids = np.arange(4000, 4200)
    index = VectorIndex.flat(D)
    index.add(ids, vecs)
    q = vecs[17]
    mask = np.zeros(208, bool)  # over ids 4000 … 4207
    mask[[17, 50, 120]] = True
    _, got = index.search(q, 3, mask, base=4000)
    assert sorted(got.tolist()) == [4017, 4050, 4120] and got[0] == 4017
    full = np.zeros(4208, bool)  # the same rows, from id 0
    full[[4017, 4050, 4120]] = True
    assert sorted(index.search(q, 3, full)[1].tolist()) == [4017, 4050, 4120]


def test_filter_columns_opened_on_late_rows_start_at_them():
    from overlapmamba.service.backends.faiss.columns import FilterColumns

    c = FilterColumns()
    c.add(np.array([90_001, 90_002]), [("r", "s", 1.0), ("r", "s", 2.0)])  # a map reopened
    assert c.base == 90_000 and len(c.alive) <= 1024
