"""Blocking work off the event loop, in the worker threads that routes, use cases and the scan
pipeline share (anyio's default pool, the one Starlette runs sync routes in)."""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Callable
from contextvars import ContextVar
from pathlib import Path
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


def cores(cgroup: Path = Path("/sys/fs/cgroup")) -> int:
    """The cores this process may use: those it may run on (its CPU affinity, which a
    container's cpuset narrows; the machine's count where the platform has no affinity),
    bounded by its cgroup's CPU quota (``docker run --cpus``, a pod's ``limits.cpu``), which
    leaves the affinity whole: on a 64-core host limited to 2 CPUs, 2, rounded up."""
    if hasattr(os, "sched_getaffinity"):
        have = max(1, len(os.sched_getaffinity(0)))
    else:
        have = max(1, os.cpu_count() or 1)
    quota = cpu_quota(cgroup)
    return have if quota is None else max(1, min(have, math.ceil(quota - 1e-9)))


def cpu_quota(cgroup: Path = Path("/sys/fs/cgroup"), own: str | None = None) -> float | None:
    """CPUs the CPU quota allows this process (quota ÷ period; the tightest of its cgroup
    and those above it), or None where there is none: cgroup v2's ``cpu.max`` ("max
    100000": none), else v1's ``cpu.cfs_quota_us`` (-1: none). ``own``: the process's
    cgroup path (default: from /proc/self/cgroup; a container's is its root)."""
    if own is None:
        try:
            lines = Path("/proc/self/cgroup").read_text().splitlines()
            own = next((ln[3:] for ln in lines if ln.startswith("0::")), "/")
        except OSError:
            own = "/"
    quotas = []
    here = Path(own.strip("/"))
    for rel in [here, *here.parents]:  # up to the root
        try:
            text = (cgroup / rel / "cpu.max").read_text().split()
            if len(text) == 2 and text[0] != "max":
                quotas.append(int(text[0]) / int(text[1]))
        except (OSError, ValueError, ZeroDivisionError):
            continue
    if quotas:
        return min(quotas)
    try:
        quota = int((cgroup / "cpu" / "cpu.cfs_quota_us").read_text())
        period = int((cgroup / "cpu" / "cpu.cfs_period_us").read_text())
    except (OSError, ValueError):
        return None
    return quota / period if quota > 0 and period > 0 else None


def encoder_threads(lanes: int, intra_op_threads: int) -> tuple[int, int]:
    """The settings' ``batching.lanes`` and ``batching.intra_op_threads`` (0: automatic) →
    (encoder calls at once, onnxruntime threads a call): by default a lane a core, each call
    on one thread; lanes given and threads not, the cores shared among them."""
    have = cores()
    n = lanes or have
    return n, intra_op_threads or max(1, have // n)
