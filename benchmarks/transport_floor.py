"""The HTTP transport's floor: what posting a scan costs when the server does no work at all.

``POST /floor?wait_ms=W`` reads the body as the service does (streamed, size-counted,
joined), waits W ms without using a core (``asyncio.sleep``: the client still waits as long
as for an encoder), and answers JSON the size of a descriptor answer, with the time it
waited. It runs in uvicorn with uvicorn's defaults, as ``overlapmamba serve`` does (uvloop
and httptools where installed), in its own process.

``benchmarks/serving_http.py`` times it beside the service, in the same alternating blocks,
with W = the bare path's median so far: HTTP time − waited time is the cost of the client
(httpx), the loopback transfer of the body, uvicorn and waking up after a wait, with no
FastAPI, no middleware and no thread hop. (bare + that) ÷ bare is the lowest HTTP ÷ bare
ratio any server on this stack could reach on this machine.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import Response
from starlette.routing import Route

from overlapmamba.service.process import free_port

ANSWER = [0.0625] * 256  # a descriptor's worth of JSON


async def floor(request: Request) -> Response:
    chunks: list[bytes] = []
    size = 0
    async for chunk in request.stream():
        size += len(chunk)
        chunks.append(chunk)
    body = b"".join(chunks)
    t0 = time.perf_counter()
    await asyncio.sleep(float(request.query_params.get("wait_ms", "0")) / 1e3)
    waited_ms = (time.perf_counter() - t0) * 1e3
    out = {"bytes": len(body), "waited_ms": waited_ms, "descriptor": ANSWER}
    return Response(json.dumps(out), media_type="application/json")


app = Starlette(routes=[Route("/floor", floor, methods=["POST"])])


@contextlib.contextmanager
def floor_server(startup_s: float = 30.0) -> Iterator[str]:
    """This module's app in uvicorn in a subprocess; its base URL once it answers."""
    port = free_port()
    cmd = [sys.executable, "-m", "uvicorn", "transport_floor:app", "--port", str(port)]
    proc = subprocess.Popen(
        [*cmd, "--log-level", "warning"],
        cwd=Path(__file__).parent,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + startup_s
        while True:
            if proc.poll() is not None:
                err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
                raise RuntimeError(f"the transport-floor server exited: {err[-2000:]}")
            try:
                httpx.post(f"{url}/floor", content=b"", timeout=1).raise_for_status()
                break
            except httpx.HTTPError:
                if time.monotonic() > deadline:
                    raise RuntimeError(
                        f"the transport-floor server is not up after {startup_s} s"
                    ) from None
                time.sleep(0.1)
        yield url
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
