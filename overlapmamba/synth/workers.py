"""Worker processes for the generator: safe to start from a threaded parent, bounded to wait on.

A process that has run onnxruntime or torch holds native thread pools. A ``fork``ed child
inherits their locks but not their threads, and deadlocks the first time it touches them (the
garbage collector freeing an inherited onnxruntime session is enough). So workers start with
``forkserver`` (``spawn`` where that is missing) and build their state from their arguments.

Every wait is bounded: a worker that dies is reported at once, naming the jobs it may have been
running; a pool that finishes no job for ``stall_timeout_s`` is killed and reported the same
way. Nothing waits forever.
"""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any, TypeVar

J = TypeVar("J")
R = TypeVar("R")

DEFAULT_STALL_TIMEOUT_S = 600.0


class WorkerError(RuntimeError):
    """A worker process died, or made no progress in time. Names the jobs concerned."""


def start_method() -> str:
    """``forkserver`` where the platform has it, else ``spawn``; never ``fork``."""
    return "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"


def _single_threaded(initializer: Callable[..., None] | None, *initargs: Any) -> None:
    # One process per core: a BLAS thread pool per worker on top oversubscribes the cores
    # (measured: 2 workers ran 2.1× *slower* than one until this was set). threadpoolctl only
    # limits libraries already loaded, and a fresh worker has not loaded numpy's BLAS yet.
    import numpy  # noqa: F401
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    if initializer is not None:
        initializer(*initargs)


def run_jobs(
    fn: Callable[[J], R],
    jobs: Iterable[J],
    *,
    workers: int,
    initializer: Callable[..., None] | None = None,
    initargs: tuple = (),
    stall_timeout_s: float = DEFAULT_STALL_TIMEOUT_S,
    what: str = "job",
) -> Iterator[tuple[int, R]]:
    """Run ``fn`` on every job in ``workers`` processes; yield ``(job index, result)`` as jobs
    finish (in completion order).

    ``fn``, the jobs and ``initargs`` must pickle: workers share nothing with the parent.
    At most ``2 × workers`` jobs are queued at once, so a stall names the few in flight.
    Raises :class:`WorkerError` when a worker dies or no job finishes for ``stall_timeout_s``;
    an exception raised by ``fn`` itself is re-raised with a note naming the job.
    """
    if workers < 1:
        raise ValueError(f"workers must be ≥ 1, got {workers}")
    if not stall_timeout_s > 0:
        raise ValueError(f"stall_timeout_s must be > 0, got {stall_timeout_s}")
    todo = enumerate(jobs)
    pool = ProcessPoolExecutor(
        max_workers=workers,
        mp_context=mp.get_context(start_method()),
        initializer=_single_threaded,
        initargs=(initializer, *initargs),
    )
    pending: dict[Future, int] = {}
    clean = False
    try:
        for i, job in todo:
            pending[pool.submit(fn, job)] = i
            if len(pending) >= 2 * workers:
                break
        while pending:
            done, _ = wait(pending, timeout=stall_timeout_s, return_when=FIRST_COMPLETED)
            if not done:
                raise WorkerError(
                    f"no {what} finished in {stall_timeout_s:g} s; a worker is stuck "
                    f"({what}s in flight: {sorted(pending.values())})"
                )
            for fut in sorted(done, key=pending.__getitem__):
                i = pending.pop(fut)
                try:
                    result = fut.result()
                except BrokenProcessPool as err:
                    raise WorkerError(
                        f"a worker process died while running {what} {i} "
                        f"({what}s in flight: {sorted([i, *pending.values()])}): {err}"
                    ) from err
                except Exception as err:
                    err.add_note(f"raised by {what} {i} in a worker process")
                    raise
                nxt = next(todo, None)
                if nxt is not None:
                    pending[pool.submit(fn, nxt[1])] = nxt[0]
                yield i, result
        clean = True
    finally:
        if not clean:  # an error, a stall, or the caller stopped early: nothing lingers
            _kill(pool)
        pool.shutdown(wait=True, cancel_futures=True)


def _kill(pool: ProcessPoolExecutor) -> None:
    # A stuck worker never returns to take the shutdown message; end it. The executor keeps
    # its processes in a private map (Python 3.14 adds terminate_workers() for this).
    procs = getattr(pool, "_processes", None) or {}
    for proc in list(procs.values()):
        if proc.is_alive():
            proc.kill()
    for proc in list(procs.values()):
        proc.join(timeout=5)
