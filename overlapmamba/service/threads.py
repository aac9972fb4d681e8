"""Blocking work off the event loop, in the worker threads that routes, use cases and the scan
pipeline share (anyio's default pool, the one Starlette runs sync routes in)."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import ParamSpec, TypeVar

import anyio.to_thread

P = ParamSpec("P")
T = TypeVar("T")


async def in_thread(fn: Callable[P, T], *args: P.args, **kwargs: P.kwargs) -> T:
    """``fn(*args, **kwargs)`` in a worker thread; the caller's task waits for it."""
    return await anyio.to_thread.run_sync(functools.partial(fn, *args, **kwargs))
