"""Operations: JSON logs with request ids, graceful shutdown (drain, then snapshot), the
doctor, and the Qdrant backend behind a real server across a SIGKILL."""

from __future__ import annotations

import json
import logging
import shutil
import signal
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from service_kit import MODEL, OCTET, running, scan, server, server_log

from overlapmamba.service.backends.faiss.map import FaissMap
from overlapmamba.service.doctor import diagnose
from overlapmamba.service.domain import NewKeyframe
from overlapmamba.service.encoder import Encoder
from overlapmamba.service.logs import JsonFormatter, new_request_id, request_id
from overlapmamba.service.settings import IndexSettings, Settings

ROOT = Path(__file__).resolve().parents[1]


def _unit(rng: np.random.Generator) -> list[float]:
    v = rng.normal(size=256)
    return (v / np.linalg.norm(v)).tolist()


# ---- logs ---------------------------------------------------------------------------------


def test_json_lines_carry_the_request_id_and_extra_fields():
    record = logging.LogRecord("overlapmamba.x", logging.WARNING, "f", 1, "hi %s", ("there",), None)
    record.status = 201
    token = request_id.set("abc-1")
    try:
        line = json.loads(JsonFormatter().format(record))
    finally:
        request_id.reset(token)
    assert line["msg"] == "hi there" and line["level"] == "warning"
    assert line["request_id"] == "abc-1" and line["status"] == 201
    assert line["ts"].endswith("Z") and line["logger"] == "overlapmamba.x"
    assert new_request_id("robot-7:frame.12") == "robot-7:frame.12"
    for hostile in ("a\nb", "x" * 200, "", "sp ace", '"}{'):
        assert new_request_id(hostile) != hostile and len(new_request_id(hostile)) == 32


@pytest.mark.anyio
async def test_every_response_has_a_request_id_and_an_access_line(tmp_path):
    lines: list[logging.LogRecord] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            record.request_id = request_id.get()
            lines.append(record)

    access = logging.getLogger("overlapmamba.access")
    keep = Keep(level=logging.DEBUG)
    access.addHandler(keep)
    old = access.level
    access.setLevel(logging.DEBUG)
    try:
        enc = Encoder(MODEL, intra_op_threads=2)
        async with running(Settings(data_dir=tmp_path / "d"), enc) as c:
            r = await c.put("/v1/maps/town", headers={"x-request-id": "mapper-42"})
            assert r.status_code == 201 and r.headers["x-request-id"] == "mapper-42"
            r = await c.get("/v1/maps/nope", headers={"x-request-id": "bad\tid"})
            assert r.status_code == 404 and len(r.headers["x-request-id"]) == 32
            big = await c.post(
                "/v1/descriptors", content=b"x", headers={**OCTET, "content-length": str(1 << 40)}
            )
            assert big.status_code == 413 and big.headers["x-request-id"]
    finally:
        access.removeHandler(keep)
        access.setLevel(old)
    got = [(x.request_id, x.status, x.path) for x in lines]  # type: ignore[attr-defined]
    assert ("mapper-42", 201, "/v1/maps/town") in got
    assert (r.headers["x-request-id"], 404, "/v1/maps/nope") in got
    assert all(isinstance(x.duration_ms, float) for x in lines)  # type: ignore[attr-defined]


@pytest.mark.anyio
async def test_a_streamed_body_over_the_limit_is_a_413_on_every_route(tmp_path):
    # a chunked body (no Content-Length) crosses the limit while it streams in; the routes
    # that let FastAPI parse their JSON (PUT /v1/maps/{id}) used to answer 400 "error parsing
    # the body", the routes that read their own body 413
    from overlapmamba.service.settings import LimitSettings

    settings = Settings(data_dir=tmp_path / "d", limits=LimitSettings(max_body_bytes=4096))

    async def chunks(pad: int):  # type: ignore[no-untyped-def]
        yield b'{"keep_geometry": false'
        for _ in range(pad):  # JSON whitespace, so the body stays valid at any length
            yield b" " * 1024
        yield b"}"

    json_type = {"content-type": "application/json"}
    enc = Encoder(MODEL, intra_op_threads=2)
    async with running(settings, enc) as c:
        r = await c.put("/v1/maps/town", content=chunks(8), headers=json_type)
        assert r.status_code == 413, r.text
        assert r.json()["error"]["code"] == "payload_too_large" and r.headers["x-request-id"]
        assert r.json()["error"]["detail"] == {"max_body_bytes": 4096}
        r = await c.post("/v1/descriptors", content=chunks(8), headers=OCTET)
        assert r.status_code == 413, r.text
        assert (await c.get("/v1/maps/town")).status_code == 404  # nothing was made of it
        # under the limit the same body, streamed the same way, creates the map
        ok = await c.put("/v1/maps/town", content=chunks(2), headers=json_type)
        assert ok.status_code == 201 and ok.json()["keep_geometry"] is False, ok.text
        # one refused by its Content-Length, before routing, is counted under its route too
        big = await c.post("/v1/descriptors", content=bytes(5000), headers=OCTET)
        assert big.status_code == 413
        text = (await c.get("/metrics")).text
    counted = {
        line.rsplit(" ", 1)[0]: float(line.split()[-1])
        for line in text.splitlines()
        if line.startswith("overlapmamba_requests_total{")
    }
    key = 'overlapmamba_requests_total{{route="{}",status="413"}}'.format
    assert counted[key("/v1/maps/{map_id}")] == 1, counted
    assert counted[key("/v1/descriptors")] == 1, counted
    assert counted[key("(before routing)")] == 1, counted  # its Content-Length said


# ---- graceful shutdown ----------------------------------------------------------------------


def test_sigterm_drains_requests_in_flight_then_snapshots(tmp_path):
    data = tmp_path / "data"
    rng = np.random.default_rng(3)
    # the largest batch (64 scans, limits.max_batch_scans): over a second of encoding even on
    # the C-kernel path (≈ 25 ms a scan), so it is in flight when the signal arrives at 0.4 s
    scans = [scan(i).tobytes() for i in range(64)]
    batch = b"".join(struct.pack("<I", len(s)) + s for s in scans)
    result: dict[str, object] = {}
    with (
        server(data, {"OVERLAPMAMBA_SHUTDOWN_DELAY_S": "1.5"}) as (url, proc),
        httpx.Client(base_url=url, timeout=60) as c,
    ):
        assert c.put("/v1/maps/town").status_code == 201
        model_id = c.get("/readyz").json()["detail"]["model_id"]
        for i in range(20):
            kf = {"keyframe_id": f"k{i}", "timestamp": float(i), "descriptor": _unit(rng)}
            body = {"model_id": model_id, "keyframes": [kf]}
            r = c.post("/v1/maps/town/keyframes:batch", json=body)
            assert r.status_code == 200, r.text

        def slow() -> None:
            r = httpx.post(
                f"{url}/v1/descriptors:batch",
                content=batch,
                headers={"content-type": "application/x-scan-batch"},
                timeout=60,
            )
            result["status"] = r.status_code
            result["n"] = len(r.json().get("descriptors", []))

        t = threading.Thread(target=slow)
        t.start()
        time.sleep(0.4)
        proc.send_signal(signal.SIGTERM)
        time.sleep(0.2)
        # the shutdown delay: not ready any more (load balancers stop sending), still serving
        ready = c.get("/readyz")
        assert ready.status_code == 503 and ready.json()["status"] == "draining"
        assert c.get("/v1/maps/town").status_code == 200
        t.join(60)
        proc.wait(60)
        out = server_log(proc).encode()
    assert result == {"status": 200, "n": 64}, out.decode()[-3000:]
    # the stop asked for is done: 0, not 143 (uvicorn raised SIGTERM again, as if killed)
    assert proc.returncode == 0, (proc.returncode, out.decode()[-2000:])
    log = [json.loads(line) for line in out.decode().splitlines() if line.startswith("{")]
    msgs = [x["msg"] for x in log]
    drain = next(i for i, m in enumerate(msgs) if m.startswith("signal 15: /readyz is 503"))
    served = next(i for i, m in enumerate(msgs) if m == "POST /v1/descriptors:batch 200")
    stopped = next(i for i, m in enumerate(msgs) if m.startswith("stopped: faiss maps closed"))
    assert drain < served < stopped  # the request finished during the drain
    # the final snapshot holds every write: nothing to replay on the next start
    report = diagnose(data, model_id=Encoder(MODEL).model_id)
    snap = next(f for f in report.findings if f.check == "snapshot")
    assert report.healthy and snap.status == "ok" and snap.data["writes_since"] == 0, report


# ---- the doctor -----------------------------------------------------------------------------


def _map_with_rows(root: Path, n: int, *, model_id: str = "m1") -> FaissMap:
    s = IndexSettings(kind="flat", snapshot_every=10_000)
    folder = root / "maps" / "town"
    m = FaissMap.create("town", folder, model_id=model_id, dim=8, kind="flat", settings=s)
    rng = np.random.default_rng(0)
    vecs = rng.normal(size=(n, 8))
    vecs = (vecs / np.linalg.norm(vecs, axis=1, keepdims=True)).astype(np.float32)
    rows = [
        NewKeyframe(f"k{i}", "r", "s", float(i), None, vecs[i], None, f"h{i}") for i in range(n)
    ]
    m.insert(rows)
    return m


def _by_check(report, check: str):
    return [f for f in report.findings if f.check == check]


def test_doctor_finds_what_is_wrong_with_a_data_folder(tmp_path):
    root = tmp_path / "data"
    m = _map_with_rows(root, 12)
    m.snapshot()
    m.delete("k0")
    unit = np.full(8, 8**-0.5, np.float32)
    m.insert([NewKeyframe("k99", "r", "s", 99.0, None, unit, None, "h99")])
    m.close()
    report = diagnose(root, model_id="m1", dim=8)
    assert report.healthy, report.to_json()
    (snap,) = _by_check(report, "snapshot")
    assert snap.status == "ok" and snap.data["writes_since"] == 2
    (index,) = _by_check(report, "index")
    assert index.status == "ok" and index.data["vectors"] == 12
    assert _by_check(report, "store")[0].data["keyframes"] == 12

    # another model's service must not serve this folder
    wrong = diagnose(root, model_id="m2", dim=8)
    assert not wrong.healthy and _by_check(wrong, "model")[0].status == "error"

    # an old snapshot with writes since, a torn temporary file, debris: warnings
    folder = root / "maps" / "town"
    (folder / "index.snap.tmp").write_bytes(b"half a snapsh")
    (root / "maps" / ".trash-old-1").mkdir()
    report = diagnose(root, model_id="m1", dim=8, max_snapshot_age_s=0)
    assert report.healthy
    statuses = {(f.check, f.status) for f in report.findings}
    assert ("snapshot", "warn") in statuses and ("debris", "warn") in statuses
    assert sum(f.check == "snapshot" and "torn" in f.message for f in report.findings) == 1

    # a snapshot that does not match the store is an error (here: another map's snapshot)
    other = _map_with_rows(tmp_path / "other", 3)
    other.snapshot()
    other.close()
    shutil.copy(tmp_path / "other" / "maps" / "town" / "index.snap", folder / "index.snap")
    bad = diagnose(root, model_id="m1", dim=8)
    (idx,) = _by_check(bad, "index")
    assert idx.status == "error" and "holds 3 vectors" in idx.message
    assert not bad.healthy

    # an unreadable snapshot costs a rebuild on the next start, not data
    (folder / "index.snap").write_bytes(b"garbage" * 10)
    report = diagnose(root, model_id="m1", dim=8)
    assert report.healthy and not _by_check(report, "index")
    assert any("unreadable" in f.message for f in _by_check(report, "snapshot"))
    # and the doctor wrote nothing: the folder is as it was
    assert (folder / "index.snap").read_bytes() == b"garbage" * 10

    # a store that is not a database is an error
    (root / "maps" / "broken").mkdir()
    (root / "maps" / "broken" / "store.sqlite").write_bytes(b"not sqlite" * 100)
    report = diagnose(root, model_id="m1", dim=8)
    assert not report.healthy
    assert any(f.map_id == "broken" and f.status == "error" for f in report.findings)


def test_doctor_cli_exit_code_and_json(tmp_path):
    root = tmp_path / "data"
    _map_with_rows(root, 4).close()
    cmd = [sys.executable, "-m", "overlapmamba", "doctor", "--data-dir", str(root)]
    res = subprocess.run([*cmd, "--json"], cwd=ROOT, capture_output=True, text=True)
    # the map was built by "model" m1; the configured (shipped) model is another one
    assert res.returncode == 1, res.stdout + res.stderr
    body = json.loads(res.stdout)
    assert body["healthy"] is False
    assert any(f["check"] == "model" and f["status"] == "error" for f in body["findings"])
    # a model named on the command line that is not there (a typo) or not an encoder: an
    # error finding (exit 1), never a traceback and never "healthy"
    (tmp_path / "text.onnx").write_text("not a model")
    for name, says in (("none.onnx", "not found"), ("text.onnx", "cannot be loaded")):
        res = subprocess.run(
            [*cmd, "--model", str(tmp_path / name)], cwd=ROOT, capture_output=True, text=True
        )
        out = " ".join(res.stdout.split())
        assert res.returncode == 1 and says in out and "ids not checked" in out, out
        assert "Traceback" not in res.stdout + res.stderr, res.stderr


# ---- Qdrant behind a real server --------------------------------------------------------------


def test_qdrant_backend_serves_and_survives_sigkill(tmp_path):
    env = {
        "OVERLAPMAMBA_INDEX__BACKEND": "qdrant",
        "OVERLAPMAMBA_QDRANT__PATH": str(tmp_path / "qdrant"),
    }
    rng = np.random.default_rng(5)
    acked: dict[str, list[float]] = {}
    with (
        server(tmp_path / "data", env) as (url, proc),
        httpx.Client(base_url=url, timeout=30) as c,
    ):
        ready = c.get("/readyz").json()["detail"]
        assert ready["backend"] == "qdrant"
        assert c.put("/v1/maps/town").status_code == 201
        r = c.post(
            "/v1/maps/town/keyframes",
            content=scan(0).tobytes(),
            params={"keyframe_id": "scan0", "timestamp": 0.0, "robot_id": "r1", "session_id": "s"},
            headers=OCTET,
        )
        assert r.status_code == 201, r.text
        for i in range(30):
            d = _unit(rng)
            kf = {"keyframe_id": f"k{i}", "timestamp": float(i + 1), "descriptor": d}
            body = {"model_id": ready["model_id"], "keyframes": [kf]}
            if c.post("/v1/maps/town/keyframes:batch", json=body).status_code == 200:
                acked[f"k{i}"] = d
        proc.kill()
        proc.wait()
    with (
        server(tmp_path / "data", env) as (url, _),
        httpx.Client(base_url=url, timeout=30) as c,
    ):
        assert c.get("/v1/maps/town").json()["keyframes"] == len(acked) + 1
        for kid, d in list(acked.items())[::7]:
            top = c.post("/v1/maps/town/query", params={"k": 1}, json={"descriptor": d}).json()
            assert top["matches"][0]["keyframe_id"] == kid
        # the turned scan finds its keyframe, with the turn, from the yaw features in Qdrant
        r = c.post("/v1/maps/town/query", content=scan(0, 40.0).tobytes(), headers=OCTET).json()
        best = r["matches"][0]
        assert best["keyframe_id"] == "scan0" and abs(best["yaw_deg"] - 40.0) < 3.0


def test_doctor_reads_the_whole_store_not_only_its_counts(tmp_path):
    """Found in review: a store whose newest rows' page was damaged passed the doctor (its
    counts read the index alone), and the service then refused to open it."""
    import sqlite3

    root = tmp_path / "data"
    m = _map_with_rows(root, 200)
    m.snapshot()
    unit = np.full(8, 8**-0.5, np.float32)
    m.insert(
        [NewKeyframe(f"n{i}", "r", "s", 1e3 + i, None, unit, None, f"n{i}") for i in range(60)]
    )
    m.close()
    store = root / "maps" / "town" / "store.sqlite"
    assert diagnose(root, model_id="m1", dim=8).healthy
    with sqlite3.connect(store) as con:
        con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        (page,) = con.execute(
            "SELECT pageno FROM dbstat WHERE name = 'keyframes' AND pagetype = 'leaf' "
            "ORDER BY path DESC LIMIT 1"
        ).fetchone()
        size = con.execute("PRAGMA page_size").fetchone()[0]
    con.close()
    with open(store, "r+b") as f:  # the newest rows' page, as a failing disk leaves it
        f.seek((page - 1) * size)
        f.write(bytes(size))
    report = diagnose(root, model_id="m1", dim=8)
    assert not report.healthy
    (found,) = [f for f in _by_check(report, "store") if f.status == "error"]
    assert "damaged" in found.message and "import-map" in found.message


def test_a_snapshot_damaged_on_disk_is_rebuilt_and_the_doctor_says_so(tmp_path):
    """Found in review: a flipped vector inside index.snap was loaded as it was (that
    keyframe no longer found) and passed the doctor; the header's CRC-32 now catches it."""
    from overlapmamba.service.domain import Filters

    root = tmp_path / "data"
    m = _map_with_rows(root, 30)
    m.snapshot()
    target = m.store.descriptor("k0")
    m.close()
    snap = root / "maps" / "town" / "index.snap"
    data = bytearray(snap.read_bytes())
    at = bytes(data).find(target.tobytes())
    assert at > 0
    data[at : at + 32] = np.full(8, -(8**-0.5), np.float32).tobytes()  # k0's vector, turned
    snap.write_bytes(bytes(data))
    report = diagnose(root, model_id="m1", dim=8)
    (found,) = _by_check(report, "snapshot")
    assert found.status == "warn" and "rebuilds the index" in found.message
    m = FaissMap.open("town", root / "maps" / "town", IndexSettings(kind="flat"))
    try:
        assert m.search(target, 1, Filters())[0].keyframe.keyframe_id == "k0"
    finally:
        m.close()


def test_the_doctor_names_an_import_cut_off_between_its_renames(tmp_path):
    """Found in review: a whole import left as .import-<id> (its map folder already moved
    away) was called debris to be removed, where the next start installs it as the map."""
    from overlapmamba.service.backends.faiss.store import IMPORTED_MARK

    root = tmp_path / "data"
    _map_with_rows(root, 5).close()
    (root / "maps" / "town").rename(root / "maps" / ".import-town")
    (root / "maps" / ".import-town" / IMPORTED_MARK).touch()
    (found,) = _by_check(diagnose(root, model_id="m1", dim=8), "import")
    assert found.map_id == "town" and "installs it as map 'town'" in found.message


def test_a_librarys_warning_is_a_json_log_line(capsys):
    """Found in review: Qdrant's client warns (an API key over http) with Python's warnings,
    which printed a raw line among the JSON ones; a log shipper could not parse it. The
    service's logging takes warnings as records."""
    import warnings

    from overlapmamba.service import logs

    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    try:
        logs.configure("info", "json")
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            warnings.warn("Api key is used with an insecure connection.", UserWarning, stacklevel=1)
        lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
        assert lines and all(json.loads(ln) for ln in lines), lines
        assert any("insecure connection" in json.loads(ln)["msg"] for ln in lines), lines
    finally:
        logging.captureWarnings(False)
        for h in list(root.handlers):
            root.removeHandler(h)
        for h in handlers:
            root.addHandler(h)
        root.setLevel(level)
