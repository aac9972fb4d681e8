"""A real ``overlapmamba serve`` in a child process, for tests, benchmarks and scripts that need
the service as users run it (uvicorn, its own process, a port):

    with serve_process(data_dir, model=MODEL) as srv:
        httpx.get(f"{srv.url}/v1/maps")
        ...
    srv.log()                                  # what it wrote, after or during the run

The server listens on a free loopback port and is yielded once ``/readyz`` answers 200; on
exit it gets SIGTERM (it drains and snapshots), then SIGKILL after 15 s. Its output goes to
a file, not a pipe: a pipe nobody drains fills up after a few hundred access lines and
blocks the server.
"""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx


@dataclass
class ServerProcess:
    url: str
    proc: subprocess.Popen[bytes]
    log_path: Path

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def serve_command() -> list[str]:
    """The installed ``overlapmamba`` script beside this interpreter, else ``-m``."""
    exe = Path(sys.executable).parent / "overlapmamba"
    return [str(exe)] if exe.is_file() else [sys.executable, "-m", "overlapmamba"]


@contextlib.contextmanager
def serve_process(
    data_dir: Path,
    *,
    model: Path,
    env: dict[str, str] | None = None,
    inherit_settings: bool = True,
    log_path: Path | None = None,
    startup_s: float = 60.0,
    cwd: Path | None = None,
) -> Iterator[ServerProcess]:
    """``overlapmamba serve`` of ``model`` over ``data_dir`` with ``env`` added to this
    process's environment (``inherit_settings=False``: without this process's
    ``OVERLAPMAMBA_*`` variables, so only ``env`` configures it). The log goes to
    ``log_path`` (default: beside ``data_dir``). RuntimeError, with the log's tail, when
    the server exits or is not ready within ``startup_s``."""
    port = free_port()
    base = dict(os.environ)
    if not inherit_settings:
        base = {k: v for k, v in base.items() if not k.startswith("OVERLAPMAMBA_")}
    cmd = [*serve_command(), "serve", "--port", str(port)]
    cmd += ["--data-dir", str(data_dir), "--model", str(model)]
    log_path = log_path or Path(data_dir).parent / f"server-{port}.log"
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "wb") as log_file:
        proc = subprocess.Popen(
            cmd, cwd=cwd, env={**base, **(env or {})}, stdout=log_file, stderr=subprocess.STDOUT
        )
    srv = ServerProcess(f"http://127.0.0.1:{port}", proc, log_path)
    try:
        _wait_ready(srv, startup_s)
        yield srv
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def _wait_ready(srv: ServerProcess, limit_s: float) -> None:
    deadline = time.monotonic() + limit_s
    with httpx.Client(base_url=srv.url, timeout=5) as client:
        while time.monotonic() < deadline:
            if srv.proc.poll() is not None:
                raise RuntimeError(
                    f"server exited with {srv.proc.returncode} before ready:\n{srv.log()[-3000:]}"
                )
            with contextlib.suppress(httpx.TransportError):
                if client.get("/readyz").status_code == 200:
                    return
            time.sleep(0.2)
    raise RuntimeError(f"server not ready after {limit_s:.0f} s:\n{srv.log()[-3000:]}")
