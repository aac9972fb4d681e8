"""``overlapmamba doctor``: is a data folder (the ``faiss`` backend's) sound? (For the
``qdrant`` backend, :func:`diagnose_backend` checks the server and the maps' models.)

Per map, read-only (SQLite opened ``mode=ro``; nothing is rebuilt or written):

    store      opens; its schema and metadata (model id, dimension) are there
    index      the snapshot holds exactly the keyframes the store had alive at the
               snapshot's seq (so snapshot + replay = the store); read in one transaction
    snapshot   readable; its age and the writes since (what the next start replays)
    model      the map's model id is the served model's, and the dimensions agree
               (descriptors of two models are not comparable and never share a map)

and for the folder: leftovers of interrupted operations (``.trash-*``, ``.import-*``,
``.create-*`` folders; a torn ``index.snap.tmp``), and whether a service holds it now.

Safe while the service runs: SQLite readers do not block its writer, and the counts are
one transaction's consistent view. Each finding is ``ok``, ``warn`` (works, but look) or
``error`` (broken: the exit code is 1).
"""

from __future__ import annotations

import fcntl
import json
import os
import struct
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

from overlapmamba.service.backends.base import MapBackend
from overlapmamba.service.backends.faiss.snapshot import SNAPSHOT_MAGIC, read_snapshot
from overlapmamba.service.backends.faiss.store import IMPORTED_MARK, Store
from overlapmamba.service.backup import LOCK_NAME
from overlapmamba.service.domain import MAP_ID
from overlapmamba.service.errors import ServiceError
from overlapmamba.service.settings import IndexSettings

Status = Literal["ok", "warn", "error"]


@dataclass
class Finding:
    map_id: str | None
    check: str
    status: Status
    message: str
    data: dict[str, Any] = field(default_factory=dict)


@dataclass
class Report:
    data_dir: str
    model_id: str | None
    findings: list[Finding] = field(default_factory=list)

    def add(
        self, map_id: str | None, check: str, status: Status, message: str, **data: Any
    ) -> None:
        self.findings.append(Finding(map_id, check, status, message, data))

    @property
    def healthy(self) -> bool:
        return all(f.status != "error" for f in self.findings)

    def to_json(self) -> str:
        return json.dumps(
            {"data_dir": self.data_dir, "model_id": self.model_id, "healthy": self.healthy}
            | {"findings": [asdict(f) for f in self.findings]},
            indent=2,
        )


def diagnose(
    data_dir: Path,
    *,
    model_id: str | None = None,
    dim: int | None = None,
    max_snapshot_age_s: float = 24 * 3600,
    settings: IndexSettings | None = None,
) -> Report:
    data_dir = Path(data_dir)
    report = Report(str(data_dir), model_id)
    root = data_dir / "maps"
    if not root.is_dir():
        why = (
            f"{data_dir} is not a folder"
            if data_dir.exists() and not data_dir.is_dir()
            else f"{root} does not exist: no maps here"
        )
        report.add(None, "data_dir", "error", why)
        return report
    _check_lock(report, data_dir)
    settings = settings or IndexSettings()  # type: ignore[call-arg]
    models: dict[str, str] = {}
    for folder in sorted(root.iterdir()):
        imported = folder.name.removeprefix(".import-")
        if (
            folder.name.startswith(".import-")
            and MAP_ID.fullmatch(imported)
            and (folder / IMPORTED_MARK).exists()
            and not (root / imported).exists()
        ):  # FaissBackend._finish_imports: the next start moves it in, as the map
            report.add(
                imported,
                "import",
                "warn",
                f"{folder.name}: a whole import of map {imported!r} cut off before it was "
                f"moved in; the next start installs it as map {imported!r}: keep it",
            )
        elif folder.name.startswith((".trash-", ".import-", ".create-")):
            report.add(
                None,
                "debris",
                "warn",
                f"{folder.name}: left by an interrupted operation; the next start removes it",
            )
        elif folder.is_dir() and MAP_ID.fullmatch(folder.name):
            mid = _check_map(report, folder, model_id, dim, max_snapshot_age_s, settings)
            if mid is not None:
                models[folder.name] = mid
    if not models and not any(f.status == "error" for f in report.findings):
        report.add(None, "maps", "ok", "no maps yet")
    if len(set(models.values())) > 1:
        report.add(
            None,
            "model",
            "warn",
            "maps of different models in one folder: one service can serve only one of them",
            models=models,
        )
    return report


def _check_lock(report: Report, data_dir: Path) -> None:
    lock = data_dir / LOCK_NAME
    if not lock.exists():
        report.add(None, "lock", "ok", "no service has run here yet")
        return
    fd = os.open(lock, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        fcntl.flock(fd, fcntl.LOCK_UN)
        report.add(None, "lock", "ok", "no service holds this folder now")
    except BlockingIOError:
        report.add(
            None, "lock", "ok", "a service is running on this folder: figures are a moment's view"
        )
    finally:
        os.close(fd)


def _check_map(
    report: Report,
    folder: Path,
    model_id: str | None,
    dim: int | None,
    max_age_s: float,
    settings: IndexSettings,
) -> str | None:
    map_id = folder.name
    if not (folder / "store.sqlite").is_file():
        report.add(map_id, "store", "warn", "a folder without store.sqlite: not a map (debris)")
        return None
    try:
        store = Store(folder / "store.sqlite", readonly=True)
        meta_model = store.get_meta("model_id")
        meta_dim = int(store.get_meta("dim") or 0)
    except Exception as err:
        report.add(map_id, "store", "error", f"the store cannot be read: {err}")
        return None
    try:
        damaged = store.problems()
        if damaged:  # a count reads the index alone: the rows a start replays may be gone
            report.add(
                map_id,
                "store",
                "error",
                f"the store is damaged (SQLite's quick_check: {'; '.join(damaged)[:300]}); the "
                "service cannot open it: restore the map from an export (import-map)",
                problems=damaged,
            )
            return meta_model
        last, live, _ = store.census(0)
        report.add(map_id, "store", "ok", f"{live} keyframes, seq {last}", keyframes=live, seq=last)
        if not meta_model or not meta_dim:
            report.add(map_id, "model", "error", "the store has no model id or dimension")
        elif model_id is not None and meta_model != model_id:
            report.add(
                map_id,
                "model",
                "error",
                f"built with model {meta_model}; the model given is {model_id}: the service "
                "would refuse this map's queries and inserts (409). Re-index it, or serve "
                "its model",
                map_model_id=meta_model,
            )
        elif dim is not None and meta_dim != dim:
            report.add(map_id, "model", "error", f"dimension {meta_dim}, the model's is {dim}")
        else:
            report.add(map_id, "model", "ok", f"model {meta_model}", map_model_id=meta_model)
        _check_index(report, folder, store, meta_dim, max_age_s, settings)
    except Exception as err:
        report.add(map_id, "store", "error", f"the store cannot be read: {err}")
    finally:
        store.close()
    return meta_model


def _check_index(
    report: Report, folder: Path, store: Store, dim: int, max_age_s: float, s: IndexSettings
) -> None:
    """The snapshot must hold exactly the keyframes the store had alive at its seq; a start
    then replays the writes after it. Read in one transaction: exact while a service runs."""
    map_id = folder.name
    if (folder / "index.snap.tmp").exists():
        report.add(
            map_id,
            "snapshot",
            "warn",
            "a torn index.snap.tmp (a snapshot cut off mid-write): ignored on start, "
            "overwritten by the next snapshot",
        )
    path = folder / "index.snap"
    if not path.exists():
        last, live, _ = store.census(0)
        report.add(
            map_id,
            "snapshot",
            "warn" if last else "ok",
            f"no snapshot: the next start indexes all {live} keyframes from the store",
        )
        return
    index, seq = read_snapshot(path, dim, s)
    if index is None:
        report.add(
            map_id,
            "snapshot",
            "warn",
            "the snapshot is unreadable: the next start rebuilds the index from the store",
            header=_header(path),
        )
        return
    age = time.time() - path.stat().st_mtime
    last, live, expected = store.census(seq)
    behind = last - seq
    data = {"seq": seq, "age_s": round(age, 1), "writes_since": behind}
    if index.ntotal != expected:
        report.add(
            map_id,
            "index",
            "error",
            f"the snapshot at seq {seq} holds {index.ntotal} vectors; the store had "
            f"{expected} keyframes then. Delete index.snap: the next start rebuilds it",
            vectors=index.ntotal,
            keyframes_at_seq=expected,
        )
        return
    report.add(
        map_id,
        "index",
        "ok",
        f"snapshot ({index.kind}) holds {index.ntotal} vectors = the store at seq {seq}; a "
        f"start replays {behind} writes to reach {live}",
        vectors=index.ntotal,
    )
    if behind and age > max_age_s:
        report.add(
            map_id,
            "snapshot",
            "warn",
            f"{age / 3600:.1f} h old with {behind} writes since: a restart replays them; "
            "POST /v1/maps/{id}/snapshot",
            **data,
        )
    else:
        report.add(
            map_id, "snapshot", "ok", f"seq {seq}, {age:.0f} s old, {behind} writes since", **data
        )


def _header(path: Path) -> str:
    with open(path, "rb") as f:
        head = f.read(4096)
    if head[:8] != SNAPSHOT_MAGIC:
        return "not a snapshot file"
    (n,) = struct.unpack("<I", head[8:12])
    return head[12 : 12 + n].decode(errors="replace")


def diagnose_backend(backend: MapBackend, *, model_id: str | None, dim: int | None) -> Report:
    """The ``qdrant`` backend has no data folder: check it answers and every map's model."""
    report = Report(backend.name, model_id)
    try:
        where = backend.describe()
        maps = backend.snapshot_list()
    except ServiceError as err:
        report.add(None, "backend", "error", err.message)
        return report
    report.add(None, "backend", "ok", f"{backend.name} answers", **where)
    for m in maps:
        if model_id is not None and m.model_id != model_id:
            report.add(
                m.map_id,
                "model",
                "error",
                f"built with model {m.model_id}; the model given is {model_id}",
                map_model_id=m.model_id,
            )
        elif dim is not None and m.dim != dim:
            report.add(m.map_id, "model", "error", f"dimension {m.dim}, the model's is {dim}")
        else:
            report.add(m.map_id, "model", "ok", f"model {m.model_id}")
        report.add(m.map_id, "index", "ok", f"{m.count} keyframes")
    return report
