"""Shared helpers for the service tests: scans, an app with its lifespan, a real server
(:mod:`overlapmamba.service.process`, which the benchmarks use too)."""

from __future__ import annotations

import asyncio
import contextlib
import subprocess
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import httpx
import numpy as np

from overlapmamba.service.app import create_app
from overlapmamba.service.encoder import Encoder
from overlapmamba.service.process import serve_process
from overlapmamba.service.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "models" / "overlapmamba-hdl64.onnx"
OCTET = {"content-type": "application/octet-stream"}


def scan(seed: int, yaw_deg: float = 0.0) -> np.ndarray:
    """(N, 4) float32 xyzi: walls, poles and ground around the origin, turned by yaw_deg."""
    from conftest import make_world

    xyz = make_world(np.random.default_rng(seed))
    xyz = xyz[np.linalg.norm(xyz[:, :2], axis=1) > 2.0]
    t = np.deg2rad(yaw_deg)
    rot = np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]])
    out = np.zeros((len(xyz), 4), np.float32)
    out[:, :3] = xyz @ rot.T.astype(np.float32)
    out[:, 3] = 0.5
    return out


def rewritten(folder: Path, sensor_input: str) -> Encoder:
    """The shipped file copied into ``folder`` and rewritten to take ``sensor_input`` (another
    model id: the weights are the same, the descriptors are not), loaded."""
    import shutil

    from overlapmamba.train.modelfile import read_metadata, with_sensor_input

    path = folder / f"{sensor_input}.onnx"
    shutil.copyfile(MODEL, path)
    meta = with_sensor_input(path, sensor_input)
    assert meta.sensor_input == sensor_input and meta.model_id != read_metadata(MODEL).model_id
    return Encoder(path)


@contextlib.asynccontextmanager
async def running(settings: Settings, encoder: Encoder) -> AsyncIterator[httpx.AsyncClient]:
    app = create_app(settings, encoder=encoder)
    async with app.router.lifespan_context(app):
        while not app.state.ready:  # maps load in the background after start-up
            if app.state.stage.startswith("failed"):
                raise RuntimeError(app.state.stage)
            await asyncio.sleep(0.01)
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            client.app = app  # type: ignore[attr-defined]
            yield client


async def three_keyframes_then_a_turned_query(
    c: httpx.AsyncClient,
) -> tuple[dict, dict]:
    """A new map of three keyframes (scans 0–2), then scan 2 turned by 40° queried: its best
    match and the descriptor of scan 2 (``/v1/descriptors``), for a test to check a model
    file's descriptor end to end."""
    assert (await c.put("/v1/maps/town", json={"index": "flat"})).status_code == 201
    for i in range(3):
        r = await c.post(
            "/v1/maps/town/keyframes",
            params={"keyframe_id": f"k{i}", "timestamp": 100.0 + i, "robot_id": "r1"},
            content=scan(i).tobytes(),
            headers=OCTET,
        )
        assert r.status_code == 201, r.text
    r = await c.post(
        "/v1/maps/town/query", params={"k": 2}, content=scan(2, 40.0).tobytes(), headers=OCTET
    )
    assert r.status_code == 200, r.text
    d = await c.post("/v1/descriptors", content=scan(2).tobytes(), headers=OCTET)
    assert d.status_code == 200, d.text
    return r.json()["matches"][0], d.json()


@contextlib.contextmanager
def server(
    data_dir: Path, env: dict[str, str] | None = None, model: Path = MODEL
) -> Iterator[tuple[str, subprocess.Popen]]:
    """A real `overlapmamba serve` process of ``model`` (default: the shipped file) on a free
    loopback port, ready when yielded (:func:`overlapmamba.service.process.serve_process`);
    its log: ``server_log(proc)``. It encodes as the defaults say (a lane a core) unless
    ``env`` says otherwise."""
    with serve_process(data_dir, model=model, env=env or {}, cwd=ROOT) as srv:
        srv.proc.log_path = srv.log_path  # type: ignore[attr-defined]
        yield srv.url, srv.proc


def server_log(proc: subprocess.Popen) -> str:
    return Path(proc.log_path).read_text(errors="replace")  # type: ignore[attr-defined]


def ws_scope(path: str, query: str, headers: dict[str, str] | None = None) -> dict:
    """The ASGI scope of a WebSocket opened on ``path?query`` (tests drive the app directly)."""
    return {
        "type": "websocket",
        "path": path,
        "raw_path": path.encode(),
        "query_string": query.encode(),
        "headers": [(k.lower().encode(), v.encode()) for k, v in (headers or {}).items()],
        "scheme": "ws",
        "server": ("test", 80),
        "client": ("127.0.0.1", 1),
        "root_path": "",
        "subprotocols": [],
        "asgi": {"version": "3.0"},
        "state": {},
    }
