"""Shared helpers for the service tests: scans, an app with its lifespan, a real server."""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import httpx
import numpy as np

from service.app import create_app
from service.encoder import Encoder
from service.settings import Settings

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


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def server(
    data_dir: Path, env: dict[str, str] | None = None
) -> Iterator[tuple[str, subprocess.Popen]]:
    """A real `overlapmamba serve` process on a free loopback port, ready when yielded.
    Its log goes to a file (``server_log(proc)``), not a pipe: a pipe nobody drains fills
    up after a few hundred access lines and blocks the server."""
    port = free_port()
    cmd = [sys.executable, "-m", "overlapmamba", "serve", "--port", str(port)]
    cmd += ["--data-dir", str(data_dir), "--model", str(MODEL)]
    log_path = Path(data_dir).parent / f"server-{port}.log"
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "wb") as log_file:
        proc = subprocess.Popen(
            cmd,
            cwd=ROOT,
            env={**os.environ, "OVERLAPMAMBA_BATCHING__INTRA_OP_THREADS": "2", **(env or {})},
            stdout=log_file,
            stderr=subprocess.STDOUT,
        )
    proc.log_path = log_path  # type: ignore[attr-defined]
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while True:
            if proc.poll() is not None:
                raise RuntimeError(f"server exited: {server_log(proc)[-2000:]}")
            try:
                if httpx.get(f"{url}/readyz", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError("server did not become ready in 60 s")
            time.sleep(0.2)
        yield url, proc
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def server_log(proc: subprocess.Popen) -> str:
    return Path(proc.log_path).read_text(errors="replace")  # type: ignore[attr-defined]
