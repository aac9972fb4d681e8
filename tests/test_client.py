"""The Python clients and `overlapmamba-client`: in-process (ASGITransport), against a real
server, retries against a transport that fails on purpose, sync/async congruence, the CLI,
the README example and the public names."""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import shutil
import subprocess
import sys
import time
from types import SimpleNamespace
from typing import Any

import httpx
import numpy as np
import pytest
from service_kit import ROOT, running, scan, server
from typer.testing import CliRunner

import overlapmamba.client as client
from overlapmamba.client import (
    NO_RETRY,
    APIError,
    AsyncPlaceRecognitionClient,
    BadRequestError,
    ConflictError,
    ConnectError,
    NotFoundError,
    Observation,
    OverloadedError,
    PlaceRecognitionClient,
    ResponseError,
    Retry,
)
from overlapmamba.client.cli import app as cli_app
from overlapmamba.service.settings import Settings

README = ROOT / "README.md"

pytestmark = pytest.mark.anyio


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    """One real `overlapmamba serve` for the module."""
    with server(tmp_path_factory.mktemp("client-data")) as (url, _):
        yield url


def test_public_names():
    assert sorted(client.__all__) == sorted(
        [
            "NO_RETRY", "APIError", "AsyncPlaceRecognitionClient", "AuthError",
            "BadRequestError", "BatchInsertResult", "ClientError", "ConflictError",
            "ConnectError", "Descriptor", "Keyframe", "LoopClosure", "MapInfo", "Match",
            "NotFoundError", "Observation", "ObserveResult", "OverloadedError",
            "PayloadTooLargeError", "PlaceRecognitionClient", "QueryResult", "ResponseError",
            "Retry", "ServerError", "Timeout", "Timeouts", "TransportError",
        ]
    )  # fmt: skip
    for name in client.__all__:
        assert getattr(client, name) is not None
    sync = {m for m in dir(PlaceRecognitionClient) if not m.startswith("_")}
    both = {m for m in dir(AsyncPlaceRecognitionClient) if not m.startswith("_")}
    assert sync == both  # the same methods


async def test_async_client_in_process(tmp_path, encoder):
    s0, s1 = scan(0), scan(1)
    np.save(tmp_path / "s1.npy", s1)
    s0.tofile(tmp_path / "s0.bin")
    async with running(Settings(data_dir=tmp_path / "d"), encoder) as c:
        transport = httpx.ASGITransport(app=c.app)  # type: ignore[attr-defined]
        async with AsyncPlaceRecognitionClient("http://test", transport=transport) as pr:
            assert (await pr.health())["status"] == "ready"
            d = await pr.describe(tmp_path / "s0.bin")
            assert d.vector.shape == (256,) and d.model_id == encoder.model_id
            batch = await pr.describe_batch([s0, s1])
            assert np.dot(batch[0].vector, d.vector) > 0.9999
            m = await pr.create_map("town")
            assert m.created and m.keyframes == 0
            meta = {"keyframe_id": "k0", "timestamp": 1.0, "robot_id": "r"}
            kf = await pr.insert_keyframe("town", s0, **meta, pose=[0, 0, 0, 0, 0, 0, 1])
            assert kf.created and kf.pose == [0, 0, 0, 0, 0, 0, 1]
            again = await pr.insert_keyframe("town", s0, **meta, pose=[0, 0, 0, 0, 0, 0, 1])
            assert again.created is False
            with pytest.raises(ConflictError, match="different content") as e:
                await pr.insert_keyframe("town", s1, keyframe_id="k0", timestamp=1.0)
            assert e.value.status == 409 and e.value.code == "keyframe_conflict"
            res = await pr.insert_descriptors(
                "town",
                [{"keyframe_id": "b1", "timestamp": 2.0, "descriptor": batch[1].vector}],
                model_id=d.model_id,
            )
            assert res.inserted == 1
            q = await pr.query("town", tmp_path / "s1.npy", k=2)
            assert q.matches[0].keyframe_id == "b1"
            q = await pr.query("town", descriptor=d.vector, k=1, exclude_robot="nobody")
            assert q.matches[0].keyframe_id == "k0" and q.matches[0].distance < 1e-3
            recent = {"exclude_recent_s": 5.0, "session_id": "default", "timestamp": 3.0}
            for robot, left in ((None, set()), ("r", {"b1"}), ("r9", {"k0", "b1"})):
                q = await pr.query("town", descriptor=d.vector, k=2, robot_id=robot, **recent)
                assert {x.keyframe_id for x in q.matches} == left, robot
            o = await pr.observe("town", s1, robot_id="r2", timestamp=10.0, insert="never")
            assert not o.inserted and o.insert_reason == "never"
            assert (await pr.get_keyframe("town", "b1")).timestamp == 2.0
            await pr.delete_keyframe("town", "b1")
            with pytest.raises(NotFoundError):
                await pr.get_keyframe("town", "b1")
            assert [m.map_id for m in await pr.list_maps()] == ["town"]
            assert (await pr.stats())["inserts"] == 2
            assert (await pr.stats("town"))["map"]["keyframes"] == 1
            await pr.delete_map("town")
            with pytest.raises(NotFoundError, match="does not exist"):
                await pr.get_map("town")
            with pytest.raises(ValueError, match=r"\(N, 3\) or \(N, 4\)"):
                await pr.describe(np.zeros((5, 7), np.float32))
            # sensors: per call, per map, per client
            assert "vlp16" in {x["name"] for x in (await pr.sensors())["sensors"]}
            v = await pr.describe(s0, sensor="vlp16")
            assert float(np.dot(v.vector, d.vector)) < 0.9999  # another projection
            robots = await pr.create_map("robots", sensor="vlp16", mount=(0.7,))
            assert robots.sensor == "vlp16" and robots.mount == {
                "height": 0.7,
                "pitch_deg": 0.0,
                "roll_deg": 0.0,
            }
            kf = await pr.insert_keyframe("robots", s0, keyframe_id="v0", timestamp=1.0)
            assert kf.sensor == "vlp16"
            q = await pr.query("robots", s0, k=1, verify=False, sensor="os1-64")
            assert q.matches[0].sensor == "vlp16"
            with pytest.raises(BadRequestError, match="unknown sensor 'mid360'") as bad:
                await pr.describe(s0, sensor="mid360")
            assert "xt32" in bad.value.detail["allowed"]
        async with AsyncPlaceRecognitionClient(
            "http://test", transport=transport, sensor="os1-64"
        ) as pr:
            kf = await pr.insert_keyframe("robots", s1, keyframe_id="o1", timestamp=2.0)
            assert kf.sensor == "os1-64"  # the client's sensor, on every scan it sends
        async with AsyncPlaceRecognitionClient(
            "http://test", transport=transport, sensor="vlp16", mount=(0.7, 2.0)
        ) as pr:  # ... and where it sits: the service levels and lifts every scan it sends
            low = await pr.describe(s0)
            assert float(np.dot(low.vector, v.vector)) < 0.9999
            again = await pr.describe(s0)
            np.testing.assert_allclose(again.vector, low.vector, atol=1e-6)
        with pytest.raises(ValueError, match="pitch_deg input should be less than or equal to 45"):
            AsyncPlaceRecognitionClient("http://test", transport=transport, mount="0.7,60")


def _failing(plan: list[object], calls: list[float]):
    """A transport answering from ``plan``: an exception to raise or (status, headers)."""

    def handler(request: httpx.Request) -> httpx.Response:
        calls.append(time.monotonic())
        step = plan.pop(0) if plan else (200, {})
        if isinstance(step, Exception):
            raise step
        status, headers = step  # type: ignore[misc]
        if status == 200:
            return httpx.Response(200, json={"status": "ready", "detail": {}})
        body = {"error": {"code": "overloaded", "message": "busy", "detail": {}}}
        return httpx.Response(status, json=body, headers=headers)

    return httpx.MockTransport(handler)


def test_retries_back_off_and_honour_retry_after():
    calls: list[float] = []
    plan = [httpx.ConnectError("refused"), httpx.ReadTimeout("slow"), (503, {"Retry-After": "0.3"})]
    retry = Retry(attempts=4, backoff_s=0.01, jitter=0.0)
    with PlaceRecognitionClient(transport=_failing(plan, calls), retry=retry) as pr:
        assert pr.health()["status"] == "ready"
    assert len(calls) == 4
    assert calls[3] - calls[2] >= 0.3  # Retry-After, longer than the backoff, was honoured
    calls.clear()
    plan = [(409, {}), (200, {})]
    with (
        PlaceRecognitionClient(transport=_failing(plan, calls), retry=retry) as pr,
        pytest.raises(ConflictError),
    ):
        pr.health()
    assert len(calls) == 1  # a 409 is an answer, not a failure: no retry
    calls.clear()
    plan = [(503, {"Retry-After": "0"})] * 5
    with PlaceRecognitionClient(transport=_failing(plan, calls), retry=retry) as pr:
        with pytest.raises(OverloadedError) as e:
            pr.health()
        assert e.value.retry_after == 0.0
    assert len(calls) == 4  # attempts exhausted
    calls.clear()
    with (
        PlaceRecognitionClient(
            transport=_failing([httpx.ConnectError("x")], calls), retry=NO_RETRY
        ) as pr,  # fmt: skip
        pytest.raises(ConnectError),
    ):
        pr.health()
    assert len(calls) == 1


async def test_async_retries_too():
    calls: list[float] = []
    plan = [httpx.ConnectError("refused"), (429, {"Retry-After": "0.05"})]
    retry = Retry(attempts=3, backoff_s=0.01)
    async with AsyncPlaceRecognitionClient(transport=_failing(plan, calls), retry=retry) as pr:
        assert (await pr.health())["status"] == "ready"
    assert len(calls) == 3


async def test_sync_and_async_agree_against_a_real_server(live):
    scans = [scan(i) for i in range(3)]
    with PlaceRecognitionClient(live) as pr:
        pr.create_map("congruent")
        for i, s in enumerate(scans):
            pr.insert_keyframe("congruent", s, keyframe_id=f"k{i}", timestamp=float(i))
        sync_q = pr.query("congruent", scan(1, 30.0), k=3)
        unverified = pr.query("congruent", scan(1, 30.0), k=3, verify=False)
        sync_d = pr.describe(scans[2])
        sync_maps = pr.list_maps()
        results = list(
            pr.stream(
                "congruent",
                [Observation(s, 100.0 + i, insert="never") for i, s in enumerate(scans)],
                robot_id="sr",
            )
        )
    async with AsyncPlaceRecognitionClient(live) as apr:
        async_q = await apr.query("congruent", scan(1, 30.0), k=3)
        async_d = await apr.describe(scans[2])
        async_maps = await apr.list_maps()
        aresults = [
            r
            async for r in apr.stream(
                "congruent",
                [
                    Observation(s, 100.0 + i, insert="never", verify=i != 1)
                    for i, s in enumerate(scans)
                ],
                robot_id="ar",
            )
        ]
    assert [m.keyframe_id for m in sync_q.matches] == [m.keyframe_id for m in async_q.matches]
    assert sync_q.matches[0].keyframe_id == "k1"
    assert abs(sync_q.matches[0].yaw_deg - 30.0) < 1.5
    # verified: the relative pose comes back as a 4×4 matrix, the closure carries it
    top, lc = sync_q.matches[0], sync_q.loop_closure
    assert top.verification is not None and top.verification.verified is True
    assert top.relative_pose is not None and top.relative_pose.shape == (4, 4)
    assert abs(np.degrees(np.arctan2(top.relative_pose[1, 0], top.relative_pose[0, 0])) + 30) < 0.5
    assert lc.verified is True and lc.keyframe_id == "k1"
    np.testing.assert_allclose(lc.relative_pose, top.relative_pose)
    assert async_q.matches[0].verification == top.verification
    assert unverified.matches[0].verification is None and unverified.loop_closure.verified is None
    assert [r.loop_closure.verified for r in aresults] == [True, None, True]
    np.testing.assert_allclose(
        [m.distance for m in sync_q.matches], [m.distance for m in async_q.matches], atol=1e-6
    )
    np.testing.assert_allclose(sync_d.vector, async_d.vector, atol=1e-6)
    assert [m.map_id for m in sync_maps] == [m.map_id for m in async_maps]
    assert [r.seq for r in results] == [0, 1, 2] == [r.seq for r in aresults]
    assert [r.matches[0].keyframe_id for r in results] == ["k0", "k1", "k2"]
    assert [r.matches[0].keyframe_id for r in aresults] == ["k0", "k1", "k2"]


def test_readme_example_runs(live, monkeypatch, capsys):
    text = README.read_text()
    block = re.search(r"<!-- client-example -->\s*```python\n(.*?)```", text, re.S)
    assert block, "the README lost its client example"
    code = block.group(1)
    assert len([ln for ln in code.splitlines() if ln.strip()]) <= 10
    monkeypatch.setenv("OVERLAPMAMBA_URL", live)
    exec(compile(code, "README.md", "exec"), {})
    printed = capsys.readouterr().out.split()
    assert printed[0] == "f0" and float(printed[1]) < 1e-3


def test_readme_curl_example_runs(live):
    """The README's five lines of curl, against a real server, as a newcomer pastes them."""
    block = re.search(r"## Five lines\n.*?```bash\n(.*?)```", README.read_text(), re.S)
    assert block, "the README lost its curl example"
    if shutil.which("curl") is None:
        pytest.skip("no curl on this machine")
    if not (ROOT.parent / "shared" / "data" / "kitti00_0000-0100").is_dir():
        pytest.skip("../shared/data (KITTI 00) is absent")
    host = live.removeprefix("http://")
    script = block[1].replace("localhost:8000", host).replace("/maps/town", "/maps/readme")
    done = subprocess.run(
        ["bash", "-euo", "pipefail", "-c", script],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    answers, text, at = [], done.stdout, 0
    while text[at:].strip():  # curl -s prints the three answers back to back
        at += len(text[at:]) - len(text[at:].lstrip())
        obj, at = json.JSONDecoder().raw_decode(text, at)
        answers.append(obj)
    assert len(answers) == 3, text[:500]
    query = answers[-1]
    assert query["matches"][0]["keyframe_id"] == "f0"
    assert query["matches"][0]["verification"]["verified"] is True  # the next frame: a closure
    assert len(query["matches"][0]["relative_pose"]) == 16


def test_cli_end_to_end_on_a_generated_sequence(live, synthetic_seq_dir, shifted_seq_dir, tmp_path):
    runner = CliRunner()
    env = {"OVERLAPMAMBA_URL": live}

    def run(*args: str) -> str:
        res = runner.invoke(cli_app, list(args), env=env)
        assert res.exit_code == 0, res.output
        return res.output

    assert "created" in run("maps", "create", "cli-town")
    assert "sensor vlp16" in run("maps", "create", "cli-robots", "--sensor", "vlp16")
    out = run("maps", "create", "cli-amr", "--sensor", "os0-128", "--mount", "0.35,1.5")
    assert "sensor os0-128, mounted 0.35 m, pitch 1.5°, roll 0°" in " ".join(out.split())
    out = run("ingest", str(synthetic_seq_dir), "--map", "cli-robots", "--every", "12",
              "--sensor", "xt32")  # fmt: skip
    assert "4 new keyframes" in out
    out = run("ingest", str(synthetic_seq_dir), "--map", "cli-town", "--every", "6")
    assert "8 scans → map cli-town: 8 new keyframes" in out
    out = run("ingest", str(synthetic_seq_dir), "--map", "cli-town", "--every", "6")
    assert "0 new keyframes, 8 already there" in out  # re-running is harmless
    out = run("query", str(synthetic_seq_dir / "velodyne" / "000012.bin"), "--map", "cli-town")
    assert "loop-000012" in out and "loop closure: ACCEPTED, verified: loop-000012" in out
    assert "relative pose T_keyframe←query" in out  # the 4×4 a pose graph takes
    # the server's default verify.stop_at_first: the candidates after it are not registered
    assert "skipped: not registered: candidate 1 verified first" in " ".join(out.split())
    out = run("query", str(synthetic_seq_dir / "velodyne" / "000012.bin"), "--map", "cli-town",
              "--no-verify")  # fmt: skip
    assert "descriptor only" in out
    assert "geometry not kept" in run("maps", "create", "cli-bare", "--no-geometry")
    rec, g2o = tmp_path / "drive.mcap", tmp_path / "graph" / "drive.g2o"
    out = run(
        "observe", str(synthetic_seq_dir), "--map", "cli-obs", "--every", "4", "--robot", "r9",
        "--record", str(rec), "--g2o", str(g2o),
    )  # fmt: skip
    assert "12 scans observed" in out and "recorded" in out
    # a second drive's pose graph (the same world driven 1.5 m to the left, turned 12°): a
    # vertex a scan at its pose, odometry between them, a loop edge a verified closure onto
    # the first session's keyframes (vertices of their own at their stored poses), at its
    # relative pose (far from the identity: an edge the wrong way round is 1.5 m off) with
    # the server's covariance
    from overlapmamba.client.posegraph import read_g2o
    from overlapmamba.core.poses import read_poses

    out2 = run(
        "observe", str(shifted_seq_dir), "--map", "cli-obs", "--every", "4", "--robot", "r8",
        "--g2o", str(g2o), "--g2o-for", "gtsam",
    )  # fmt: skip
    vertices, edges = read_g2o(g2o)
    from overlapmamba.client.posegraph import odometry_information

    # written for GTSAM's reader: the odometry's information over the rotation vector
    assert np.allclose(edges[0][3], odometry_information(0.1, 1.0, "gtsam"))
    truth = read_poses(shifted_seq_dir / "poses.txt")
    scans = [v for v in sorted(vertices) if v < 48]
    assert scans == list(range(0, 48, 4))
    assert all(np.abs(vertices[i] - truth[i]).max() < 1e-6 for i in scans)
    odometry, loops = edges[:11], edges[11:]
    assert [(a, b) for a, b, _, _ in odometry] == [(i, i + 4) for i in range(0, 44, 4)]
    verified = out2.count("verified loop closure with")
    assert verified >= 6 and len(loops) == verified, out2
    assert f"{verified} loop edges" in " ".join(out2.split())
    first = read_poses(synthetic_seq_dir / "poses.txt")
    for a, b, measured, info in loops:  # the first session's keyframe is numbered after 47
        assert a >= 48 and b in scans
        assert any(np.abs(vertices[a] - p).max() < 1e-6 for p in first)  # its stored pose
        true = np.linalg.inv(vertices[a]) @ vertices[b]
        assert np.linalg.norm(true[:3, 3]) > 1.0  # an inverted edge could not pass
        assert np.abs(measured[:3, 3] - true[:3, 3]).max() < 0.1, (a, b, measured, true)
        turn = np.arccos(np.clip((np.trace(measured[:3, :3].T @ true[:3, :3]) - 1) / 2, -1, 1))
        assert np.degrees(turn) < 1.0, (a, b)
        assert np.allclose(info, info.T) and np.linalg.eigvalsh(info).min() > 0
    from mcap.reader import make_reader  # the recording opens with MCAP's own reader

    topics: dict[str, list[dict]] = {}
    with open(rec, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            assert schema.name in ("foxglove.PoseInFrame", "foxglove.SceneUpdate")
            topics.setdefault(channel.topic, []).append(json.loads(message.data))
    assert len(topics["/overlapmamba/robots/r9"]) == 12
    inserted = int(re.search(r"(\d+) inserted", out).group(1))
    assert len(topics["/overlapmamba/keyframes"]) == inserted >= 1
    closed = out.count("loop closure with")
    assert len(topics.get("/overlapmamba/loop_closures", [])) == closed
    for m in topics.get("/overlapmamba/loop_closures", []):
        (line,) = m["entities"][0]["lines"]
        assert len(line["points"]) == 2 and line["color"]["a"] == 1.0
    assert "cli-town" in run("maps", "list")
    assert "queries" in run("stats") and "map keyframes" in run("stats", "--map", "cli-obs")
    report, plot = tmp_path / "fleet.json", tmp_path / "fleet.png"
    out = run(
        "simulate-fleet", "--map", "cli-fleet", "--sequence", str(synthetic_seq_dir),
        "--robots", "2", "--duration", "30", "--scans", "3", "--rate", "4", "--mount", "1.8,2",
        "--out", str(report), "--plot", str(plot),
    )  # fmt: skip
    data = json.loads(report.read_text())
    assert data["robots"] == 2 and data["observations"] == 6 and data["errors"] == {}
    assert data["scans_per_robot"] == 3 and data["duration_s"] < 30
    assert data["precision"] is None  # this sequence ships no ground truth
    assert plot.stat().st_size > 1000
    bad = ["simulate-fleet", "--map", "x", "--sequence", str(synthetic_seq_dir), "--mount", "0"]
    res = runner.invoke(cli_app, bad, env=env)
    assert res.exit_code == 2 and "HEIGHT[,PITCH[,ROLL]]" in " ".join(res.output.split())
    assert "deleted" in run("maps", "delete", "cli-fleet", "--yes")
    res = runner.invoke(cli_app, ["maps", "delete", "cli-fleet", "--yes"], env=env)
    assert res.exit_code == 1 and "map_not_found" in res.output
    res = runner.invoke(cli_app, ["maps", "list"], env={"OVERLAPMAMBA_URL": "http://127.0.0.1:9"})
    assert res.exit_code == 2 and "cannot connect" in res.output


def test_a_recording_holds_poses_keyframes_and_closure_edges(tmp_path):
    from mcap.reader import make_reader

    from overlapmamba.client.recording import DESCRIPTOR_ONLY, VERIFIED, MapRecording

    with MapRecording(tmp_path / "r.mcap") as rec:
        rec.observation("r1", 1.5, [0, 0, 0, 0, 0, 0, 1], keyframe_id="k0")
        rec.observation("r1", 2.0, [5, 1, 0, 0, 0, 0, 1], closure=("k0", [0, 0, 0], True))
        rec.observation("r2", 2.5, [9, 9, 0, 0, 0, 0, 1], closure=("k0", [0, 0, 0], None))
        rec.observation("r2", 3.0, None, keyframe_id="k9")  # no pose: nothing to draw
    got: dict[str, list[tuple[int, dict]]] = {}
    with open(tmp_path / "r.mcap", "rb") as f:
        for _, channel, message in make_reader(f).iter_messages():
            got.setdefault(channel.topic, []).append((message.log_time, json.loads(message.data)))
    assert [t for t, _ in got["/overlapmamba/robots/r1"]] == [1_500_000_000, 2_000_000_000]
    assert got["/overlapmamba/robots/r1"][1][1]["pose"]["position"] == {"x": 5, "y": 1, "z": 0}
    (kf,) = got["/overlapmamba/keyframes"]
    assert kf[1]["entities"][0]["id"] == "k0" and kf[1]["entities"][0]["spheres"]
    lines = [m["entities"][0]["lines"][0] for _, m in got["/overlapmamba/loop_closures"]]
    assert [ln["color"] for ln in lines] == [VERIFIED, DESCRIPTOR_ONLY]
    assert lines[0]["points"] == [{"x": 5, "y": 1, "z": 0}, {"x": 0, "y": 0, "z": 0}]


def test_a_robot_that_cannot_read_its_scan_stops_the_fleet_with_that_error(live, tiny_seq):
    """One robot's own failure (a scan file it cannot read) ends the simulation with that
    error at once and leaves no other robot running on the loop; before, the others went on
    after the call had raised, against a client already closed."""
    import dataclasses

    from overlapmamba.client._replay import Drive, open_drive
    from overlapmamba.client.fleet import simulate

    @dataclasses.dataclass
    class Broken(Drive):
        def scan(self, i: int) -> np.ndarray:
            if i == 2:
                raise OSError(f"scan {i} is unreadable")
            return super().scan(i)

    plain = open_drive(tiny_seq)
    drive = Broken(**{f.name: getattr(plain, f.name) for f in dataclasses.fields(Drive)})

    async def run() -> list[asyncio.Task]:
        with pytest.raises(OSError, match="scan 2 is unreadable"):
            await simulate(live, "fleet-broken", [drive], robots=2, duration_s=60, rate_hz=5.0)
        return [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]

    t0 = time.monotonic()
    assert asyncio.run(run()) == []
    assert time.monotonic() - t0 < 30


def test_fleet_scores_loop_closures_against_ground_truth(live, tiny_seq):
    from overlapmamba.client._replay import open_drive
    from overlapmamba.client.fleet import simulate

    drive = open_drive(tiny_seq)
    assert drive.loop_radius is not None
    assert drive.sensor == "kitti-hdl64"  # its manifest says; a user's --sensor would win
    assert open_drive(tiny_seq, sensor="vlp16").sensor == "vlp16"
    report, samples = asyncio.run(
        simulate(live, "fleet-gt", [drive], robots=2, duration_s=4.0, rate_hz=3.0)
    )
    assert report.errors == {} and report.observations == len(samples) >= 6
    assert report.correct is not None and report.queries_with_loop is not None
    assert 0 <= report.correct <= report.loop_closures
    # the report names what it measured: the service's model, the drive, when
    ready = httpx.get(f"{live}/readyz").json()["detail"]
    assert report.server["model_id"] == ready["model_id"] and report.server["views"] >= 1
    assert report.drives == [drive.name] and report.when.endswith("+00:00")


def test_fleet_robots_stop_after_the_scans_asked_and_refuse_a_count_below_one(live, tiny_seq):
    """``scans``: each robot observes that many scans and stops (the run ends before its
    time bound), so the robots cover the same stretches of the drive on any machine."""
    import time

    from overlapmamba.client._replay import open_drive
    from overlapmamba.client.fleet import simulate

    drive = open_drive(tiny_seq)
    t0 = time.monotonic()
    report, samples = asyncio.run(
        simulate(live, "fleet-n", [drive], robots=2, duration_s=120.0, rate_hz=20.0, scans=4)
    )
    assert time.monotonic() - t0 < 60.0  # ended by the count, not by the bound
    assert report.errors == {} and report.scans_per_robot == 4
    assert {r: v["observations"] for r, v in report.per_robot.items()} == {
        "robot-00": 4,
        "robot-01": 4,
    }
    half = len(drive) // 2  # the second robot starts halfway: its own four frames
    assert sorted(s.frame for s in samples) == [0, 1, 2, 3, half, half + 1, half + 2, half + 3]
    with pytest.raises(ValueError, match="scans must be at least 1"):
        asyncio.run(
            simulate(live, "fleet-n", [drive], robots=1, duration_s=1.0, rate_hz=1.0, scans=0)
        )


def test_fleet_judges_verified_closures_by_their_pose_beyond_the_loop_radius():
    """Precision counts a closure right when its keyframe lies within the loop radius; a
    verified closure's pose is judged as well, wherever the keyframe lies: a right pose to
    a keyframe 20 m away is an edge a pose graph can take, a wrong one is not."""

    from overlapmamba.client._replay import Drive
    from overlapmamba.client.fleet import _report, _Sample

    n = 100
    world = np.tile(np.eye(4), (n, 1, 1))
    world[:, 0, 3] = np.arange(n, dtype=float)  # a straight drive, a metre a frame
    xyzq = np.zeros((n, 7))
    xyzq[:, 0], xyzq[:, 6] = world[:, 0, 3], 1.0
    drive = Drive(
        seq=SimpleNamespace(poses=world, name="line"),
        times=np.arange(n, dtype=float),
        poses=xyzq,
        loop_radius=5.0,
    )
    keyframes = {f"kf{j}": (0, j, 0.0) for j in (10, 40, 48, 78)}

    def sample(frame: int, kf: int, verified: bool, pose: np.ndarray | None) -> _Sample:
        return _Sample(
            robot="r", drive=0, frame=frame, sent=1.0, latency_ms=1.0, accepted=True,
            top=f"kf{kf}", inserted=None, error=None, verified=verified, relative_pose=pose,
        )  # fmt: skip

    def truth(kf: int, frame: int) -> np.ndarray:
        return np.linalg.inv(world[kf]) @ world[frame]

    samples = [
        sample(50, 48, True, truth(48, 50)),  # within the radius, pose right
        sample(60, 40, True, truth(40, 60)),  # 20 m away, pose right
        sample(70, 10, True, np.eye(4)),  # 60 m away, pose wrong
        sample(80, 78, False, None),  # within the radius, not verified
    ]
    r = _report(samples, keyframes, [drive], 1, 1.0, 1.0, 0.0, 0.0)
    assert (r.loop_closures, r.correct, r.verified_closures) == (4, 2, 3)
    assert r.precision == 0.5 and r.verified_pose_right == 2
    assert r.covariance is None  # no closure carried one
    # the right closures' covariances judged against the truth: a pose 0.3 m off along x is
    # inside an ellipsoid of σ 0.2 m there, outside one of 1 cm; a wrong pose is not judged
    off = truth(48, 50) @ np.array([[1, 0, 0, 0.3], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    for sigma, inside in ((0.2, 1.0), (0.01, 0.5)):
        judged = [sample(50, 48, True, off), sample(60, 40, True, truth(40, 60)), samples[2]]
        cov = np.diag([sigma**2] * 3 + [1e-4] * 3)
        for x in judged:
            x.covariance = cov
        r = _report(judged, keyframes, [drive], 1, 1.0, 1.0, 0.0, 0.0)
        assert r.covariance == {"closures": 2, "inside_95": inside}, sigma


@pytest.mark.parametrize(
    "duration_s, rate_hz, says",
    [
        (float("nan"), 1.0, "duration_s nan"),
        (1.0, float("nan"), "rate_hz nan"),
        (1.0, float("inf"), "rate_hz inf"),
        (0.0, 1.0, "duration_s 0.0"),
    ],
)
def test_a_fleet_refuses_a_duration_or_rate_that_is_not_a_number_above_0(duration_s, rate_hz, says):
    """Checked before anything connects: the port here has no server."""
    from overlapmamba.client.fleet import simulate

    with pytest.raises(ValueError, match=f"finite rate > 0 Hz.*{says}"):
        asyncio.run(
            simulate(
                "http://127.0.0.1:9",
                "m",
                [object()],
                robots=1,
                duration_s=duration_s,  # type: ignore[list-item]
                rate_hz=rate_hz,
            )
        )


def test_times_txt_is_one_finite_time_a_line_and_a_bad_one_is_named(tmp_path):
    from overlapmamba.client._replay import read_times

    f = tmp_path / "times.txt"
    f.write_text("0.0\n0.1\n0.2\n")
    np.testing.assert_array_equal(read_times(f, 3), [0.0, 0.1, 0.2])
    for text, says in [
        ("0.0 1\n0.1 2\n0.2 3\n", "has 2 columns"),
        ("time\n0.0\n0.1\n", "cannot be read as times"),
        ("0.0\nnan\n0.2\n", "line 2 is not a finite time"),
        ("0.0\n0.1\n", "2 times for 3 scans"),
    ]:
        f.write_text(text)
        with pytest.raises(ValueError, match=says) as err:
            read_times(f, 3)
        assert str(f) in str(err.value) and "one time in seconds a line" in str(err.value)


def _answering(plan: list[object]):
    """A transport answering from ``plan``: an exception to raise, or (status, body, type)."""

    def handler(request: httpx.Request) -> httpx.Response:
        step = plan.pop(0)
        if isinstance(step, Exception):
            raise step
        status, body, kind = step  # type: ignore[misc]
        return httpx.Response(status, content=body, headers={"content-type": kind})

    return httpx.MockTransport(handler)


HTML = (200, b"<html><body>Welcome to nginx!</body></html>", "text/html")
EMPTY = (200, b"{}", "application/json")
GONE = (404, b'{"error": {"code": "map_not_found", "message": "no map"}}', "application/json")
DELETED = (204, b"", "application/json")


def test_a_success_that_is_not_this_apis_answer_is_a_response_error():
    """A proxy's page or an empty object under 200: ResponseError naming the route, the
    status, the type and the body's head, never a JSONDecodeError or KeyError (a
    ClientError: the CLI prints it in one line and exits 2)."""
    for plan, says in [([HTML], "text/html"), ([EMPTY], "KeyError")]:
        with (
            PlaceRecognitionClient(transport=_answering(plan), retry=NO_RETRY) as pr,
            pytest.raises(ResponseError, match=says) as err,
        ):
            pr.describe(scan(0))
        assert "POST /v1/descriptors answered 200" in str(err.value)

    async def run() -> None:
        async with AsyncPlaceRecognitionClient(transport=_answering([HTML]), retry=NO_RETRY) as pr:
            with pytest.raises(ResponseError, match="Welcome to nginx"):
                await pr.describe(scan(0))

    asyncio.run(run())
    from overlapmamba.client._stream import stream_result

    for frame in ("<html>", "[1, 2]", '{"ok": true}'):
        with pytest.raises(ResponseError, match="not this API's result"):
            stream_result(frame)


def test_a_delete_whose_answer_was_lost_is_done_when_its_retry_finds_nothing():
    """The first DELETE was carried out and its answer lost (a read timeout): the retry's
    404 means deleted. A 404 at the first try, or after a 503 (refused, nothing done), is
    still NotFoundError."""
    retry = Retry(attempts=3, backoff_s=0.01)
    lost = [httpx.ReadTimeout("no answer"), GONE]
    with PlaceRecognitionClient(transport=_answering(lost), retry=retry) as pr:
        assert pr.delete_map("town") is None
    for plan in ([GONE], [(503, b"{}", "application/json"), GONE]):
        with (
            PlaceRecognitionClient(transport=_answering(plan), retry=retry) as pr,
            pytest.raises(NotFoundError),
        ):
            pr.delete_keyframe("town", "kf-1")

    async def run() -> None:
        lost = [httpx.ReadTimeout("no answer"), GONE]
        async with AsyncPlaceRecognitionClient(transport=_answering(lost), retry=retry) as pr:
            assert await pr.delete_keyframe("town", "kf-1") is None

    asyncio.run(run())
    # a pool timeout never sent the first try: its retry's 404 is a real "not there"
    never = [httpx.PoolTimeout("no free connection"), GONE]
    with (
        PlaceRecognitionClient(transport=_answering(never), retry=retry) as pr,
        pytest.raises(NotFoundError),
    ):
        pr.delete_keyframe("town", "kf-1")


def test_an_insert_or_observation_retried_after_a_lost_answer_says_it_may_be_its_own():
    """The first try inserted and its answer was lost (a read timeout); the retry is told
    "existing". The answer says it was a retry's (``retried``), and an observation's
    ``keyframe`` is the one that earlier try made: the fleet and the CLI count it as theirs."""
    retry = Retry(attempts=3, backoff_s=0.01)
    kf = {
        "keyframe_id": "r1:s:5.0",
        "robot_id": "r1",
        "session_id": "s",
        "timestamp": 5.0,
        "pose": None,
        "created": False,
    }
    observed = {
        "matches": [],
        "loop_closure": {"accepted": False, "threshold": 0.3},
        "timings_ms": {},
        "inserted": False,
        "keyframe_id": "r1:s:5.0",
        "insert_reason": "existing",
    }
    for call, body in (("insert", kf), ("observe", observed)):
        plan = [
            httpx.ReadTimeout("no answer"),
            (200, json.dumps(body).encode(), "application/json"),
        ]
        with PlaceRecognitionClient(transport=_answering(plan), retry=retry) as pr:
            if call == "insert":
                got = pr.insert_keyframe("town", scan(0), keyframe_id="r1:s:5.0", timestamp=5.0)
                assert got.retried and got.created is False
            else:
                o = pr.observe("town", scan(0), robot_id="r1", session_id="s", timestamp=5.0)
                assert o.retried and o.keyframe == "r1:s:5.0" and not o.inserted
    # answered at the first try, "existing" is someone else's: not ours
    plan = [(200, json.dumps(observed).encode(), "application/json")]
    with PlaceRecognitionClient(transport=_answering(plan), retry=retry) as pr:
        o = pr.observe("town", scan(0), robot_id="r1", session_id="s", timestamp=5.0)
        assert not o.retried and o.keyframe is None


def test_a_refused_observation_raised_names_those_sent_after_it(monkeypatch):
    """errors="raise": observation 0 refused while 1 was in flight (the server takes it and
    may insert it); the error says 1 was sent and not answered, as a socket failure's does.
    An ``errors`` that is neither "raise" nor "return" is refused (it returned errors)."""
    import websockets.sync.client as ws_client

    sent: list[int] = []

    class Sock:
        def __init__(self, *args: object, **kwargs: object) -> None:
            self.read = 0

        def __enter__(self) -> Sock:
            return self

        def __exit__(self, *args: object) -> None:
            return None

        def send(self, frame: str | bytes) -> None:
            if isinstance(frame, str):
                sent.append(json.loads(frame)["seq"])

        def recv(self, timeout: float | None = None) -> str:
            seq = sent[self.read]
            self.read += 1
            refused = {"code": "bad_scan", "message": "too few points"}
            return json.dumps({"seq": seq, "ok": False, "status": 400, "error": refused})

    monkeypatch.setattr(ws_client, "connect", Sock)
    obs = [Observation(scan=scan(0), timestamp=float(t)) for t in range(3)]
    with PlaceRecognitionClient("http://test") as pr:
        with pytest.raises(APIError) as err:
            list(pr.stream("town", obs, robot_id="r1", window=2))
        assert err.value.unanswered == [1]  # type: ignore[attr-defined]
        with pytest.raises(ValueError, match="errors must be 'raise' or 'return'"):
            list(pr.stream("town", obs, robot_id="r1", errors="rasie"))


def test_a_fleet_run_ends_at_its_duration_even_when_a_call_hangs(monkeypatch):
    """A server that takes connections and never answers: the run asked for 1 s lasted as
    long as the client's read timeout and retries (minutes with the defaults). A call still
    waiting 5 s (GRACE_S) after the duration is cut there and counted as "duration"."""
    import contextlib
    import functools
    import socket
    import threading
    import time

    from overlapmamba.client import Timeouts, fleet
    from overlapmamba.client._replay import Drive

    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(16)
    held: list[socket.socket] = []

    def accept() -> None:
        with contextlib.suppress(OSError):
            while True:
                held.append(server.accept()[0])

    threading.Thread(target=accept, daemon=True).start()

    class Seq:
        name = "still"

        def __len__(self) -> int:
            return 50

        def xyzi(self, i: int) -> np.ndarray:
            return scan(0)

    drive = Drive(seq=Seq(), times=np.arange(50) * 0.1, poses=None, loop_radius=None)
    client = functools.partial(AsyncPlaceRecognitionClient, timeout=Timeouts(read=30.0))
    monkeypatch.setattr(fleet, "AsyncPlaceRecognitionClient", client)

    async def nothing(self: object, *args: object, **kwargs: object) -> dict:
        return {}

    async def empty_map(self: object, *args: object, **kwargs: object) -> Any:
        return SimpleNamespace(keyframes=0)

    monkeypatch.setattr(AsyncPlaceRecognitionClient, "create_map", empty_map)
    monkeypatch.setattr(AsyncPlaceRecognitionClient, "health", nothing)
    url = f"http://127.0.0.1:{server.getsockname()[1]}"
    t0 = time.monotonic()
    try:
        report, _ = asyncio.run(
            fleet.simulate(url, "m", [drive], robots=1, duration_s=1.0, rate_hz=10)
        )
    finally:
        server.close()
        for c in held:
            c.close()
    assert time.monotonic() - t0 < 10 and report.errors == {"duration": 1}, report.errors


async def test_observations_sent_again_on_a_stream_count_their_keyframes(live):
    """After a stream failed, resending its unanswered observations (as the docs say) got
    ``inserted=False, reason="existing", keyframe=None`` for those the server had carried
    out: the robot lost the keyframes it had made. Sent with ``retry=True`` they come back
    ``retried``, and their keyframe is counted, as an HTTP retry's is."""
    import dataclasses

    obs = [Observation(scan(i), 200.0 + 10 * i, insert="always") for i in range(2)]
    with PlaceRecognitionClient(live) as pr:
        pr.create_map("resend")
        first = list(pr.stream("resend", obs, robot_id="rr"))
        again = [dataclasses.replace(o, retry=True) for o in obs]
        sync = list(pr.stream("resend", again, robot_id="rr"))
    async with AsyncPlaceRecognitionClient(live) as apr:
        asyn = [r async for r in apr.stream("resend", again, robot_id="rr")]
    made = [r.keyframe for r in first]
    assert all(made) and all(r.inserted for r in first)
    for results in (sync, asyn):
        assert [r.insert_reason for r in results] == ["existing", "existing"]
        assert all(r.retried for r in results) and [r.keyframe for r in results] == made


def test_fleet_scoring_refuses_a_used_map_and_keeps_recall_within_its_loops(live, tiny_seq):
    """Found in review of the fleet simulator: on a map that already held keyframes (an
    earlier run's) every closure to them was scored wrong (precision 0.0); a right closure to
    a keyframe whose robot had not yet been answered counted in recall's numerator but not
    its denominator (recall 1.25); and after its pacing wait a robot sent once more past the
    run's end."""
    from overlapmamba.client._replay import Drive, open_drive
    from overlapmamba.client.fleet import _report, _Sample, simulate

    drive = open_drive(tiny_seq)
    with PlaceRecognitionClient(live) as pr:
        pr.create_map("fleet-used")
        pr.insert_keyframe("fleet-used", scan(0), keyframe_id="old", timestamp=0.0)
    with pytest.raises(ValueError, match="already holds 1 keyframes"):
        asyncio.run(simulate(live, "fleet-used", [drive], robots=1, duration_s=1, rate_hz=1))

    poses = np.zeros((4, 7))
    poses[:, 6] = 1.0
    poses[[1, 3], 0] = 100.0  # frames 0 and 2 at one place, 1 and 3 at another
    d = Drive(seq=drive.seq, times=np.arange(4.0) * 100, poses=poses, loop_radius=5.0)
    keyframes = {"a": (0, 0, 1.0), "b": (0, 1, 50.0)}  # b acknowledged long after it is used
    samples = [
        _Sample("r2", 0, 2, 10.0, 1.0, True, "a", None, None),  # a loop it could count on
        _Sample("r3", 0, 3, 20.0, 1.0, True, "b", None, None),  # right, but b not yet known
    ]
    report = _report(samples, keyframes, [d], 2, 60.0, 1.0, 30.0, 0.0)
    assert report.precision == 1.0 and report.queries_with_loop == 1 and report.recall == 1.0

    t0 = time.monotonic()
    late, _ = asyncio.run(
        simulate(live, "fleet-late", [drive], robots=1, duration_s=1, rate_hz=0.4)
    )
    assert late.observations == 1 and time.monotonic() - t0 < 2.0  # the second was due at 2.5 s


async def test_the_async_client_counts_the_tries_it_retried_and_sizes_its_pool():
    """Found in review: a load run's refusals (503 overloaded) that a retry got through were
    nowhere in its report, and beyond httpx's 100 connections robots waited in the client."""
    from overlapmamba.client import Retry

    answers = iter([503, 200, 503, 503])

    def handler(request: httpx.Request) -> httpx.Response:
        if next(answers) == 503:
            body = {"error": {"code": "overloaded", "message": "queue full", "detail": {}}}
            return httpx.Response(503, json=body, headers={"Retry-After": "0"})
        return httpx.Response(200, json={"queries": 7})

    transport = httpx.MockTransport(handler)
    retry = Retry(attempts=2, backoff_s=0.0)
    async with AsyncPlaceRecognitionClient("http://x", transport=transport, retry=retry) as pr:
        assert (await pr.stats())["queries"] == 7
        assert pr.retried == {"overloaded": 1}
        with pytest.raises(APIError, match="queue full"):  # failed for good: an error only
            await pr.stats()
        assert pr.retried == {"overloaded": 1}


async def _connections_at_once(max_connections: int | None, calls: int) -> int:
    """The most connections a server saw open at once while ``calls`` requests of an async
    client were in flight together (each answered once all have come, or after 1 s)."""
    open_now = most = 0
    everyone = asyncio.Event()

    async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        nonlocal open_now, most
        open_now += 1
        most = max(most, open_now)
        try:
            while (await reader.readuntil(b"\r\n\r\n")) is not None:
                if most >= calls:
                    everyone.set()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(everyone.wait(), 1.0)
                body = b'{"queries": 0}'
                head = "HTTP/1.1 200 OK\r\ncontent-type: application/json\r\n"
                writer.write(f"{head}content-length: {len(body)}\r\n\r\n".encode() + body)
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            open_now -= 1
            writer.close()

    srv = await asyncio.start_server(serve, "127.0.0.1", 0)
    port = srv.sockets[0].getsockname()[1]
    sized = {} if max_connections is None else {"max_connections": max_connections}
    try:
        async with AsyncPlaceRecognitionClient(f"http://127.0.0.1:{port}", **sized) as pr:
            await asyncio.gather(*(pr.stats() for _ in range(calls)))
    finally:
        srv.close()
    return most


async def test_the_async_client_holds_as_many_requests_in_flight_as_its_pool_is_sized():
    """Beyond httpx's 100 connections a fleet's robots waited in the client; a client sized
    for 150 has 150 requests on the wire at once, and the default still 100."""
    assert await _connections_at_once(150, 150) == 150
    assert await _connections_at_once(None, 150) == 100


def test_simulate_fleet_exits_1_when_no_observation_was_answered(live, synthetic_seq_dir, tmp_path):
    """Found in review: every observation refused (a sensor the service does not know) wrote
    latencies of 0 ms and exited 0."""
    out = tmp_path / "f.json"
    args = ["simulate-fleet", "--map", "fleet-none", "-s", str(synthetic_seq_dir), "--robots", "1"]
    args += ["--scans", "2", "--rate", "5", "--sensor", "lidar9000", "--out", str(out)]
    res = CliRunner().invoke(
        cli_app, [*args, "--plot", str(tmp_path / "f.png")], env={"OVERLAPMAMBA_URL": live}
    )
    assert res.exit_code == 1 and "no observation was answered" in res.output, res.output
    got = json.loads(out.read_text())
    assert got["latency_ms"]["p50"] is None and got["errors"] == {"unknown_sensor": 2}


async def test_the_async_client_reads_and_compresses_scans_off_its_event_loop(
    tmp_path, monkeypatch
):
    """Found in review: reading a scan file and compressing it ran on the event loop (stalls
    of tens of ms for every other task); they now run in a worker thread."""
    import threading

    from overlapmamba.client import _base

    where: list[str] = []
    real = _base.Calls.describe

    def spy(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        where.append(threading.current_thread().name)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(_base.Calls, "describe", spy)
    path = tmp_path / "s.bin"
    scan(0).tofile(path)

    def handler(request: httpx.Request) -> httpx.Response:
        return httpx.Response(400, json={"error": {"code": "bad", "message": "x", "detail": {}}})

    async with AsyncPlaceRecognitionClient(
        "http://x", transport=httpx.MockTransport(handler), compress=True
    ) as pr:
        with pytest.raises(APIError):
            await pr.describe(path)
    assert where and where[0] != threading.main_thread().name


def test_a_replay_that_stops_keeps_its_pose_graph_so_far_beside_the_path(
    live, synthetic_seq_dir, tmp_path, monkeypatch
):
    """observe --g2o whose server stops answering at the fifth scan: the graph of the four
    scans observed is kept as NAME.incomplete.g2o and said, the path is left as it was, a
    second stop keeps its own; the replay's own error is the one reported."""
    from overlapmamba.client import PlaceRecognitionClient
    from overlapmamba.client._exceptions import ConnectError
    from overlapmamba.client.posegraph import read_g2o

    real, calls = PlaceRecognitionClient.observe, []

    def stops(self, *args, **kwargs):
        calls.append(1)
        if len(calls) % 5 == 0:
            raise ConnectError("the server stopped answering")
        return real(self, *args, **kwargs)

    monkeypatch.setattr(PlaceRecognitionClient, "observe", stops)
    g2o, rec = tmp_path / "drive.g2o", tmp_path / "drive.mcap"
    args = ["observe", str(synthetic_seq_dir), "--map", "cli-stops", "--every", "4"]
    for n, stays in ((1, "was not written"), (2, "is as it was")):
        record = ["--record", str(rec)] if n == 1 else []  # both kept, each said
        res = CliRunner().invoke(
            cli_app, [*args, "--g2o", str(g2o), *record], env={"OVERLAPMAMBA_URL": live}
        )
        text = " ".join(res.output.split())
        assert res.exit_code == 2 and "the server stopped answering" in text, text
        kept = tmp_path / ("drive.incomplete.g2o" if n == 1 else "drive.incomplete-2.g2o")
        assert f"its pose graph so far is in {kept} ({g2o} {stays})" in text, text
        vertices, edges = read_g2o(kept)
        assert sorted(vertices)[:4] == [0, 4, 8, 12] and len(edges) >= 3
        if n == 1:
            assert not g2o.exists() and not rec.exists()
            assert (tmp_path / "drive.incomplete.mcap").stat().st_size > 0
            assert "what it recorded is in" in text, text
            g2o.write_text("EARLIER\n")  # a whole graph of an earlier replay
    assert g2o.read_text() == "EARLIER\n"
    monkeypatch.setattr(PlaceRecognitionClient, "observe", real)
    res = CliRunner().invoke(cli_app, [*args, "--g2o", str(g2o)], env={"OVERLAPMAMBA_URL": live})
    assert res.exit_code == 0 and "pose graph so far" not in res.output, res.output
    assert read_g2o(g2o)[0] and not (tmp_path / "drive.incomplete-3.g2o").exists()


def test_a_failed_replay_leaves_the_recording_at_its_path_and_keeps_its_own_beside(tmp_path):
    """Found in review: a replay that failed after recording something renamed its partial
    file over the whole recording already at the path."""
    from overlapmamba.client.recording import MapRecording

    path = tmp_path / "drive.mcap"
    with MapRecording(path) as rec:
        for i in range(5):
            rec.observation("r1", float(i), [i, 0, 0, 0, 0, 0, 1], keyframe_id=f"k{i}")
    whole = path.read_bytes()
    with pytest.raises(ConnectionError), MapRecording(path) as rec:
        rec.observation("r1", 9.0, [9, 0, 0, 0, 0, 0, 1])
        raise ConnectionError("server unreachable")
    assert path.read_bytes() == whole and rec.incomplete == tmp_path / "drive.incomplete.mcap"
    assert rec.incomplete.stat().st_size > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["drive.incomplete.mcap", "drive.mcap"]


def test_failed_replays_keep_every_partial_recording_and_their_own_error(tmp_path, monkeypatch):
    """Found in review: a second failed replay replaced the first one's incomplete file; a
    path without .mcap gave one without it; and a disk gone full while finishing raised the
    disk's error in the replay's place, the file left open and its .part behind."""
    from overlapmamba.client.recording import MapRecording, Writer

    finished = Writer.finish

    def fail(path):
        with pytest.raises(ConnectionError), MapRecording(path) as rec:
            rec.observation("r1", 1.0, [1, 0, 0, 0, 0, 0, 1])
            raise ConnectionError("server unreachable")
        return rec

    first, second = fail(tmp_path / "a.mcap"), fail(tmp_path / "a.mcap")
    assert (first.incomplete.name, second.incomplete.name) == (
        "a.incomplete.mcap",
        "a.incomplete-2.mcap",
    )
    assert fail(tmp_path / "drive").incomplete.name == "drive.incomplete.mcap"

    def full(self):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Writer, "finish", full)
    rec = fail(tmp_path / "b.mcap")  # the replay's ConnectionError, not the disk's
    assert rec._file.closed and rec.incomplete == tmp_path / "b.incomplete.mcap"
    with pytest.raises(OSError, match="No space"), MapRecording(tmp_path / "c.mcap") as rec:
        rec.observation("r1", 1.0, [1, 0, 0, 0, 0, 0, 1])
    assert rec._file.closed and rec.incomplete == tmp_path / "c.incomplete.mcap"
    assert not (tmp_path / "c.mcap").exists()  # never put at the path unfinished
    assert not [p.name for p in tmp_path.iterdir() if p.name.endswith(".part")]
    # Ctrl-C while finishing (found in the day's review): what was recorded is kept beside
    monkeypatch.undo()

    def interrupted(self):
        finished(self)
        raise KeyboardInterrupt

    monkeypatch.setattr(Writer, "finish", interrupted)
    with pytest.raises(KeyboardInterrupt), MapRecording(tmp_path / "d.mcap") as rec:
        rec.observation("r1", 1.0, [1, 0, 0, 0, 0, 0, 1])
    assert rec.incomplete == tmp_path / "d.incomplete.mcap" and rec.incomplete.stat().st_size
    assert fail(tmp_path / "e.mcap").incomplete == tmp_path / "e.incomplete.mcap"


def test_the_cli_sends_a_drives_manifest_mount_and_the_users_over_it(
    live, synthetic_seq_dir, tmp_path, monkeypatch
):
    """Found in review: ingest, observe and simulate-fleet sent a synthetic drive's scans
    without the mounting its manifest records (``overlapmamba eval`` reads it): a robot's
    drive was described as if from the car's roof."""
    from overlapmamba.client._base import Calls

    drive = tmp_path / "amr"
    (drive / "velodyne").mkdir(parents=True)
    for i in range(3):
        shutil.copy(synthetic_seq_dir / "velodyne" / f"{i:06d}.bin", drive / "velodyne")
    poses = (synthetic_seq_dir / "poses.txt").read_text().splitlines()[:3]
    (drive / "poses.txt").write_text("\n".join(poses) + "\n")
    mounting = {"name": "amr", "height": 0.35, "pitch_deg": 1.5, "roll_deg": 0.0}
    (drive / "manifest.json").write_text(json.dumps({"resolved": {"mounting": mounting}}))
    sent: list[str | None] = []
    params_of = Calls._sensor

    def spy(self, sensor, mount=None):
        params = params_of(self, sensor, mount)
        sent.append(params.get("mount"))
        return params

    monkeypatch.setattr(Calls, "_sensor", spy)
    env = {"OVERLAPMAMBA_URL": live}

    def run(*args: str) -> None:
        res = CliRunner().invoke(cli_app, list(args), env=env)
        assert res.exit_code == 0, res.output

    run("ingest", str(drive), "--map", "cli-mounted")
    run("observe", str(drive), "--map", "cli-mounted-obs")
    run("simulate-fleet", "--map", "cli-mounted-fleet", "-s", str(drive), "--robots", "1",
        "--scans", "3", "--rate", "20", "--out", str(tmp_path / "f.json"),
        "--plot", str(tmp_path / "f.png"))  # fmt: skip
    assert sent == ["0.35,1.5,0"] * 9
    sent.clear()
    run("ingest", str(drive), "--map", "cli-mounted", "--mount", "0.5")
    assert sent == ["0.5"] * 3
    with PlaceRecognitionClient(live) as pr:  # the keyframes were described from 0.35 m
        scan0 = np.fromfile(drive / "velodyne" / "000000.bin", np.float32).reshape(-1, 4)
        at = pr.query("cli-mounted", scan0, k=1, verify=False, mount="0.35,1.5")
        roof = pr.query("cli-mounted", scan0, k=1, verify=False)
    assert at.matches[0].distance < 1e-4 < roof.matches[0].distance


def test_a_stopped_replay_says_whether_a_recording_stood_at_its_path(
    synthetic_seq_dir, tmp_path, monkeypatch
):
    """Found in review: the note said the path "is as it was" where nothing had stood."""
    import overlapmamba.client.cli as cli

    class Stops:  # a client whose server goes away after two observations
        calls = 0

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return None

        def create_map(self, map_id):
            return None

        def observe(self, *args, **kwargs):
            Stops.calls += 1
            if Stops.calls > 2:
                raise KeyboardInterrupt
            lc = SimpleNamespace(accepted=False, keyframe_id=None, verified=None)
            return SimpleNamespace(keyframe="k", matches=[], loop_closure=lc)

    monkeypatch.setattr(cli, "client", lambda *args: Stops())
    for existed, says in ((False, "was not written"), (True, "is as it was")):
        Stops.calls = 0
        rec = tmp_path / f"{existed}.mcap"
        if existed:
            rec.write_bytes(b"an earlier recording")
        args = ["observe", str(synthetic_seq_dir), "--map", "m", "--record", str(rec)]
        res = CliRunner().invoke(cli.app, args)
        assert res.exit_code == 130, res.output
        assert says in " ".join(res.output.split())
        assert rec.exists() == existed


def test_stats_watch_into_a_pipe_prints_each_refresh_as_it_comes(live):
    """Found in review: ``stats --watch`` into a file or a pipe (a log) wrote nothing until
    Ctrl-C, and nothing at all when stopped by SIGTERM: the table lived in a terminal-only
    display. Each refresh is now printed whole and flushed."""
    import signal

    cmd = [sys.executable, "-c", "from overlapmamba.client.cli import main; main()"]
    args = ["stats", "--watch", "--interval", "0.2", "--url", live]
    proc = subprocess.Popen([*cmd, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        time.sleep(6.0)  # the interpreter's start, then refreshes every 0.2 s
    finally:
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=30)
    tables = stdout.decode().count("loop-closure rate")
    assert tables >= 2, (stdout.decode()[-500:], stderr.decode()[-500:])


def test_a_drive_of_a_sensor_the_service_does_not_know_makes_no_map(live, synthetic_seq_dir):
    """Found in review: ``ingest`` and ``observe`` made the map, then met the unknown sensor
    at the first scan (400), leaving an empty map behind. Refused before, naming the ones
    the service knows."""
    runner = CliRunner()
    for command in ("ingest", "observe"):
        args = [command, str(synthetic_seq_dir), "--map", f"never-{command}", "--sensor", "nosuch"]
        res = runner.invoke(cli_app, [*args, "--url", live])
        said = " ".join(res.output.split())
        assert res.exit_code == 2 and "knows no sensor 'nosuch'" in said and "vlp16" in said
    with PlaceRecognitionClient(live) as pr:
        assert not {m.map_id for m in pr.list_maps()} & {"never-ingest", "never-observe"}


def test_simulate_fleet_checks_where_its_outputs_go_before_the_run(synthetic_seq_dir, tmp_path):
    """Found in review: a --plot format matplotlib does not write, or an --out under a file,
    was found after the whole simulation (the JSON written, the plot lost). Both are refused
    before a robot starts (here no service even listens)."""
    (tmp_path / "afile").write_text("")
    base = ["simulate-fleet", "--map", "m", "-s", str(synthetic_seq_dir), "--duration", "1"]
    for extra, says in (
        (["--plot", str(tmp_path / "p.txt")], "allowed formats are"),
        (["--out", str(tmp_path / "afile" / "r.json")], "afile is a file, not a folder"),
        (["--out", str(tmp_path)], "is a folder"),
    ):
        res = CliRunner().invoke(cli_app, [*base, *extra, "--url", "http://127.0.0.1:9"])
        said = " ".join(res.output.split())
        assert res.exit_code == 2 and says in said and "connect" not in said, said
