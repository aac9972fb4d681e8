"""Where a scan's sensor sits, as the clients send it: a call's own mount before the
client's, a stream observation's before its stream's, and a recorded drive's from its
manifest (as ``overlapmamba eval`` reads it) unless the user names one."""

from __future__ import annotations

import json
import shutil

import httpx
import numpy as np
import pytest

from overlapmamba.client import AsyncPlaceRecognitionClient, Observation, PlaceRecognitionClient
from overlapmamba.client._replay import open_drive
from overlapmamba.client._stream import observation_frames

pytestmark = pytest.mark.anyio

SCAN = np.random.default_rng(0).normal(0, 5, (200, 4)).astype(np.float32)


def _recording(seen: list[httpx.Request]) -> httpx.MockTransport:
    """Records each request and answers as the service would, enough for the clients."""

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        path = request.url.path
        kf = {"keyframe_id": "a", "robot_id": "r", "session_id": "s", "timestamp": 1.0}
        lc = {"accepted": False, "keyframe_id": None, "threshold": 0.1, "margin_top1_top2": None}
        answers = {
            "/v1/descriptors": {"descriptor": [0.0] * 4, "model_id": "m", "timings_ms": {}},
            "/v1/descriptors:batch": {
                "descriptors": [[0.0] * 4],
                "model_id": "m",
                "timings_ms": [{}],
            },
            "/v1/maps/m/keyframes": {**kf, "created": True},
            "/v1/maps/m/query": {"matches": [], "loop_closure": lc, "timings_ms": {}},
            "/v1/maps/m/observe": {
                "matches": [],
                "loop_closure": lc,
                "keyframe": None,
                "inserted": False,
                "timings_ms": {},
            },
        }
        return httpx.Response(200, json=answers[path])

    return httpx.MockTransport(handler)


def _mounts(seen: list[httpx.Request]) -> list[str | None]:
    return [r.url.params.get("mount") for r in seen]


def test_a_calls_own_mount_wins_over_the_clients_and_the_clients_fills_in():
    seen: list[httpx.Request] = []
    with PlaceRecognitionClient(
        "http://t", transport=_recording(seen), mount="0.7", sensor="vlp16"
    ) as pr:
        pr.describe(SCAN)
        pr.describe(SCAN, mount=(1.8, 5.0))
        pr.describe_batch([SCAN], mount="0.35,1.5")
        pr.insert_keyframe("m", SCAN, keyframe_id="a", timestamp=1.0, mount="0.5")
        pr.query("m", SCAN, k=1, mount="0.6")
        pr.query("m", descriptor=np.zeros(4), k=1, mount="0.6")  # a descriptor has no mount
        pr.observe("m", SCAN, robot_id="r", timestamp=1.0, mount="0.4,0,2")
        pr.observe("m", SCAN, robot_id="r", timestamp=2.0)
        with pytest.raises(ValueError, match="pitch_deg input should be less than or equal to 45"):
            pr.describe(SCAN, mount="0.7,60")
        pr.describe(SCAN, mount=0.35)  # a height alone
        with pytest.raises(ValueError, match=r"HEIGHT\[,PITCH\[,ROLL\]\] as a string"):
            pr.describe(SCAN, mount={"height": 0.35})
        with pytest.raises(ValueError, match="as numbers"):
            pr.describe(SCAN, mount=("low",))
    assert _mounts(seen) == [
        *("0.7", "1.8,5.0", "0.35,1.5", "0.5", "0.6", None, "0.4,0,2", "0.7", "0.35")
    ]
    assert {r.url.params.get("sensor") for r in seen if r.content[:1] != b"{"} == {"vlp16"}


async def test_the_async_client_sends_a_calls_own_mount_too():
    seen: list[httpx.Request] = []
    async with AsyncPlaceRecognitionClient("http://t", transport=_recording(seen)) as pr:
        await pr.describe(SCAN)
        await pr.describe(SCAN, mount="1.2")
        await pr.describe_batch([SCAN], mount=(0.9,))
        await pr.insert_keyframe("m", SCAN, keyframe_id="a", timestamp=1.0, mount="0.5")
        await pr.query("m", SCAN, k=1, mount="0.6")
        await pr.observe("m", SCAN, robot_id="r", timestamp=1.0, mount="0.4")
    assert _mounts(seen) == [None, "1.2", "0.9", "0.5", "0.6", "0.4"]


def test_a_stream_observation_names_its_own_mount():
    meta, _ = observation_frames(Observation(SCAN, 1.0, mount=(0.35, 1.5)), 0, compress=False)
    assert json.loads(meta)["mount"] == "0.35,1.5"
    meta, _ = observation_frames(Observation(SCAN, 1.0), 1, compress=False)
    assert "mount" not in json.loads(meta)  # the stream's, or the map's
    with pytest.raises(ValueError, match="HEIGHT"):
        observation_frames(Observation(SCAN, 1.0, mount="low"), 2, compress=False)


def _with_mounting(src, dst, mounting):
    shutil.copytree(src, dst)
    manifest = {"config": {"sensor": "vlp16"}, "resolved": {"mounting": mounting}}
    (dst / "manifest.json").write_text(json.dumps(manifest))
    return dst


def test_a_drive_takes_its_manifests_mount_unless_one_is_named(synthetic_seq_dir, tmp_path):
    """Found in review: ``overlapmamba eval`` read a synthetic drive's mounting from its
    manifest, the client's ingest, observe and simulate-fleet did not (a robot's drive at
    0.35 m went to the service as the model's own 1.73 m)."""
    low = {"name": "amr", "height": 0.35, "pitch_deg": 1.5, "roll_deg": 0.0}
    drive = open_drive(_with_mounting(synthetic_seq_dir, tmp_path / "amr", low))
    assert (drive.sensor, drive.mount) == ("vlp16", "0.35,1.5,0")
    assert open_drive(tmp_path / "amr", mount="0.5").mount == "0.5"  # the user's wins
    # the model's own mount is sent too: a map declaring a robot's must not stand in for it
    car = {"name": "car", "height": 1.73, "pitch_deg": 0.0, "roll_deg": 0.0}
    assert open_drive(_with_mounting(synthetic_seq_dir, tmp_path / "car", car)).mount == "1.73,0,0"
    assert open_drive(synthetic_seq_dir).mount is None  # no manifest: none sent
