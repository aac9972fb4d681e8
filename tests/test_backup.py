"""Backups of a map's store (``export-map``, ``import-map``) and stores that are not whole:
what a copy holds is what it reports, a damaged file is refused and never served as a map."""

from __future__ import annotations

import contextlib
import os
import sqlite3

import numpy as np
import pytest
from test_backends import opened, row

from overlapmamba.service import backup
from overlapmamba.service.backends.faiss.sqlfile import StoreError
from overlapmamba.service.backends.faiss.store import Store
from overlapmamba.service.domain import Filters
from overlapmamba.service.errors import Unavailable


def _live(path) -> int:
    with contextlib.closing(sqlite3.connect(f"file:{path}?mode=ro", uri=True)) as con:
        sql = "SELECT COUNT(*) FROM keyframes WHERE keyframe_id IS NOT NULL"
        return int(con.execute(sql).fetchone()[0])


def test_an_import_takes_the_keyframes_still_in_the_sources_write_ahead_log(tmp_path):
    """A store whose last writes sit in its ``-wal`` (its service still runs, or was killed):
    the import holds them, and says how many it holds."""
    with opened("faiss", tmp_path / "a") as b:
        m, _ = b.create("town", "flat")
        m.insert([row(i, np.random.default_rng(i)) for i in range(20)])
        src = tmp_path / "a" / "data" / "maps" / "town" / "store.sqlite"
        assert (src.parent / "store.sqlite-wal").stat().st_size > 0  # not checkpointed
        out = backup.import_map(tmp_path / "b" / "data", "copy", src)
    assert out["keyframes"] == 20
    with opened("faiss", tmp_path / "b") as b:
        assert b.get("copy").count == 20


def test_an_import_refuses_a_truncated_backup_and_leaves_the_map_as_it_was(tmp_path):
    data = tmp_path / "data"
    with opened("faiss", tmp_path) as b:
        m, _ = b.create("town", "flat")
        m.insert([row(i, np.random.default_rng(i), yaw=True) for i in range(300)])
    backup.export_map(data, "town", tmp_path / "town.sqlite")
    whole = (tmp_path / "town.sqlite").read_bytes()
    (tmp_path / "cut.sqlite").write_bytes(whole[: len(whole) * 3 // 4])
    with pytest.raises(backup.BackupError, match="damaged") as err:
        backup.import_map(data, "town", tmp_path / "cut.sqlite", replace=True)
    assert "cut.sqlite" in str(err.value)
    # a page lost inside the file: the keyframes still count, the file is not whole
    for page in range(2, len(whole) // 4096):
        hole = whole[: page * 4096] + bytes(4096) + whole[(page + 1) * 4096 :]
        (tmp_path / "hole.sqlite").write_bytes(hole)
        with contextlib.suppress(sqlite3.DatabaseError):
            if _live(tmp_path / "hole.sqlite") == 300:
                break
    else:
        pytest.fail("no page whose loss leaves the count whole")
    with pytest.raises(backup.BackupError, match="damaged .*quick_check"):
        backup.import_map(data, "town", tmp_path / "hole.sqlite", replace=True)
    with opened("faiss", tmp_path) as b:
        assert b.get("town").count == 300
    assert not list((data / "maps").glob(".import-*"))


def test_a_zero_byte_store_is_a_failed_map_never_an_empty_one(tmp_path):
    """The schema is never written over a store that lost its content: the map is listed as
    failed (503 naming the file and the way back) and its file is left as it was."""
    with opened("faiss", tmp_path) as b:
        b.create("town", "flat")[0].insert([row(0, np.random.default_rng(0))])
    folder = tmp_path / "data" / "maps" / "town"
    for f in folder.iterdir():
        f.unlink() if f.name != "store.sqlite" else f.write_bytes(b"")
    with opened("faiss", tmp_path) as b:
        assert "town" in b.failed
        with pytest.raises(Unavailable) as err:
            b.get("town")
    message = str(err.value)
    assert "store.sqlite" in message and "import-map" in message and "doctor" in message
    assert (folder / "store.sqlite").stat().st_size == 0
    with pytest.raises(StoreError, match="no map store"):
        Store(folder / "store.sqlite")
    with pytest.raises(StoreError, match="does not exist"):
        Store(tmp_path / "nothing.sqlite")


def test_an_export_only_reads_its_map_and_names_a_damaged_one(tmp_path):
    with opened("faiss", tmp_path) as b:
        b.create("town", "flat")[0].insert([row(0, np.random.default_rng(0))])
    store = tmp_path / "data" / "maps" / "town" / "store.sqlite"
    store.write_bytes(b"")
    with pytest.raises(backup.BackupError, match="cannot be read"):
        backup.export_map(tmp_path / "data", "town", tmp_path / "town.sqlite")
    assert store.stat().st_size == 0  # nothing written into it
    assert not (tmp_path / "town.sqlite").exists()
    assert not (tmp_path / "town.sqlite.tmp").exists()


def test_an_export_clears_the_debris_of_one_cut_short(tmp_path, monkeypatch):
    data = tmp_path / "data"
    with opened("faiss", tmp_path) as b:
        b.create("town", "flat")[0].insert([row(i, np.random.default_rng(i)) for i in range(3)])
    out = tmp_path / "town.sqlite"
    (tmp_path / "town.sqlite.tmp").write_bytes(b"half a copy")  # a killed export's
    assert backup.export_map(data, "town", out)["keyframes"] == 3
    assert _live(out) == 3 and not (tmp_path / "town.sqlite.tmp").exists()

    def disk_full(self, dest):
        dest.write_bytes(b"part")
        raise sqlite3.OperationalError("database or disk is full")

    monkeypatch.setattr(Store, "backup", disk_full)
    with pytest.raises(backup.BackupError, match="disk is full"):
        backup.export_map(data, "town", tmp_path / "again.sqlite")
    assert not list(tmp_path.glob("again.sqlite*"))


def test_a_full_disk_at_create_or_snapshot_is_named_and_leaves_no_debris(tmp_path, monkeypatch):
    """503 storage_full, not a 500: a map whose creation hit a full disk leaves no
    ``.create-`` folder and can be created once there is room; a snapshot that could not be
    written leaves the map serving (the snapshot is derived)."""
    import errno

    from overlapmamba.service.backends.faiss import folder as faiss_folder
    from overlapmamba.service.backends.faiss import map as faiss_map

    real_store = faiss_folder.Store

    def full_store(path, **kw):
        raise sqlite3.OperationalError("database or disk is full")

    def full_write(*args, **kw):
        raise OSError(errno.ENOSPC, "No space left on device")

    with opened("faiss", tmp_path) as b:
        monkeypatch.setattr(faiss_folder, "Store", full_store)
        with pytest.raises(Unavailable, match="cannot be created.*free disk space") as err:
            b.create("town", "flat")
        assert err.value.code == "storage_full" and err.value.status == 503
        assert err.value.headers["Retry-After"] == "30"  # an operator must free disk first
        assert not list((tmp_path / "data" / "maps").glob(".create-*"))
        monkeypatch.setattr(faiss_folder, "Store", real_store)
        m, created = b.create("town", "flat")
        assert created
        m.insert([row(i, np.random.default_rng(i)) for i in range(3)])
        monkeypatch.setattr(faiss_map, "write_snapshot", full_write)
        with pytest.raises(Unavailable, match="snapshot was not written") as err:
            m.snapshot()
        assert err.value.code == "storage_full"
        assert m.count == 3
        assert len(m.search(row(0, np.random.default_rng(0)).descriptor, 1, Filters())) == 1
        monkeypatch.undo()


def test_paths_with_uri_characters_are_files_not_uri_parts(tmp_path):
    """A ``#`` or ``?`` in a folder or a backup's name: SQLite must open that file, not read
    the rest as a URI fragment (and create a stray file at the cut). And a backup's folder
    that cannot be made is a BackupError, one line in the CLI, not a traceback."""
    root = tmp_path / "om#1?x"
    with opened("faiss", root) as b:
        b.create("town", "flat")[0].insert([row(i, np.random.default_rng(i)) for i in range(4)])
    with opened("faiss", root) as b:  # its stores reopened read-write and read
        assert b.get("town").count == 4
    out = tmp_path / "bk" / "town#1.sqlite"
    assert backup.export_map(root / "data", "town", out)["keyframes"] == 4
    assert backup.import_map(tmp_path / "d2", "copy", out)["keyframes"] == 4
    names = {p.name for p in out.parent.iterdir()}
    assert "town" not in names and all(n.startswith("town#1.sqlite") for n in names), names
    (tmp_path / "a-file").write_text("")
    with pytest.raises(backup.BackupError, match="cannot write"):
        backup.export_map(root / "data", "town", tmp_path / "a-file" / "town.sqlite")


@pytest.mark.skipif(not hasattr(os, "setuid") or os.geteuid() != 0, reason="needs root to drop")
def test_an_account_that_may_only_read_exports_and_imports():
    """A backup account that may read the data folder and the backups, not write beside
    them. SQLite reads a WAL-mode file by making files next to it: an export (left in WAL
    mode) was "damaged or not a map export" to such an account, a stopped service's store
    "cannot be read", and where the account could write, an import left -shm and -wal
    files beside the user's backup. An export is now a file of its own, and a store with
    no write-ahead log left is read as the file it is."""
    import shutil
    import tempfile
    from pathlib import Path

    tmp_path = Path(tempfile.mkdtemp())  # pytest's own folder is the owner's alone
    os.chmod(tmp_path, 0o755)
    try:
        _read_only_account(tmp_path)
    finally:
        shutil.rmtree(tmp_path, ignore_errors=True)


def _read_only_account(tmp_path) -> None:  # type: ignore[no-untyped-def]
    with opened("faiss", tmp_path) as b:
        m, _ = b.create("town", "flat")
        m.insert([row(i, np.random.default_rng(i)) for i in range(5)])
    out = tmp_path / "bk" / "town.sqlite"
    backup.export_map(tmp_path / "data", "town", out)
    assert out.read_bytes()[18:20] == b"\x01\x01"  # rollback journal, not WAL
    backup.import_map(tmp_path / "again", "town", out)
    assert sorted(p.name for p in out.parent.iterdir()) == ["town.sqlite"]  # nothing beside
    for folder in (out.parent, tmp_path / "data", tmp_path / "data" / "maps"):
        os.chmod(folder, 0o555)
    os.chmod(tmp_path / "data" / "maps" / "town", 0o555)
    restore = tmp_path / "restore"
    restore.mkdir(mode=0o777)
    os.chmod(restore, 0o777)
    pid = os.fork()
    if pid == 0:  # the backup account: nobody
        code = 1
        try:
            os.setgid(65534)
            os.setuid(65534)
            got = backup.import_map(restore / "data", "town", out)
            made = backup.export_map(tmp_path / "data", "town", restore / "copy.sqlite")
            code = 0 if got["keyframes"] == 5 and made["keyframes"] == 5 else 3
        except Exception as err:  # reported through the exit code
            print(err, flush=True)
        finally:
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    for folder in (out.parent, tmp_path / "data", tmp_path / "data" / "maps"):
        os.chmod(folder, 0o755)
    os.chmod(tmp_path / "data" / "maps" / "town", 0o755)
    assert os.waitstatus_to_exitcode(status) == 0
    assert sorted(p.name for p in out.parent.iterdir()) == ["town.sqlite"]


def test_export_and_import_take_the_services_data_folder_from_its_settings(tmp_path):
    """``export-map`` and ``import-map`` without --data-dir looked in ./data, whatever the
    service's settings said: in the container image (OVERLAPMAMBA_DATA_DIR=/data) the
    documented commands found no map. They read the settings, as doctor does."""
    from typer.testing import CliRunner

    from overlapmamba.cli import app

    with opened("faiss", tmp_path) as b:
        m, _ = b.create("town", "flat")
        m.insert([row(i, np.random.default_rng(i)) for i in range(3)])
    runner = CliRunner()
    env = {"OVERLAPMAMBA_DATA_DIR": str(tmp_path / "data"), "COLUMNS": "200"}
    out = tmp_path / "bk" / "town.sqlite"
    res = runner.invoke(app, ["export-map", "town", str(out)], env=env)
    assert res.exit_code == 0 and "3 keyframes" in res.output, res.output
    res = runner.invoke(app, ["import-map", "copy", str(out)], env=env)
    assert res.exit_code == 0, res.output
    assert (tmp_path / "data" / "maps" / "copy" / "store.sqlite").is_file()


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root: an import run as root")
def test_an_import_run_as_root_into_the_services_maps_is_refused_naming_the_user(tmp_path):
    """Found in review: import-map run by root (sudo, a container's default user) beside a
    service that runs as its own user left root's files, which that service could not write
    (the map refused at start); handing them over by path would let that user, who may
    rename entries of its own folder, point root's chown elsewhere."""
    with opened("faiss", tmp_path / "a") as b:
        m, _ = b.create("town", "flat")
        m.insert([row(i, np.random.default_rng(i)) for i in range(4)])
    src = tmp_path / "town.sqlite"
    backup.export_map(tmp_path / "a" / "data", "town", src)
    maps = tmp_path / "b" / "data" / "maps"
    maps.mkdir(parents=True)
    os.chown(maps, 10001, 10001)  # the image's service user
    with pytest.raises(backup.BackupError, match="belongs to user 10001.*--user 10001"):
        backup.import_map(tmp_path / "b" / "data", "town", src)
    assert not list(maps.iterdir())


def test_an_import_refuses_a_database_that_is_no_maps_store(tmp_path):
    """Found in review: a SQLite file of the store's schema but without a map's meta (its
    model, dimension and write count) was imported; the map's first insert then failed."""
    with opened("faiss", tmp_path) as b:
        m, _ = b.create("town", "flat")
        m.insert([row(i, np.random.default_rng(i)) for i in range(3)])
    src = tmp_path / "town.sqlite"
    backup.export_map(tmp_path / "data", "town", src)
    with contextlib.closing(sqlite3.connect(src)) as con, con:
        con.execute("DELETE FROM meta WHERE key = 'seq'")
    with pytest.raises(backup.BackupError, match="not a map export: its meta table lacks seq"):
        backup.import_map(tmp_path / "data", "copy", src)
    assert not (tmp_path / "data" / "maps" / "copy").exists()


def test_an_import_cut_off_while_moving_in_says_so_and_the_next_start_finishes_it(
    tmp_path, monkeypatch
):
    """Found in review: an error in the import's last steps (a rename) escaped as a raw
    OSError, with a traceback and no word of what was left."""
    with opened("faiss", tmp_path) as b:
        m, _ = b.create("town", "flat")
        m.insert([row(i, np.random.default_rng(i)) for i in range(3)])
    src = tmp_path / "town.sqlite"
    backup.export_map(tmp_path / "data", "town", src)
    real = os.replace

    def cut(a, b):
        if str(a).endswith(".import-copy"):
            raise OSError(5, "Input/output error")
        return real(a, b)

    monkeypatch.setattr(backup.os, "replace", cut)
    with pytest.raises(backup.BackupError, match="cut off while moving it in .*finishes it"):
        backup.import_map(tmp_path / "data", "copy", src)
    monkeypatch.undo()
    with opened("faiss", tmp_path) as b:
        assert b.get("copy").count == 3


def test_an_import_whose_old_map_cannot_move_away_leaves_it_as_it_was(tmp_path, monkeypatch):
    """Found in the evening's review: the first rename (the old map away) failing said the
    next start would finish the import, which that start then cleared as debris."""
    with opened("faiss", tmp_path) as b:
        m, _ = b.create("town", "flat")
        m.insert([row(i, np.random.default_rng(i)) for i in range(3)])
    src = tmp_path / "town.sqlite"
    backup.export_map(tmp_path / "data", "town", src)
    with opened("faiss", tmp_path) as b:
        b.get("town").insert([row(9, np.random.default_rng(9))])  # the map moves on
    real = os.replace

    def busy(a, b):
        if str(b).split("/")[-1].startswith(".trash-town"):
            raise OSError(16, "Device or resource busy")
        return real(a, b)

    monkeypatch.setattr(backup.os, "replace", busy)
    with pytest.raises(backup.BackupError, match="could not be moved away .* it is as it was"):
        backup.import_map(tmp_path / "data", "town", src, replace=True)
    monkeypatch.undo()
    assert not list((tmp_path / "data" / "maps").glob(".import-*"))
    with opened("faiss", tmp_path) as b:
        assert b.get("town").count == 4


def test_a_service_starting_while_doctor_looks_at_the_lock_waits_for_it(tmp_path):
    """``doctor`` takes the data folder's lock for a moment to see whether a service holds
    it; a service started in that moment was refused as if another service ran there. A
    lock let go within ``wait_s`` is waited for; one held longer is still refused."""
    import fcntl
    import threading

    data = tmp_path / "d"
    data.mkdir()
    fd = os.open(data / backup.LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # doctor's probe, let go in 0.3 s
        threading.Timer(0.3, fcntl.flock, (fd, fcntl.LOCK_UN)).start()
        with backup.data_dir_lock(data):
            pass
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # a service's, held on
        held = pytest.raises(backup.BackupError, match="in use by a running service")
        with held, backup.data_dir_lock(data, wait_s=0.2):
            pass
    finally:
        os.close(fd)


def test_a_folder_given_for_a_file_or_a_file_for_the_data_folder_is_named_as_such(tmp_path):
    """Found in review: a folder given as the config file or as the backup to import, and a
    file given as the data folder, were each reported as missing."""
    from overlapmamba.service.doctor import diagnose
    from overlapmamba.service.settings import load_settings

    folder, afile = tmp_path / "folder", tmp_path / "afile"
    folder.mkdir()
    afile.write_text("")
    with pytest.raises(ValueError, match="is a folder; allowed: a TOML file"):
        load_settings(folder)
    with pytest.raises(backup.BackupError, match="is a folder; allowed: a map's backup"):
        backup.import_map(tmp_path / "data", "m", folder)
    (finding,) = diagnose(afile).findings
    assert finding.status == "error" and finding.message == f"{afile} is not a folder"
