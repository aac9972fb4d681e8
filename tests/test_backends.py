"""The two map backends — FAISS (embedded) and Qdrant (qdrant-client's local mode) — given
the same inserts, deletes, filtered queries and restarts, give the same answers, and both
agree with a numpy brute force over the live keyframes."""

from __future__ import annotations

import contextlib
import dataclasses
import sqlite3
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from overlapmamba.service.backends.base import MapBackend
from overlapmamba.service.backends.factory import open_backend
from overlapmamba.service.backends.faiss.index import search_reference
from overlapmamba.service.domain import Filters, NewKeyframe, content_hash
from overlapmamba.service.errors import BadRequest, Conflict, NotFound, Unavailable
from overlapmamba.service.settings import Settings

DIM = 32
MODEL_ID = "test-model"


def settings_for(kind: str, root: Path) -> Settings:
    if kind == "faiss":
        return Settings(data_dir=root / "data")
    return Settings(data_dir=root / "data", index={"backend": "qdrant"}, qdrant={"path": root})


@contextlib.contextmanager
def opened(kind: str, root: Path) -> Iterator[MapBackend]:
    b = open_backend(settings_for(kind, root), model_id=MODEL_ID, dim=DIM)
    b.load_all()
    try:
        yield b
    finally:
        b.close()


def row(i: int, rng: np.random.Generator, *, yaw: bool = False) -> NewKeyframe:
    desc = rng.normal(size=DIM)
    desc = (desc / np.linalg.norm(desc)).astype(np.float32)  # the service's descriptors
    robot, session = f"r{i % 3}", f"s{i % 5}"
    ts = float(i)
    return NewKeyframe(
        keyframe_id=f"kf-{i}",
        robot_id=robot,
        session_id=session,
        timestamp=ts,
        pose=[float(i), 0.0, 0.0, 1.0, 0.0, 0.0, 0.0] if i % 2 else None,
        descriptor=desc,
        yaw=rng.normal(size=(4, 36)).astype(np.float32) if yaw else None,
        content_hash=content_hash("descriptor", desc.tobytes(), {"i": i}),
        sensor="vlp16" if i % 4 == 3 else None,  # a map holds keyframes of several sensors
    )


FILTERS = [
    Filters(),
    Filters(exclude_session="s1"),
    Filters(exclude_robot="r2"),
    Filters(exclude_recent_s=40.0, session_id="s3", timestamp=150.0),
    Filters(exclude_recent_s=40.0, session_id="s3", robot_id="r0", timestamp=150.0),
    Filters(time_from=20.0, time_to=90.5),
    Filters(exclude_robot="r0", time_from=50.0),
    Filters(max_match_distance=7.0),
    Filters(exclude_session="nobody-has-this"),
]


def allowed(rows: dict[str, NewKeyframe], f: Filters) -> list[NewKeyframe]:
    """The filter semantics, spelled out once more in plain Python."""
    out = []
    for r in rows.values():
        if f.exclude_session is not None and r.session_id == f.exclude_session:
            continue
        if f.exclude_robot is not None and r.robot_id == f.exclude_robot:
            continue
        if f.exclude_recent_s is not None:
            assert f.timestamp is not None
            own = r.session_id == f.session_id and f.robot_id in (None, r.robot_id)
            if own and r.timestamp > f.timestamp - f.exclude_recent_s:
                continue
        if f.time_from is not None and r.timestamp < f.time_from:
            continue
        if f.time_to is not None and r.timestamp > f.time_to:
            continue
        out.append(r)
    return out


def answers(b: MapBackend, queries: np.ndarray, k: int) -> list[list[tuple[str, float]]]:
    m = b.get("town")
    return [
        [(x.keyframe.keyframe_id, x.distance) for x in m.search(q, k, f)]
        for q in queries
        for f in FILTERS
    ]


def expected(rows: dict[str, NewKeyframe], queries: np.ndarray, k: int) -> list[list[str]]:
    out = []
    for q in queries:
        for f in FILTERS:
            live = allowed(rows, f)
            if not live:
                out.append([])
                continue
            vecs = np.stack([r.descriptor / np.linalg.norm(r.descriptor) for r in live])
            ids = np.array([r.keyframe_id for r in live])
            dist, top = search_reference(vecs, ids, q / np.linalg.norm(q), k)
            keep = [
                i
                for d, i in zip(dist, top, strict=True)
                if f.max_match_distance is None or d <= f.max_match_distance
            ]
            out.append(keep)
    return out


def same(a: list[list[tuple[str, float]]], b: list[list[tuple[str, float]]]) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert [i for i, _ in x] == [i for i, _ in y]
        np.testing.assert_allclose([d for _, d in x], [d for _, d in y], atol=2e-5)


def test_backends_agree_through_inserts_deletes_filters_and_restarts(tmp_path):
    rng = np.random.default_rng(7)
    rows = {r.keyframe_id: r for r in (row(i, rng, yaw=i < 10) for i in range(160))}
    queries = rng.normal(size=(6, DIM))
    queries = (queries / np.linalg.norm(queries, axis=1, keepdims=True)).astype(np.float32)
    k = 12
    results: dict[str, list] = {}
    for kind in ("faiss", "qdrant"):
        root = tmp_path / kind
        live = dict(rows)
        with opened(kind, root) as b:
            m, created = b.create("town", "flat")
            assert created and m.model_id == MODEL_ID and m.dim == DIM
            assert b.create("town", None)[1] is False
            with pytest.raises(Conflict):
                b.create("town", "ivf")
            batch = list(rows.values())
            first = m.insert(batch[:100])
            assert all(r.created for r in first)
            # a retry is idempotent; a repeated id in one request is created once
            again = m.insert([*batch[90:160], batch[150]])
            assert [r.created for r in again] == [False] * 10 + [True] * 60 + [False]
            assert m.count == 160
            other = row(3, rng)
            with pytest.raises(Conflict):  # same id, other content: refused whole
                m.insert([batch[0], other])
            # the same content as an earlier release hashed it (same_as): not a conflict
            rehashed = dataclasses.replace(
                batch[0], content_hash="new-hash", same_as=(batch[0].content_hash,)
            )
            assert [r.created for r in m.insert([rehashed])] == [False]
            with pytest.raises(BadRequest):
                m.insert([dataclasses.replace(row(999, rng), descriptor=np.ones(DIM + 1))])
            # normalised once, before a backend: one that is not a unit vector is refused
            long = dataclasses.replace(row(998, rng), descriptor=2 * row(998, rng).descriptor)
            with pytest.raises(BadRequest, match="kf-998.*norm 2; allowed: a unit vector"):
                m.insert([long])
            for kid in ("kf-5", "kf-6", "kf-77", "kf-140"):
                m.delete(kid)
                live.pop(kid)
            with pytest.raises(NotFound):
                m.delete("kf-5")
            assert m.get("kf-5") is None
            got = m.get("kf-7")
            assert got is not None and got.public() == {
                "keyframe_id": "kf-7",
                "robot_id": "r1",
                "session_id": "s2",
                "timestamp": 7.0,
                "pose": [7.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
                "sensor": "vlp16",
            }
            last = m.last_keyframe("r2", "s3")
            assert last is not None and last.keyframe_id == "kf-158"
            last = m.last_keyframe("r2", "s0")  # the robot's last in that session
            assert last is not None and last.keyframe_id == "kf-155"
            assert m.last_keyframe("nobody", "s3") is None
            before = answers(b, queries, k)
            # the yaw features travel with the keyframe and come back for the top-k
            yq = np.asarray(rows["kf-1"].yaw)
            hit = m.search(rows["kf-1"].descriptor, 1, Filters(), yaw=yq)[0]
            assert hit.keyframe.keyframe_id == "kf-1" and hit.distance < 1e-3
            assert hit.yaw_deg is not None and abs(hit.yaw_deg) < 0.1  # float16 features
            # a runner-up fetched for its distance only gets no yaw
            with_yaw = Filters(time_to=9.0)  # kf-0 … kf-9 carry yaw features
            three = m.search(rows["kf-1"].descriptor, 3, with_yaw, yaw=yq)
            assert [x.yaw_deg is not None for x in three] == [True, True, True]
            three = m.search(rows["kf-1"].descriptor, 3, with_yaw, yaw=yq, yaw_k=2)
            assert [x.yaw_deg is not None for x in three] == [True, True, False]
            assert three[0].yaw_deg == hit.yaw_deg
            info = m.info()
            assert info["backend"] == kind and info["keyframes"] == 156
        with opened(kind, root) as b:  # a restart: everything acknowledged is there
            assert [x.map_id for x in b.snapshot_list()] == ["town"]
            m = b.get("town")
            assert m.count == 156 and m.model_id == MODEL_ID
            after = answers(b, queries, k)
            same(before, after)
            assert [[i for i, _ in a] for a in after] == expected(live, queries, k)
            m.insert([row(500, rng)])
            assert m.count == 157
            b.delete("town")
            with pytest.raises(NotFound):
                b.get("town")
            with pytest.raises(NotFound):
                m.count  # noqa: B018  # a handle held across the delete
            assert b.snapshot_list() == []
        results[kind] = after
    same(results["faiss"], results["qdrant"])


def test_qdrant_maps_are_shared_between_replicas_and_refuse_foreign_collections(tmp_path):
    """Two backends on one Qdrant see each other's maps at once (local mode allows one
    client per folder, so the second "replica" shares the first one's client)."""
    from qdrant_client import models

    from overlapmamba.service.backends.qdrant.backend import QdrantBackend

    s = settings_for("qdrant", tmp_path)
    with opened("qdrant", tmp_path) as a:
        m, _ = a.create("yard", None)
        assert m.kind == "auto"
        assert isinstance(a, QdrantBackend)
        b = QdrantBackend(s.qdrant, s.index, model_id=MODEL_ID, dim=DIM, client=a.client)
        rng = np.random.default_rng(1)
        m.insert([row(1, rng)])
        assert b.get("yard").count == 1
        a.client.create_collection(
            "overlapmamba-alien",
            vectors_config=models.VectorParams(size=DIM, distance=models.Distance.COSINE),
        )
        with pytest.raises(Conflict, match="not this service's map"):
            b.get("alien")
        assert [x.map_id for x in b.snapshot_list()] == ["yard"]
        # a second service with a longer prefix: neither sees the other's maps
        v2 = QdrantBackend(
            s.qdrant.model_copy(update={"collection_prefix": "overlapmamba-v2-"}),
            s.index,
            model_id="model-2",
            dim=DIM,
            client=a.client,
        )
        v2.create("town", "flat")
        assert [x.map_id for x in v2.snapshot_list()] == ["town"]
        assert [x.map_id for x in b.snapshot_list()] == ["yard"]
        with pytest.raises(Conflict):
            b.get("v2-town")  # the collection overlapmamba-v2-town is v2's "town"
        with pytest.raises(Conflict, match="local mode has no snapshots"):
            m.snapshot()
        held = b.get("yard")
        a.delete("yard")  # the other replica still holds a fresh handle
        with pytest.raises(NotFound):
            held.count  # noqa: B018
        with pytest.raises(NotFound):
            b.get("yard")
        # its own DELETE of the map the other replica deleted is 404, not 204
        a.create("lot", None)
        b.get("lot")
        a.delete("lot")
        with pytest.raises(NotFound):
            b.delete("lot")
        # a handle opened before its map was deleted (a write under way) writes nothing into
        # the map made again under the id: 404, as the FAISS backend's retired map answers
        stale, _ = a.create("lot", None)
        a.delete("lot")
        fresh, created = a.create("lot", None)
        assert created
        with pytest.raises(NotFound):
            stale.insert([row(2, rng)])
        with pytest.raises(NotFound):
            stale.delete("kf-2")
        assert fresh.count == 0 and fresh.insert([row(3, rng)])[0].created


def test_get_nowait_answers_only_without_io(tmp_path):
    """The event loop's map lookup: FAISS holds every map in memory and answers like get
    (the map, or the same error); Qdrant answers only while its last look at the server is
    fresh, else None (the caller then asks get, in a worker thread)."""
    from overlapmamba.service.backends.qdrant.backend import FRESH_S, QdrantBackend

    with opened("faiss", tmp_path / "f") as f:
        m, _ = f.create("yard", None)
        assert f.get_nowait("yard") is m is f.get("yard")
        with pytest.raises(NotFound):
            f.get_nowait("nowhere")
        with pytest.raises(BadRequest):
            f.get_nowait("no spaces")
    s = settings_for("qdrant", tmp_path / "q")
    with opened("qdrant", tmp_path / "q") as a:
        a.create("yard", None)
        assert isinstance(a, QdrantBackend)
        b = QdrantBackend(s.qdrant, s.index, model_id=MODEL_ID, dim=DIM, client=a.client)
        assert b.get_nowait("yard") is None  # never looked at: only the server knows
        assert b.get_nowait("nowhere") is None
        m = b.get("yard")
        assert b.get_nowait("yard") is m
        m.checked -= FRESH_S + 1  # the look has gone stale: another replica may delete it
        assert b.get_nowait("yard") is None
        with pytest.raises(BadRequest):
            b.get_nowait("no spaces")


def test_faiss_snapshot_still_reports_its_seq(tmp_path):
    with opened("faiss", tmp_path) as b:
        m, _ = b.create("town", "flat")
        m.insert([row(i, np.random.default_rng(i)) for i in range(3)])
        snap = m.snapshot()
        assert snap["seq"] == 1 and snap["bytes"] > 0


@pytest.mark.parametrize("cache_mb", [0, 8])
@pytest.mark.parametrize("kind", ["faiss", "qdrant"])
def test_a_scan_querys_matches_carry_their_stored_descriptors(kind, cache_mb, tmp_path):
    """A second stage may score by part of each candidate's descriptor
    (overlapmamba.service.ranking): every match of a query with yaw features carries the
    descriptor it was inserted with, read from the store, the engine or the row cache alike."""
    s = settings_for(kind, tmp_path)
    s = s.model_copy(update={"index": s.index.model_copy(update={"row_cache_mb": cache_mb})})
    b = open_backend(s, model_id=MODEL_ID, dim=DIM)
    b.load_all()
    try:
        m, _ = b.create("town", "flat")
        rows = {
            r.keyframe_id: r
            for r in (row(i, np.random.default_rng(i), yaw=True) for i in range(12))
        }
        m.insert(list(rows.values()))
        q = rows["kf-3"]
        for _ in range(2):  # the second time from the row cache, where there is one
            found = m.search(q.descriptor, 6, Filters(), q.yaw, yaw_k=5, descriptors=True)
            assert len(found) == 6
            for x in found:
                assert x.keyframe.descriptor is not None, x.keyframe.keyframe_id
                np.testing.assert_array_equal(
                    x.keyframe.descriptor, rows[x.keyframe.keyframe_id].descriptor
                )
    finally:
        b.close()


@pytest.mark.parametrize("kind", ["faiss", "qdrant"])
def test_positions_are_the_latest_keyframes_that_have_a_pose(kind, tmp_path):
    """The overview's ``limit`` counts keyframes with a pose: keyframes without one (every
    other here, the newest among them) never crowd posed ones out of the answer."""
    rng = np.random.default_rng(0)
    with opened(kind, tmp_path) as b:
        m, _ = b.create("town", "flat")
        m.insert([row(i, rng) for i in range(12)])  # odd i have a pose; 11 is the newest
        assert m.positions(3) == [("r2", 11.0, 0.0), ("r0", 9.0, 0.0), ("r1", 7.0, 0.0)]
        assert len(m.positions(100)) == 6
        if kind == "faiss":  # an index answers it: the dashboard asks every few seconds, and
            # reading and sorting the whole table took 0.3 s at 150,000 keyframes
            store = m.store  # type: ignore[attr-defined]
            with store._file.reading() as con:
                plan = " ".join(
                    str(r[-1])
                    for r in con.execute(
                        "EXPLAIN QUERY PLAN SELECT robot_id, pose FROM keyframes WHERE "
                        "keyframe_id IS NOT NULL AND pose IS NOT NULL ORDER BY timestamp DESC "
                        "LIMIT 3"
                    )
                )
            assert "keyframes_posed_time" in plan and "TEMP B-TREE" not in plan, plan


@pytest.mark.parametrize("kind", ["faiss", "qdrant"])
def test_a_maps_sensor_and_mount_are_kept_across_restarts_and_fixed(kind, tmp_path):
    from overlapmamba.core.sensors.mount import Mount

    low = Mount(height=0.35, pitch_deg=2.0)
    with opened(kind, tmp_path) as b:
        m, created = b.create("amr", None, None, "os0-128", low)
        assert created and m.mount == low and m.info()["mount"] == low.key()
        plain, _ = b.create("cars", None)
        assert plain.mount is None and plain.info()["mount"] is None
        assert b.create("amr", None, None, None, low)[1] is False  # the same again: no change
        assert b.create("amr", None)[0].mount == low  # naming none keeps it
        with pytest.raises(Conflict, match=r"exists with mount 0.35,2,0, not 0.7,0,0") as err:
            b.create("amr", None, None, None, Mount(height=0.7))
        assert err.value.detail["mount"] == low.key()
        with pytest.raises(Conflict, match="exists with mount none, not 0.7"):
            b.create("cars", None, None, None, Mount(height=0.7))
    with opened(kind, tmp_path) as b:  # a restart: the settings are the map's
        assert b.get("amr").mount == low and b.get("amr").sensor == "os0-128"
        assert b.get("cars").mount is None


def test_a_map_created_again_while_its_deletion_waits_is_kept(tmp_path, monkeypatch):
    """A robot's idempotent PUT of a map while an operator's DELETE of it waits for the map
    (a snapshot or a write in progress) must neither take the old map's folder nor lose its
    own to the deletion: it waits for the deletion, then creates a fresh map whose
    keyframes survive a restart. Past the wait it answers 503 map_busy."""
    import threading
    import time

    from overlapmamba.service.backends.faiss import backend as faiss_backend
    from overlapmamba.service.errors import Unavailable

    rng = np.random.default_rng(0)
    with opened("faiss", tmp_path) as b:
        old, _ = b.create("town", "flat")
        old.insert([row(i, rng) for i in range(3)])
        created: list[tuple[object, bool]] = []
        with old.lock.read():  # what a snapshot being written holds
            deleting = threading.Thread(target=b.delete, args=("town",))
            deleting.start()
            t0 = time.monotonic()
            while "town" in b.maps and time.monotonic() - t0 < 10:
                time.sleep(0.01)
            monkeypatch.setattr(faiss_backend, "DELETE_WAIT_S", 0.2)
            with pytest.raises(Unavailable, match="still being deleted") as busy:
                b.create("town", "flat")
            assert busy.value.code == "map_busy"
            monkeypatch.setattr(faiss_backend, "DELETE_WAIT_S", 30.0)
            creating = threading.Thread(target=lambda: created.append(b.create("town", "flat")))
            creating.start()
            creating.join(0.3)
            assert creating.is_alive()  # waiting for the deletion, not taking its folder
        deleting.join(10)
        creating.join(10)
        new, was_created = created[0]
        assert was_created and new is not old
        assert isinstance(new, type(old)) and new.count == 0
        new.insert([row(i, rng) for i in range(10, 12)])
    with opened("faiss", tmp_path) as b:
        assert b.get("town").count == 2


def test_a_deletion_waits_for_a_snapshot_under_way(tmp_path):
    """A snapshot writes its file after letting go of the map's lock: a deletion that did
    not wait for it could move the folder away and let the file land in a new map's."""
    import threading

    with opened("faiss", tmp_path) as b:
        m, _ = b.create("town", "flat")
        m.insert([row(i, np.random.default_rng(i)) for i in range(3)])
        with m._snapshot_lock:  # a snapshot between its serialising and its file
            deleting = threading.Thread(target=b.delete, args=("town",))
            deleting.start()
            deleting.join(0.3)
            assert deleting.is_alive()
        deleting.join(10)
        assert not deleting.is_alive() and "town" not in b.maps
        assert not (tmp_path / "data" / "maps" / "town").exists()


def test_a_failed_or_foreign_snapshot_costs_a_rebuild_never_keyframes(tmp_path, monkeypatch):
    """A snapshot cut short by a full disk leaves no half-written copy (as large as the
    index) behind, and one left by a crash is removed at start-up; a snapshot that reflects
    more writes than its store holds is not this store's and is rebuilt from it."""
    from overlapmamba.service.backends.faiss import snapshot as snap
    from overlapmamba.service.backends.faiss.index import VectorIndex

    folder = tmp_path / "data" / "maps" / "town"
    with opened("faiss", tmp_path) as b:
        m, _ = b.create("town", "flat")
        m.insert([row(i, np.random.default_rng(i)) for i in range(3)])

        def full(fd: int) -> None:
            raise OSError(28, "No space left on device")

        monkeypatch.setattr(snap.os, "fsync", full)
        with pytest.raises(Unavailable, match="No space left") as err:  # 503, not 500
            m.snapshot()
        assert err.value.code == "storage_full"
        monkeypatch.undo()
        assert not list(folder.glob("*.tmp"))
    (folder / "index.snap.tmp").write_bytes(b"half a snapshot")
    empty = VectorIndex.flat(DIM).serialize()
    snap.write_snapshot(folder / snap.SNAPSHOT_NAME, empty, 999, "flat", DIM)
    with opened("faiss", tmp_path) as b:
        assert b.get("town").count == 3
        assert not list(folder.glob("*.tmp"))


def test_an_export_counts_what_its_file_holds_while_a_service_writes(tmp_path, monkeypatch):
    """Keyframes written after the copy was taken are not in the file: the count the export
    reports is the file's."""
    from overlapmamba.service import backup

    data = tmp_path / "data"
    with opened("faiss", tmp_path) as b:
        m, _ = b.create("town", "flat")
        m.insert([row(i, np.random.default_rng(i)) for i in range(3)])
        real_replace = backup.os.replace

        def written_meanwhile(src, dst):  # the service inserts between the copy and its rename
            m.insert([row(i, np.random.default_rng(i)) for i in range(3, 5)])
            real_replace(src, dst)

        monkeypatch.setattr(backup.os, "replace", written_meanwhile)
        out = backup.export_map(data, "town", tmp_path / "town.sqlite")
        monkeypatch.undo()
        assert m.count == 5 and out["keyframes"] == 3
    with sqlite3.connect(tmp_path / "town.sqlite") as con:
        sql = "SELECT COUNT(*) FROM keyframes WHERE keyframe_id IS NOT NULL"
        assert con.execute(sql).fetchone()[0] == 3


def test_an_import_cut_off_between_its_renames_is_finished_at_start_up(tmp_path, monkeypatch):
    """import-map moves the old map away, then the new one in: a crash between the two must
    not leave start-up to clear both as debris."""
    from overlapmamba.service import backup

    data = tmp_path / "data"
    with opened("faiss", tmp_path) as b:
        m, _ = b.create("town", "flat")
        m.insert([row(i, np.random.default_rng(i)) for i in range(3)])
    backup.export_map(data, "town", tmp_path / "town.sqlite")
    with opened("faiss", tmp_path) as b:
        b.get("town").insert([row(i, np.random.default_rng(i)) for i in range(3, 5)])
    real_replace, calls = backup.os.replace, []

    def crash_on_the_second(src, dst):  # the process dies after moving the old map away
        calls.append(dst)
        if len(calls) == 2:
            raise SystemExit("killed")
        real_replace(src, dst)

    monkeypatch.setattr(backup.os, "replace", crash_on_the_second)
    with pytest.raises(SystemExit):
        backup.import_map(data, "town", tmp_path / "town.sqlite", replace=True)
    monkeypatch.undo()
    assert not (data / "maps" / "town").exists()
    with opened("faiss", tmp_path) as b:
        assert b.get("town").count == 3  # the import's keyframes, not nothing
    assert not list((data / "maps").glob(".import-*"))
    assert not (data / "maps" / "town" / "imported").exists()


def test_a_write_stored_but_not_indexed_is_rebuilt_never_snapshotted_away(tmp_path, monkeypatch):
    """The store commits first, then the index and the filter columns are updated. When that
    update fails (out of memory), the keyframe is stored (a retry answers created: false):
    the map must rebuild it into its index, and no snapshot may record it as applied
    before, or a restart would never replay it."""
    rng = np.random.default_rng(0)
    rows = [row(i, rng) for i in range(4)]
    with opened("faiss", tmp_path) as b:
        m, _ = b.create("town", "flat")
        m.insert(rows[:2])
        real_add = m.index.add

        def out_of_memory(ids, vecs):
            raise MemoryError("faiss could not grow its index")

        m._maintenance.acquire()  # no background rebuild yet: the snapshot must see to it
        monkeypatch.setattr(m.index, "add", out_of_memory)
        with pytest.raises(MemoryError):
            m.insert([rows[2]])
        monkeypatch.setattr(m.index, "add", real_add)
        assert m.insert([rows[2]])[0].created is False  # stored: a retry finds it
        m.insert([rows[3]])  # a later write moves the applied seq past the lost one
        m.snapshot()
        assert m.count == 4
        m._maintenance.release()
        only = Filters(time_from=2.0, time_to=2.0)  # read from the filter columns
        found = [x.keyframe.keyframe_id for x in m.search(rows[2].descriptor, 1, only)]
        assert found == ["kf-2"]
    with opened("faiss", tmp_path) as b:
        assert b.get("town").count == 4


def test_a_write_that_fails_while_a_snapshot_or_rebuild_is_under_way_is_repaired(
    tmp_path, monkeypatch
):
    """Two narrower timings of the failure above. A snapshot past its ``incomplete`` check
    but not yet in its read lock, when a write failed and a later one succeeded, recorded
    the later seq as applied: after a crash the failed keyframe was in the store and never
    in the index. A rebuild that read ``incomplete`` before such a failure put the row in
    its index but not in the filter columns, and cleared the flag: every filtered search
    (observe always filters) skipped the keyframe for good."""
    import threading

    rng = np.random.default_rng(0)
    rows = [row(i, rng) for i in range(6)]

    def fail_one_write_while(m, gate_store_call: str, first: int, action) -> None:  # type: ignore[no-untyped-def]
        at_gate, go = threading.Event(), threading.Event()
        real = getattr(m.store, gate_store_call) if gate_store_call else m.lock.read

        def gated(*a, **k):  # type: ignore[no-untyped-def]
            if threading.current_thread() is worker and not at_gate.is_set():
                at_gate.set()
                go.wait(10)
            return real(*a, **k)

        if gate_store_call:
            monkeypatch.setattr(m.store, gate_store_call, gated)
        else:
            monkeypatch.setattr(m.lock, "read", gated)
        worker = threading.Thread(target=action)
        worker.start()
        assert at_gate.wait(10)
        real_add = m.index.add

        def out_of_memory(ids, vecs):  # type: ignore[no-untyped-def]
            raise MemoryError("faiss could not grow its index")

        monkeypatch.setattr(m.index, "add", out_of_memory)
        with pytest.raises(MemoryError):
            m.insert([rows[first]])
        monkeypatch.setattr(m.index, "add", real_add)
        m.insert([rows[first + 1]])  # a later write succeeds
        go.set()
        worker.join(10)
        monkeypatch.undo()

    with opened("faiss", tmp_path) as b:
        m, _ = b.create("town", "flat")
        m.insert(rows[:2])
        m._maintenance.acquire()  # no background maintenance: the test's calls only
        fail_one_write_while(m, "", 2, m.snapshot)  # between the check and the read lock
        assert m.snapshot_seq == m.store.last_seq and not m.incomplete
        fail_one_write_while(m, "live_rows", 4, m.rebuild)  # while the rebuild reads rows
        m._maintenance.release()
        for i in (2, 4):
            only = Filters(time_from=float(i), time_to=float(i))  # the filter columns
            found = [x.keyframe.keyframe_id for x in m.search(rows[i].descriptor, 1, only)]
            assert found == [f"kf-{i}"], (i, found)
        b.close(snapshot=False)  # a crash: the next start has the snapshot and the store
    with opened("faiss", tmp_path) as b:
        m = b.get("town")
        assert m.count == 6
        found = [x.keyframe.keyframe_id for x in m.search(rows[2].descriptor, 1, Filters())]
        assert found == ["kf-2"]


def test_a_full_disk_is_named_and_the_map_goes_on_afterwards(tmp_path):
    """SQLite rolls a transaction back itself when the disk fills: the error the operator
    sees must say the disk is full (503 storage_full), not that no transaction was active;
    nothing half-written stays, and once there is room again the map takes writes."""
    from overlapmamba.service.errors import Unavailable

    rng = np.random.default_rng(0)
    with opened("faiss", tmp_path) as b:
        m, _ = b.create("town", "flat")
        m.insert([row(i, rng) for i in range(2)])
        con = m.store._file.writer
        pages = con.execute("PRAGMA page_count").fetchone()[0]
        con.execute(f"PRAGMA max_page_count = {pages + 1}")  # the disk is full
        big = [row(i, rng, yaw=True) for i in range(2, 60)]
        with pytest.raises(Unavailable, match="store cannot grow: database or disk is full") as e:
            m.insert(big)
        assert e.value.code == "storage_full" and not con.in_transaction
        assert m.count == 2 and m.store.count() == 2
        con.execute("PRAGMA max_page_count = 1073741823")  # room again
        assert all(r.created for r in m.insert(big))
        assert m.count == 60


def test_a_read_under_way_finishes_before_its_map_is_deleted(tmp_path, monkeypatch):
    """GET of a keyframe while its map is deleted: the read finishes first (or finds the
    map gone: 404), never a store closed or moved away under it (500)."""
    import threading
    import time

    rng = np.random.default_rng(0)
    with opened("faiss", tmp_path) as b:
        m, _ = b.create("town", "flat")
        m.insert([row(i, rng) for i in range(2)])
        real_get, got = m.store.get, []

        def slow_get(keyframe_id):
            time.sleep(0.3)  # a read the deletion overtakes
            return real_get(keyframe_id)

        monkeypatch.setattr(m.store, "get", slow_get)
        reading = threading.Thread(target=lambda: got.append(m.get("kf-1")))
        reading.start()
        time.sleep(0.05)
        b.delete("town")
        reading.join(10)
        assert got and got[0] is not None and got[0].keyframe_id == "kf-1"
        with pytest.raises(NotFound):
            m.get("kf-1")


def test_a_qdrant_urls_credentials_never_reach_a_message(tmp_path):
    """A ``qdrant.url`` with a proxy's ``user:password@`` was shown as is in every error
    about Qdrant, in the log, and on /readyz, which answers without a key."""
    from overlapmamba.service.errors import Unavailable

    for url, shown in (
        ("http://overlap:Hunter2@127.0.0.1:9", "http://***@127.0.0.1:9"),
        ("https://token@[::1]:9/prefix", "https://***@[::1]:9/prefix"),
        ("http://127.0.0.1:9", "http://127.0.0.1:9"),
    ):
        settings = Settings(
            data_dir=tmp_path / "d",
            index={"backend": "qdrant"},
            qdrant={"url": url, "timeout_s": 1},
        )
        b = open_backend(settings, model_id=MODEL_ID, dim=DIM)
        try:
            assert b.where == shown
            if "Hunter2" in url:
                with pytest.raises(Unavailable) as err:
                    b.load_all()
                assert "Hunter2" not in err.value.message and shown in err.value.message
        finally:
            b.close()


@pytest.mark.parametrize("kind", ["faiss", "qdrant"])
def test_a_robots_last_keyframe_is_the_same_on_either_backend_when_times_tie(kind, tmp_path):
    """Keyframes of one robot at one time (a map-building batch): the FAISS store took
    whichever SQLite met first, Qdrant whichever its order gave, so the robot's insert
    schedule could differ by backend. Both take the one written last, then the greatest id."""
    from dataclasses import replace

    rng = np.random.default_rng(0)

    def mine(i: int, t: float):  # type: ignore[no-untyped-def]
        return replace(row(i, rng), robot_id="r", session_id="s", timestamp=t)

    tied = [mine(i, 5.0) for i in (11, 13, 12)]
    with opened(kind, tmp_path) as b:
        m, _ = b.create("town", "flat")
        m.insert([mine(1, 1.0)])
        m.insert(tied)  # one write: the greatest id
        assert m.last_keyframe("r", "s").keyframe_id == "kf-13"
        time.sleep(0.01)
        m.insert([mine(2, 5.0)])  # written last
        assert m.last_keyframe("r", "s").keyframe_id == "kf-2"
        assert m.last_keyframe("nobody", "s") is None


def test_a_snapshot_written_is_reported_though_its_tombstones_could_not_be_purged(
    tmp_path, monkeypatch, caplog
):
    """After the snapshot is written, the store's tombstones it covers are purged: on a full
    disk that delete failed and POST /snapshot answered 500 for a snapshot that was written.
    The purge waits for the next snapshot; this one is reported."""
    rng = np.random.default_rng(0)
    with opened("faiss", tmp_path) as b:
        m, _ = b.create("town", "flat")
        m.insert([row(i, rng) for i in range(4)])
        m.delete("kf-1")

        def full(seq: int) -> int:
            raise sqlite3.OperationalError("database or disk is full")

        monkeypatch.setattr(m.store, "purge_tombstones", full)
        got = m.snapshot()
        assert got["seq"] == m.store.last_seq and got["purged_tombstones"] == 0
        assert "tombstones not purged" in caplog.text
        monkeypatch.undo()
        assert m.snapshot()["purged_tombstones"] == 1


def test_a_deletion_that_cannot_move_its_folder_leaves_the_map_served(tmp_path, monkeypatch):
    """Found in review: a deletion whose rename failed (EBUSY on a mount) left the map
    closed and unserved though its files stayed, and a create of that id then removed them
    as debris."""
    import errno
    import shutil

    import overlapmamba.service.backends.faiss.backend as faiss_backend
    from overlapmamba.service.errors import Unavailable

    rows = [row(i, np.random.default_rng(i)) for i in range(5)]
    with opened("faiss", tmp_path) as b:
        m, _ = b.create("town", "flat")
        m.insert(rows)

        def busy(src, dst):
            raise OSError(errno.EBUSY, "Device or resource busy", str(src))

        monkeypatch.setattr(faiss_backend.os, "replace", busy)
        with pytest.raises(OSError, match="busy"):
            b.delete("town")
        monkeypatch.undo()
        again = b.get("town")  # served again, every keyframe there
        assert again is not m and again.count == 5
        hit = again.search(rows[3].descriptor, 1, Filters())[0]
        assert hit.keyframe.keyframe_id == "kf-3"
        # a map's files the service does not serve are never taken for debris
        shutil.copytree(tmp_path / "data" / "maps" / "town", tmp_path / "data" / "maps" / "copy")
        with pytest.raises(Unavailable, match="not served"):
            b.create("copy", "flat")
        assert (tmp_path / "data" / "maps" / "copy" / "store.sqlite").exists()
