"""Blocking work off the event loop, in the worker threads that routes, use cases and the scan
pipeline share (anyio's default pool, the one Starlette runs sync routes in)."""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from contextvars import ContextVar
from typing import ParamSpec, TypeVar

import anyio.to_thread

P = ParamSpec("P")
T = TypeVar("T")

# When the request under way must be answered by (time.monotonic(); the guard's timeout),
# carried into the worker threads with the request's context: work queued for it past then
# is not worth doing. None outside an HTTP request (the stream's frames, start-up).
request_deadline: ContextVar[float | None] = ContextVar("request_deadline", default=None)


async def in_thread(fn: Callable[P, T], *args: P.args, **kwargs: P.kwargs) -> T:
    """``fn(*args, **kwargs)`` in a worker thread; the caller's task waits for it."""
    return await anyio.to_thread.run_sync(functools.partial(fn, *args, **kwargs))


def cores() -> int:
    """The cores this process may run on (its CPU affinity, which a container's cpuset
    narrows; the machine's count where the platform has no affinity)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def encoder_threads(lanes: int, intra_op_threads: int) -> tuple[int, int]:
    """The settings' ``batching.lanes`` and ``batching.intra_op_threads`` (0: automatic) →
    (encoder calls at once, onnxruntime threads a call): by default a lane a core, each call
    on one thread; lanes given and threads not, the cores shared among them."""
    have = cores()
    n = lanes or have
    return n, intra_op_threads or max(1, have // n)
