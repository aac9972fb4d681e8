"""Where registration runs: in the server's own worker threads, or in child processes
(``verify.processes``).

small_gicp keeps Python's lock for the whole of each call (voxel grid, k-d tree, normals,
GICP, nearest-neighbour search): while one request prepares or registers, no other
request's Python runs, on any core. Under a fleet's load that lock, not the cores, bounded
the server: with registration in its threads the machine had cores to spare while the
server waited (the e2e report's ``cpu``, ``reports/e2e/load-*-processes-0.json``), and
py-spy found registration in most of the time the lock was held. With ``processes`` ≥ 1
the query's side is prepared, kept, packed into a keyframe's geometry and registered in a
child process; this process sends the query's thinned points once and each candidate's
blob, and gets verdicts back. What a fleet gets from it: ``docs/deploy.md``, sizing.

    prepare(xyz)  → Held: the query's side, where it is kept (this process or a child's
                    key), its grid size, and why it cannot be registered when it cannot
    geometry(h)   → the keyframe's blob (``registration.keyframe_geometry``)
    verify(h, …)  → one verdict per candidate (``verify.verify_candidates``)

Each child keeps the ``HELD`` latest prepared queries; a query it no longer holds (evicted,
or the child restarted) is prepared again from the points the Held keeps, so the results
are the same either way. A child that dies is started again and the call tried once more;
failing again, the query's candidates are refused with the reason, and a keyframe's
geometry answers 503 (retry: nothing is stored without it).

A call still in its child's queue at its request's deadline (the guard's timeout, carried
in the request's context; ``stale_s``, the service's request timeout, after the call where
there is none) is skipped there: its request has been answered already (504), and registering it
would only delay the calls queued behind it, whose requests would time out in turn. The
query's candidates are then refused with the reason and a keyframe's geometry answers 503,
as above; ``usage()["stale"]`` counts them (``overlapmamba_registration_stale_total``).
With stale calls skipped, no call waits for its answer much past ``stale_s``: one that waits
twice as long is taken for a child that hangs, which is killed and then started again as a
dead one is.
"""

from __future__ import annotations

import contextlib
import ctypes
import itertools
import logging
import multiprocessing
import os
import signal
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from overlapmamba.service.errors import Unavailable
from overlapmamba.service.registration import (
    Prepared,
    RegistrationParams,
    keyframe_geometry,
    prepare,
)
from overlapmamba.service.sensors import FieldOfView
from overlapmamba.service.settings import VerifySettings
from overlapmamba.service.threads import request_deadline
from overlapmamba.service.verify import Verdict, params_of, verify_candidates

log = logging.getLogger(__name__)

STOP_WAIT_S = 5.0  # a child's call under way at shutdown: then it is killed
HELD = 32  # prepared queries a child keeps (≈ 0.4 MB each); one it dropped is prepared again
Candidates = list[tuple[bytes | None, float | None, float]]


@dataclass(frozen=True)
class Held:
    """The query's side of registration, wherever it is kept."""

    size: int  # its voxel grid's points
    reason: str | None  # why it cannot be registered, when it cannot
    local: Prepared | None = None  # kept in this process (``processes`` 0)
    xyz: np.ndarray | None = None  # the thinned points: a child that lost it prepares again
    key: int = -1  # its key in a child
    child: int = -1  # which child
    failed: bool = False  # the child died twice preparing it: the reason says how

    @property
    def unregistrable(self) -> Prepared:
        """What ``verify_candidates`` refuses every candidate of, with the reason."""
        return Prepared(None, self.size, self.reason or "the query could not be prepared")


class Registrar:
    """Prepare, pack and register, in this process (``processes`` 0) or in ``processes``
    children, a query kept by the child that prepared it (the next child in turn). The
    methods block: they run in the service's worker threads (:func:`threads.in_thread`)."""

    def __init__(self, processes: int = 0, stale_s: float | None = None) -> None:
        if processes < 0:
            raise ValueError(f"verify.processes must be 0 or more, got {processes}")
        if stale_s is not None and stale_s <= 0:
            raise ValueError(f"stale_s must be above 0 s, got {stale_s}")
        self.processes = processes
        self.stale_s = stale_s  # a call queued longer in its child is skipped there
        self.stale = 0  # calls skipped so far
        self._children: list[ProcessPoolExecutor | None] = [None] * processes
        self._lock = threading.Lock()  # starting and restarting children
        self._keys = itertools.count()
        self._turn = itertools.count()
        self.restarts = 0
        self._stopped = False
        self._cpu_seen: dict[int, float] = {}  # each child's CPU seconds at the last usage()
        self._cpu_gone = 0.0  # the last seen of children no longer running

    @property
    def where(self) -> str:
        if not self.processes:
            return "the server's own threads (verify.processes 0)"
        return f"{self.processes} child process{'es' if self.processes > 1 else ''}"

    def __repr__(self) -> str:
        return f"Registrar({self.where})"

    def start(self) -> None:
        """Start the children now (each imports small_gicp, ≈ 0.5 s, in the background)."""
        for i in range(self.processes):
            self._child(i).submit(_ping)

    def stop(self, wait_s: float = STOP_WAIT_S) -> None:
        """Stop the children: the calls queued are cancelled, and one under way has
        ``wait_s`` to finish; a child still busy then (a registration stuck) is killed, so
        that the service's shutdown goes on to close its maps. No child starts after."""
        with self._lock:
            self._stopped = True
            children, self._children = self._children, [None] * self.processes
        procs = []
        for ex in children:
            if ex is not None:
                procs += list((getattr(ex, "_processes", None) or {}).values())
                ex.shutdown(wait=False, cancel_futures=True)
        deadline = time.monotonic() + wait_s
        for proc in procs:
            proc.join(max(0.0, deadline - time.monotonic()))
            if proc.is_alive():
                log.error(
                    "registration process %d still busy %g s after the stop: killing it",
                    proc.pid,
                    wait_s,
                )
                proc.kill()
                proc.join(5)

    # ---- the three operations ----------------------------------------------------------------

    def prepare(self, xyz: np.ndarray, p: RegistrationParams) -> Held:
        if not self.processes:
            q = prepare(xyz, p)
            return Held(q.size, q.reason, local=q)
        # the child prepares every point it is sent: the same grid as ``prepare(xyz, p)``
        thin = np.ascontiguousarray(xyz[:: max(1, p.stride), :3])
        held = Held(
            0, None, xyz=thin, key=next(self._keys), child=next(self._turn) % self.processes
        )
        try:
            size, reason = self._call(held, _prepare, p, send=True)
        except _Stale as err:
            return replace(held, reason=str(err), failed=True)
        except _Failed as err:
            return replace(held, reason=f"the registration process failed: {err}", failed=True)
        return replace(held, size=size, reason=reason)

    def geometry(self, held: Held, p: RegistrationParams) -> bytes | None:
        """The keyframe's blob; raises :class:`Unavailable` (503, retry) when the
        registration process fails twice: a keyframe is not stored without its geometry."""
        if held.failed:
            raise self._unavailable(held.reason)
        if held.local is not None or held.xyz is None or held.reason is not None:
            return keyframe_geometry(held.local or held.unregistrable, p)
        try:
            return self._call(held, _geometry, p)
        except _Stale as err:
            raise self._unavailable(str(err)) from err
        except _Failed as err:
            raise self._unavailable(f"it failed twice packing the geometry: {err}") from err

    @staticmethod
    def _unavailable(why: str | None) -> Unavailable:
        return Unavailable(
            f"the keyframe's geometry could not be made ({why}); nothing was stored: retry",
            code="registration_failed",
        )

    def verify(
        self,
        held: Held,
        candidates: Candidates,
        v: VerifySettings,
        views: list[FieldOfView | None] | None = None,
    ) -> list[Verdict]:
        if held.local is not None:
            return verify_candidates(held.local, candidates, v, views)
        if held.xyz is None or held.reason is not None:
            return verify_candidates(held.unregistrable, candidates, v, views)
        try:
            return self._call(held, _verify, params_of(v), candidates, v, views)
        except _Stale as err:
            return verify_candidates(Prepared(None, held.size, str(err)), candidates, v, views)
        except _Failed as err:
            q = Prepared(None, held.size, f"the registration process failed twice: {err}")
            return verify_candidates(q, candidates, v, views)

    # ---- children ----------------------------------------------------------------------------

    def usage(self) -> dict[str, float]:
        """The children's count, restarts, and (Linux) their resident memory and CPU time
        together, from ``/proc``: what the server's own process series leave out."""
        out: dict[str, float] = {
            "processes": self.processes,
            "restarts": self.restarts,
            "stale": self.stale,
        }
        if not Path("/proc/self/stat").exists():
            return out
        rss = 0.0
        alive: dict[int, float] = {}
        for pid in self.pids():
            try:
                status = Path(f"/proc/{pid}/status").read_text()
                stat = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            except OSError:  # exited meanwhile
                continue
            kb = next((ln.split()[1] for ln in status.splitlines() if ln.startswith("VmRSS:")), 0)
            rss += float(kb) * 1024
            alive[pid] = (int(stat[11]) + int(stat[12])) / os.sysconf("SC_CLK_TCK")
        with self._lock:  # a child gone keeps the CPU last seen of it: the counter never falls
            for pid, seconds in self._cpu_seen.items():
                if pid not in alive:
                    self._cpu_gone += seconds
                else:  # two scrapes at once: the later-read one may be stored first
                    alive[pid] = max(alive[pid], seconds)
            self._cpu_seen = alive
            cpu = self._cpu_gone + sum(alive.values())
        return out | {"resident_bytes": rss, "cpu_seconds": cpu}

    def pids(self) -> list[int]:
        """The children's process ids (those started)."""
        with self._lock:
            children = [ex for ex in self._children if ex is not None]
        return [pid for ex in children for pid in getattr(ex, "_processes", None) or {}]

    def _child(self, i: int) -> ProcessPoolExecutor:
        with self._lock:
            if self._stopped:  # a call under way at the stop: it fails, nothing restarts
                raise _Failed("the registration processes were stopped (the service stops)")
            ex = self._children[i]
            if ex is None:
                ex = self._children[i] = self._new_child()
            return ex

    @staticmethod
    def _new_child() -> ProcessPoolExecutor:
        return ProcessPoolExecutor(
            max_workers=1,
            mp_context=multiprocessing.get_context("spawn"),  # never fork a threaded server
            initializer=_child_init,
            initargs=(os.getpid(),),
        )

    def _restart(self, i: int, dead: ProcessPoolExecutor) -> None:
        with self._lock:
            if self._children[i] is dead:  # another thread may have restarted it already
                self._children[i] = None
                self.restarts += 1
                log.warning("registration process %d died; starting it again", i)
        dead.shutdown(wait=False, cancel_futures=True)

    def _call(
        self,
        held: Held,
        fn: Callable[..., Any],
        p: RegistrationParams,
        *args: Any,
        send: bool = False,
    ) -> Any:
        """``fn`` in the query's child. The query's points go along when ``send`` or when
        the child no longer holds the query (it answers :class:`_Missing`); a child that
        died is started again and asked once more, and :class:`_Failed` says it died twice."""
        died: list[str] = []
        xyz = held.xyz if send else None
        # stale once its request has been answered: at the request's own deadline where it
        # has one (an HTTP request; it may have spent most of its time before this call),
        # else ``stale_s`` from now (a stream's frame)
        expires = None if self.stale_s is None else time.monotonic() + self.stale_s
        deadline = request_deadline.get()
        if expires is not None and deadline is not None:
            expires = min(expires, deadline)
        while True:
            ex = self._child(held.child)
            try:
                out = self._answer(ex, held.child, _timely, expires, fn, held.key, xyz, p, *args)
            except BrokenProcessPool as err:
                died.append(str(err) or type(err).__name__)
                self._restart(held.child, ex)
                if len(died) == 2:
                    raise _Failed("; ".join(died)) from err
                xyz = held.xyz
                continue
            if isinstance(out, _Late):
                with self._lock:
                    self.stale += 1
                raise _Stale(
                    "the registration process had not started it by the request's deadline "
                    f"(its timeout, {self.stale_s:g} s): skipped"
                )
            if not isinstance(out, _Missing):
                return out
            assert xyz is None, "a child prepares the points it is sent"
            xyz = held.xyz

    def _answer(self, ex: ProcessPoolExecutor, i: int, *call: Any) -> Any:
        """``call`` in child ``i``; one that answers nothing in twice ``stale_s`` hangs: it
        is killed, and the call raises BrokenProcessPool like any call to a dead child."""
        fut = ex.submit(*call)
        if self.stale_s is None:
            return fut.result()
        try:
            return fut.result(timeout=2 * self.stale_s)
        except TimeoutError:
            log.error(
                "registration process %d answered nothing in %g s: killing it", i, 2 * self.stale_s
            )
            for pid in getattr(ex, "_processes", None) or {}:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
        try:
            return fut.result(timeout=10)  # the pool sees its child dead: BrokenProcessPool
        except TimeoutError:
            raise _Failed(f"it hung for {2 * self.stale_s:g} s and did not die") from None


class _Failed(Exception):
    """The registration process died twice on one call."""


class _Stale(Exception):
    """The call waited in its child's queue past ``stale_s``: skipped (the message says so)."""


# ---- in the child ------------------------------------------------------------------------------


class _Missing:
    """The child no longer holds the query: send its points."""


class _Late:
    """The call came off the child's queue after it expired: not done."""


def _timely(expires: float | None, fn: Callable[..., Any], *args: Any) -> Any:
    # CLOCK_MONOTONIC is one clock for every process of the machine (Linux, macOS)
    if expires is not None and time.monotonic() > expires:
        return _Late()
    return fn(*args)


_HELD: OrderedDict[int, Prepared] = OrderedDict()


def _child_init(server: int) -> None:
    # Ctrl-C reaches the whole process group: the server drains, its child must not die
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # a server that is killed (SIGKILL, the OOM killer) cannot stop its child: the child
    # leaves as soon as its parent is another process (PR_SET_PDEATHSIG would fire when the
    # thread that started it ends, and threads come and go in a server)
    threading.Thread(target=_orphaned, args=(server,), daemon=True, name="parent").start()
    _fixed_mmap_threshold()


def _fixed_mmap_threshold() -> None:
    """glibc raises its mmap threshold each time a large block is freed, after which each
    query's points (≈ 0.4 MB, unpickled) come from the heap, which fragments: a child grew
    by about 75 kB a query without end. A fixed threshold (128 KiB, glibc's initial one)
    keeps it flat (≈ 80 MB over 800 KITTI queries). Elsewhere than glibc: nothing to do."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 128 * 1024)  # M_MMAP_THRESHOLD
    except (OSError, AttributeError):
        pass


def _orphaned(server: int) -> None:
    while os.getppid() == server:
        time.sleep(0.5)
    os._exit(0)


def _ping() -> bool:
    return True


def _held(key: int, xyz: np.ndarray | None, p: RegistrationParams) -> Prepared | None:
    q = _HELD.get(key)
    if q is not None:
        _HELD.move_to_end(key)
        return q
    if xyz is None:
        return None
    q = prepare(xyz, replace(p, stride=1))  # the points came thinned
    _HELD[key] = q
    while len(_HELD) > HELD:
        _HELD.popitem(last=False)
    return q


def _prepare(key: int, xyz: np.ndarray | None, p: RegistrationParams) -> Any:
    q = _held(key, xyz, p)
    return _Missing() if q is None else (q.size, q.reason)


def _geometry(key: int, xyz: np.ndarray | None, p: RegistrationParams) -> Any:
    q = _held(key, xyz, p)
    return _Missing() if q is None else keyframe_geometry(q, p)


def _verify(
    key: int,
    xyz: np.ndarray | None,
    p: RegistrationParams,
    candidates: Candidates,
    v: VerifySettings,
    views: list[FieldOfView | None] | None,
) -> Any:
    q = _held(key, xyz, p)
    if q is None:
        return _Missing()
    try:
        return verify_candidates(q, candidates, v, views)
    finally:
        q.spectra.clear()  # its turned seeds serve this call's registrations only
