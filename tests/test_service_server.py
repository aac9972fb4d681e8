"""Against a real `overlapmamba serve` process: the WebSocket stream, SIGKILL durability,
backup and restore, and the refusal to listen openly without keys."""

from __future__ import annotations

import json
import signal
import sqlite3
import subprocess
import sys
import threading
import time
import tomllib

import httpx
import numpy as np
import onnx
import pytest
from service_kit import MODEL, OCTET, ROOT, scan, server
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from overlapmamba.service import backup

pytestmark = pytest.mark.slow


def _meta(ts: float, **extra: object) -> str:
    return json.dumps({"seq": ts, "timestamp": ts, "pose": f"{ts},0,0,0,0,0,1", **extra})


def test_stream_sigkill_durability_and_backup(tmp_path, encoder):
    data = tmp_path / "data"
    env = {"OVERLAPMAMBA_OBSERVE__STREAM_QUEUE": "3", "OVERLAPMAMBA_INDEX__SNAPSHOT_EVERY": "25"}
    rng = np.random.default_rng(0)
    acked: dict[str, list[float]] = {}
    with server(data, env) as (url, proc):
        c = httpx.Client(base_url=url, timeout=30)
        assert c.put("/v1/maps/town").status_code == 201
        ready = c.get("/readyz").json()["detail"]
        model_id = ready["model_id"]
        assert (ready["model_id"], ready["views"]) == (encoder.model_id, encoder.views)
        ws_url = url.replace("http", "ws") + "/v1/maps/town/stream?robot_id=r1&session_id=s1&k=3"

        # ---- the stream: results in order, a bad frame answered, then backpressure ----------
        with connect(ws_url) as ws:
            ws.send(_meta(0.0, insert="always"))
            ws.send(scan(0).tobytes())
            got = [json.loads(ws.recv(timeout=30))]
            ws.send(_meta(1.0))  # the next three fit in the queue of 3 even if none is done
            ws.send(b"\x00\x01\x02")  # not a whole record
            ws.send(b"orphan")  # binary without metadata
            ws.send(_meta(60.0))
            ws.send(scan(1).tobytes())
            got += [json.loads(ws.recv(timeout=30)) for _ in range(3)]
        assert [g["seq"] for g in got] == [0.0, 1.0, None, 60.0]
        assert got[0]["ok"] and got[0]["inserted"] and got[0]["insert_reason"] == "always"
        assert not got[1]["ok"] and got[1]["error"]["code"] == "undecodable_point_cloud"
        assert not got[2]["ok"] and "without a metadata frame" in got[2]["error"]["message"]
        assert got[3]["ok"] and got[3]["insert_reason"] == "time"
        assert got[3]["matches"][0]["keyframe_id"] == "r1:s1:0.0"
        acked |= {g["keyframe_id"]: [] for g in got if g.get("inserted")}

        body = scan(2).tobytes()
        with pytest.raises(ConnectionClosed) as closed, connect(ws_url) as ws:
            # far more than 3 pending, without reading: 60 scans arrive much faster than even the
            # C-kernel encoder (≈ 25 ms a scan) describes them
            for i in range(60):
                ws.send(_meta(100.0 + i, insert="never"))
                ws.send(body)
            for _ in range(60):
                ws.recv(timeout=30)
        assert closed.value.rcvd is not None and closed.value.rcvd.code == 1013
        assert "outran" in closed.value.rcvd.reason

        nope = url.replace("http", "ws") + "/v1/maps/nope/stream?robot_id=r1"
        with pytest.raises(InvalidStatus) as refused, connect(nope):
            pass  # refused as a route answers: the status, and the error naming why
        assert refused.value.response.status_code == 404
        assert json.loads(refused.value.response.body)["error"]["code"] == "map_not_found"
        # a scan frame as large as an HTTP body may be (uvicorn's own 16 MiB cap closed it)
        with connect(ws_url) as ws:
            big = np.zeros((1_100_000, 4), np.float32)
            big[:, 0] = np.linspace(2.0, 40.0, len(big), dtype=np.float32)
            ws.send(_meta(150.0, insert="never"))
            ws.send(big.tobytes())  # 17.6 MB
            answer = json.loads(ws.recv(timeout=120))
        assert answer["seq"] == 150.0 and answer["ok"] is True, answer

        # ---- the stream names its sensor: per connection, per frame; unknown ones refused ---
        # ... and where it sits (per connection, per frame)
        mounted = ws_url.replace("session_id=s1", "session_id=s2") + "&sensor=vlp16&mount=0.7"
        with connect(mounted) as ws:
            extras = [{}, {"sensor": "os1-64"}, {"sensor": "mid360"}, {"mount": "0.7,60"}]
            for i, extra in enumerate(extras):
                ws.send(_meta(200.0 + i, insert="always", **extra))
                ws.send(scan(i).tobytes())
            named = [json.loads(ws.recv(timeout=30)) for _ in range(4)]
        assert named[0]["ok"] and named[1]["ok"], named
        assert named[2]["error"]["code"] == "unknown_sensor"
        assert named[3]["error"]["code"] == "bad_mount" and "±45°" in named[3]["error"]["message"]
        kfs = [c.get(f"/v1/maps/town/keyframes/{g['keyframe_id']}").json() for g in named[:2]]
        assert [k["sensor"] for k in kfs] == ["vlp16", "os1-64"]
        acked |= {g["keyframe_id"]: [] for g in named[:2]}
        bad = url.replace("http", "ws") + "/v1/maps/town/stream?robot_id=r1&sensor=mid360"
        with pytest.raises(Exception, match="1008|unknown_sensor|rejected"), connect(bad):
            pass

        # ---- keyframes acknowledged one by one, then SIGKILL mid-stream --------------------
        stop = threading.Event()

        def insert_forever():
            i = 0
            while not stop.is_set():
                v = rng.normal(size=256)
                v /= np.linalg.norm(v)
                kf = {"keyframe_id": f"b{i}", "timestamp": float(i), "descriptor": v.tolist()}
                try:
                    r = c.post(
                        "/v1/maps/town/keyframes:batch",
                        json={"model_id": model_id, "keyframes": [kf]},
                    )
                except httpx.TransportError:
                    return
                if r.status_code == 200:
                    acked[f"b{i}"] = v.tolist()
                i += 1

        t = threading.Thread(target=insert_forever)
        t.start()
        time.sleep(2.0)
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        stop.set()
        t.join(30)
        c.close()
    assert len(acked) > 40, len(acked)
    assert (data / "maps" / "town" / "index.snap").exists()  # snapshots were taken mid-stream

    # ---- restart: every acknowledged keyframe is there and searchable -----------------------
    with server(data) as (url, _):
        c = httpx.Client(base_url=url, timeout=30)
        info = c.get("/v1/maps/town").json()
        assert info["index"]["vectors"] == info["keyframes"] >= len(acked)
        for kid in acked:
            assert c.get(f"/v1/maps/town/keyframes/{kid}").status_code == 200, kid
        for kid in [k for k in acked if k.startswith("b")][-5:]:
            r = c.post("/v1/maps/town/query", params={"k": 1}, json={"descriptor": acked[kid]})
            assert r.json()["matches"][0]["keyframe_id"] == kid
        # backup while running; restore needs the service stopped
        backup = tmp_path / "town.sqlite"
        cli = [sys.executable, "-m", "overlapmamba"]
        res = subprocess.run(
            [*cli, "export-map", "town", str(backup), "--data-dir", str(data)],
            capture_output=True,
            text=True,
            cwd=ROOT,
        )
        assert res.returncode == 0, res.stderr
        res = subprocess.run(
            [*cli, "import-map", "copy", str(backup), "--data-dir", str(data)],
            capture_output=True,
            text=True,
            cwd=ROOT,
        )
        assert res.returncode == 2 and "running service" in res.stderr
        c.close()
    fresh = tmp_path / "restored"
    res = subprocess.run(
        [*cli, "import-map", "town2", str(backup), "--data-dir", str(fresh)],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert res.returncode == 0, res.stderr
    con = sqlite3.connect(fresh / "maps" / "town2" / "store.sqlite")
    n = con.execute("SELECT COUNT(*) FROM keyframes WHERE keyframe_id IS NOT NULL").fetchone()[0]
    con.close()
    assert n == info["keyframes"]


def test_serve_refuses_an_open_host_without_keys(tmp_path):
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "overlapmamba",
            "serve",
            "--host",
            "0.0.0.0",
            "--port",
            "1",
            "--data-dir",
            str(tmp_path),
            "--model",
            str(MODEL),
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=60,
    )
    assert res.returncode == 2 and "without API keys" in res.stderr and "--insecure" in res.stderr


def test_serve_refuses_a_file_that_is_not_an_encoder_in_one_line(tmp_path):
    # a truncated download, and an ONNX graph that is not one of ours: each refused before
    # uvicorn starts (exit 2, one line naming the file and what is expected), not a traceback
    truncated = tmp_path / "truncated.onnx"
    truncated.write_bytes(MODEL.read_bytes()[:4096])
    plain = tmp_path / "plain.onnx"
    graph = onnx.helper.make_graph(
        [onnx.helper.make_node("Identity", ["x"], ["y"])],
        "g",
        [onnx.helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [1])],
        [onnx.helper.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [1])],
    )
    onnx.save(onnx.helper.make_model(graph), plain)
    for path, why in ((truncated, "DecodeError"), (plain, "overlapmamba-encoder")):
        args = ["serve", "--port", "1", "--data-dir", str(tmp_path / "data"), "--model", str(path)]
        res = subprocess.run(
            [sys.executable, "-m", "overlapmamba", *args],
            capture_output=True,
            text=True,
            cwd=ROOT,
            timeout=60,
        )
        assert res.returncode == 2, res.stderr
        out = " ".join((res.stdout + res.stderr).split())  # rich wraps long lines
        assert str(path.name) in out and why in out and "overlapmamba export" in out, out
        assert "Traceback" not in res.stdout + res.stderr


def _edited(tmp_path, name: str, props: dict[str, str], batch: int | None = None):  # type: ignore[no-untyped-def]
    """The shipped file with metadata ``props`` replaced and, with ``batch``, its graph's
    input fixed to that many images."""
    proto = onnx.load(str(MODEL))
    for prop in proto.metadata_props:
        if prop.key in props:
            prop.value = props[prop.key]
    if batch is not None:
        dim = proto.graph.input[0].type.tensor_type.shape.dim[0]
        dim.ClearField("dim_param")
        dim.dim_value = batch
    path = tmp_path / name
    onnx.save(proto, str(path))
    return path


def test_a_model_whose_graph_or_id_disagrees_with_its_metadata_is_refused(tmp_path):
    """Only the input and output names were checked at load: a file declaring 128 floats a
    descriptor whose graph gives 256 said ready, and then refused every insert as the
    client's fault; one whose graph takes one image at a time (the service batches)
    failed every scan, or ended serve in uvicorn's traceback; one whose views were changed
    by hand, its id kept, served other descriptors into the maps of that id. Each is
    refused at load, naming the disagreement, and `serve` says so in one line (exit 2)."""
    from overlapmamba.service.encoder import Encoder, ModelLoadError

    cases = {
        "dim.onnx": (
            {"overlapmamba.descriptor_dim": "128"},
            None,
            r"descriptors of shape \(2, 256\)",
        ),
        "batch.onnx": ({}, 1, "its graph does not run on the input its metadata describes"),
        "views.onnx": ({"overlapmamba.views": "1"}, None, "is not the one its metadata gives"),
    }
    for name, (props, batch, says) in cases.items():
        path = _edited(tmp_path, name, props, batch)
        with pytest.raises(ModelLoadError, match=says):
            Encoder(path, intra_op_threads=1, scan_kernel=False)
    # (and a message holding ":a:" is printed as it is, not as rich's emoji for it)
    _edited(tmp_path, "stage.onnx", {"overlapmamba.first_stage": "bogus"})
    args = ["serve", "--port", "1", "--data-dir", str(tmp_path / "data"), "--model"]
    for name, says in (("batch.onnx", "does not run on the input"), ("stage.onnx", "mixed:A:")):
        res = subprocess.run(
            [sys.executable, "-m", "overlapmamba", *args, str(tmp_path / name)],
            capture_output=True,
            text=True,
            cwd=ROOT,
            timeout=60,
        )
        out = " ".join((res.stdout + res.stderr).split())
        assert res.returncode == 2 and says in out and "Traceback" not in out, out
    # export into a folder named like a file: refused before the work, not a traceback after
    (tmp_path / "folder.onnx").mkdir()
    args = ["export", str(MODEL), "--views", "1", "--out", str(tmp_path / "folder.onnx")]
    res = subprocess.run(
        [sys.executable, "-m", "overlapmamba", *args], capture_output=True, text=True, cwd=ROOT
    )
    out = " ".join((res.stdout + res.stderr).replace("│", " ").split())
    assert res.returncode == 2 and "is a folder" in out and "Traceback" not in out, out


def test_serve_refuses_what_its_start_up_would_meet_in_one_line(tmp_path):
    """A setting out of range, a data folder that is a file, a data folder another service
    holds, a sensor file that is not there: each refused before uvicorn starts (exit 2, one
    line), where the start-up would otherwise end in uvicorn's traceback (exit 3), or the
    setting in typer's usage text and box."""
    (tmp_path / "a-file").write_text("")
    held = tmp_path / "held"
    missing = tmp_path / "sensors.toml"
    missing.write_text(f'[sensors]\nfiles = ["{tmp_path / "nope.toml"}"]\n')
    inf = tmp_path / "inf.toml"
    inf.write_text("[limits]\nrequest_timeout_s = inf\n")
    cases = [
        (["--data-dir", str(tmp_path / "d"), "--config", str(inf)], "request_timeout_s: Input"),
        (["--data-dir", str(tmp_path / "a-file")], "cannot use"),
        (["--data-dir", str(held)], "in use by a running service"),
        (["--data-dir", str(tmp_path / "d"), "--config", str(missing)], "cannot read sensor"),
    ]
    with backup.data_dir_lock(held):  # another service's
        for extra, why in cases:
            res = subprocess.run(
                [sys.executable, "-m", "overlapmamba", "serve", "--port", "1", *extra],
                capture_output=True,
                text=True,
                cwd=ROOT,
                timeout=60,
            )
            out = " ".join((res.stdout + res.stderr).split())
            assert res.returncode == 2 and why in out, (extra, out)
            assert "Traceback" not in out and "Usage:" not in out, out
            assert len((res.stdout + res.stderr).strip().splitlines()) <= 2, out  # one line


def test_an_old_settings_name_is_one_warning_line_naming_both_names(tmp_path):
    """Found in review: an old name in the environment printed a warning that pointed at
    pydantic_settings' source file and quoted its line; the command line says it in one."""
    res = subprocess.run(
        [sys.executable, "-m", "overlapmamba", "dump-config"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={"PATH": "/usr/bin:/bin", "OVERLAPMAMBA_VERIFY__K": "3"},
    )
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["verify"]["candidates"] == 3
    line = "warning: verify.k is deprecated and goes in 0.3.0: it is now verify.candidates"
    assert line in res.stderr.splitlines(), res.stderr
    assert "pydantic" not in res.stderr and ".py:" not in res.stderr, res.stderr


def test_dump_config_and_hash_key(tmp_path):
    cfg = tmp_path / "s.toml"
    cfg.write_text("[batching]\nmax_batch = 5\n")
    res = subprocess.run(
        [sys.executable, "-m", "overlapmamba", "dump-config", "--config", str(cfg)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={"PATH": "/usr/bin:/bin", "OVERLAPMAMBA_PORT": "8123"},
    )
    assert res.returncode == 0, res.stderr
    dumped = json.loads(res.stdout)
    assert dumped["batching"]["max_batch"] == 5 and dumped["port"] == 8123
    # the thresholds as the service answers for its model, each with where it came from
    assert "loop_closure.max_score = " in res.stderr and "verify.min_fitness" in res.stderr
    res = subprocess.run(
        [sys.executable, "-m", "overlapmamba", "hash-key", "--role", "viewer", "--key", "abc"],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert 'role = "viewer"' in res.stdout
    assert "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad" in res.stdout
    odd = 'ops "night" \\ robot'  # what it prints is pasted into a TOML file: stays TOML
    res = subprocess.run(
        [sys.executable, "-m", "overlapmamba", "hash-key", "--name", odd, "--key", "abc"],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert tomllib.loads(res.stdout)["auth"]["keys"][0]["name"] == odd, res.stdout
    _ = OCTET
