"""verify.processes: registration in child processes answers exactly as in the server's own
threads; a child that lost a query prepares it again; a child that dies is started again; one
that dies twice refuses the query's candidates with the reason and answers a keyframe's
geometry with 503; the setting over HTTP and /readyz (overlapmamba.service.registrar)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from concurrent.futures import Future
from concurrent.futures.process import BrokenProcessPool
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError
from service_kit import OCTET, running, scan

from overlapmamba.service.errors import Unavailable
from overlapmamba.service.registrar import Registrar, _ping
from overlapmamba.service.settings import Settings, VerifySettings
from overlapmamba.service.verify import params_of

V = VerifySettings(ambiguity_margin=0.3, stop_at_first=False)
P = params_of(V)


@pytest.fixture(scope="module")
def scans() -> list[np.ndarray]:
    # one place: the query, two keyframes of it (turned: the seed yaw is the opposite turn),
    # one of another place
    return [scan(1)[:, :3], scan(1, 30.0)[:, :3], scan(1, -60.0)[:, :3], scan(7)[:, :3]]


@pytest.fixture(scope="module")
def child():
    r = Registrar(1)
    r.start()
    yield r
    r.stop()


def answers(r: Registrar, scans: list[np.ndarray]) -> tuple[list[bytes | None], list]:
    blobs = [r.geometry(r.prepare(s, P), P) for s in scans[1:]]
    cands = [(b, yaw, 0.1) for b, yaw in zip(blobs, (-30.0, 60.0, 0.0), strict=True)]
    return blobs, r.verify(r.prepare(scans[0], P), cands, V)


def test_a_child_answers_as_the_server_threads_do(child, scans):
    local_blobs, local = answers(Registrar(0), scans)
    blobs, remote = answers(child, scans)
    assert blobs == local_blobs  # the same keyframe geometry, byte for byte
    assert [v.verified for v in local][:2] == [True, True]  # the place, turned
    assert local[2].verified is False  # another place
    for a, b in zip(local, remote, strict=True):
        assert (a.verified, a.fitness, a.rmse, a.reason) == (
            b.verified,
            b.fitness,
            b.rmse,
            b.reason,
        )
        assert a.rival_fitness == b.rival_fitness
        assert (a.relative_pose is None) == (b.relative_pose is None)
        if a.relative_pose is not None:
            np.testing.assert_array_equal(a.relative_pose, b.relative_pose)
    assert child.pids() and os.getpid() not in child.pids()


def test_a_query_the_child_no_longer_holds_is_prepared_again(child, scans):
    _, local = answers(Registrar(0), scans)
    blob = child.geometry(child.prepare(scans[1], P), P)
    held = child.prepare(scans[0], P)
    lost = replace(held, key=-1)  # a key the child never held: evicted, or the child restarted
    (v,) = child.verify(lost, [(blob, -30.0, 0.1)], V)
    assert (v.verified, v.fitness) == (local[0].verified, local[0].fitness)


def test_a_sparse_query_is_refused_without_the_child(child):
    held = child.prepare(np.zeros((10, 3), np.float32), P)
    assert held.size < P.min_points and "registration needs at least" in held.reason
    (v,) = child.verify(held, [(b"x", 0.0, 0.1)], V)
    assert v.verified is False and v.reason == held.reason
    assert child.geometry(held, P) is None


def test_a_killed_child_is_started_again(scans):
    r = Registrar(1)
    try:
        blob = r.geometry(r.prepare(scans[1], P), P)
        held = r.prepare(scans[0], P)
        (before,) = r.verify(held, [(blob, -30.0, 0.1)], V)
        (pid,) = r.pids()
        os.kill(pid, signal.SIGKILL)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:  # reaped: the pool knows it is broken
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                break
            time.sleep(0.05)
        (after,) = r.verify(held, [(blob, -30.0, 0.1)], V)  # prepared again in the new child
        assert (after.verified, after.fitness) == (before.verified, before.fitness)
        assert r.restarts == 1 and r.pids() and r.pids() != [pid]
    finally:
        r.stop()


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="CPU time from /proc")
def test_the_childrens_cpu_counter_never_goes_down_when_one_is_replaced():
    """``cpu_seconds`` (``overlapmamba_registration_cpu_seconds_total``, a counter) summed
    the children alive: one that died took its CPU with it and the counter fell, which
    Prometheus reads as a reset (``increase()`` then counts the survivors' whole lives
    again). The dead children's last CPU seen stays in the sum."""
    r = Registrar(2)
    try:
        for i in (0, 1):
            r._child(i).submit(sum, range(20_000_000)).result(timeout=60)  # CPU in each
        before = r.usage()["cpu_seconds"]
        pid = r.pids()[0]
        os.kill(pid, signal.SIGKILL)
        ex = r._children[0]
        with pytest.raises(BrokenProcessPool):
            ex.submit(_ping).result(timeout=30)  # type: ignore[union-attr]
        r._restart(0, ex)  # type: ignore[arg-type]
        r._child(0).submit(_ping).result(timeout=60)
        after = r.usage()["cpu_seconds"]
        assert pid not in r.pids() and after >= before > 0.1, (before, after)
    finally:
        r.stop()


def test_a_killed_server_leaves_no_child_behind():
    """SIGKILL gives the server no chance to stop its child: the child leaves by itself."""
    code = (
        "import time\n"
        "from overlapmamba.service.registrar import Registrar\n"
        "if __name__ == '__main__':\n"
        "    r = Registrar(1)\n"
        "    r.start()\n"
        "    while not r.pids():\n"
        "        time.sleep(0.05)\n"
        "    print(r.pids()[0], flush=True)\n"
        "    time.sleep(120)\n"
    )
    with subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True) as srv:
        assert srv.stdout is not None
        child = int(srv.stdout.readline())
        os.kill(srv.pid, signal.SIGKILL)
        srv.wait(timeout=10)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and _alive(child):
        time.sleep(0.1)
    assert not _alive(child), f"registration process {child} outlived its server"


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state != "Z"  # a zombie has exited (its parent, init, reaps it)


class _Dying:
    """A child that is dead whenever it is asked (each call's pool breaks)."""

    def submit(self, *args: object, **kwargs: object) -> Future:
        f: Future = Future()
        f.set_exception(BrokenProcessPool("the child was killed"))
        return f

    def shutdown(self, wait: bool = True, cancel_futures: bool = False) -> None:
        pass


class _AlwaysDying(Registrar):
    @staticmethod
    def _new_child():  # type: ignore[override]
        return _Dying()


def test_a_child_that_dies_twice_refuses_and_never_stores_without_geometry(scans):
    r = _AlwaysDying(1)
    held = r.prepare(scans[0], P)  # it could not be prepared: the reason says why
    assert held.reason and "registration process failed" in held.reason
    (v,) = r.verify(held, [(b"x", 0.0, 0.1)], V)
    assert v.verified is False and "registration process failed" in v.reason
    with pytest.raises(Unavailable, match="nothing was stored") as err:
        r.geometry(held, P)  # a keyframe is never stored without its geometry
    assert err.value.status == 503 and err.value.code == "registration_failed"
    assert err.value.headers["Retry-After"] == "1"  # every 503 says when to come back
    prepared = replace(held, reason=None, size=1000, failed=False)  # then the child died twice
    with pytest.raises(Unavailable, match="failed twice") as err:
        r.geometry(prepared, P)
    assert err.value.status == 503
    (v,) = r.verify(prepared, [(b"x", 0.0, 0.1)], V)
    assert v.verified is False and "failed twice" in v.reason and "killed" in v.reason
    assert r.restarts == 6  # each call that reached a child: died, started again, died again


def _warm(r: Registrar) -> None:
    """Start child 0 and wait until it answers: a cold start (spawn, imports) on a loaded
    machine can take longer than the short ``stale_s`` these tests use, which would make
    the first call stale for a reason the test is not about."""
    assert r._child(0).submit(_ping).result(timeout=60) is True


def test_a_call_queued_past_the_request_timeout_is_skipped_in_the_child(scans):
    """A call that waited in its child's queue longer than ``stale_s`` belongs to a request
    answered already (504): the child skips it, its candidates are refused with the reason,
    a keyframe's geometry answers 503; the calls after it are served as before."""
    r = Registrar(1, stale_s=1.0)  # a call waiting 2 s: the child hangs
    try:
        _warm(r)
        blob = r.geometry(r.prepare(scans[1], P), P)
        held = r.prepare(scans[0], P)
        busy = r._child(0).submit(time.sleep, 1.4)  # busy with a long call, not hung
        (v,) = r.verify(held, [(blob, -30.0, 0.1)], V)
        assert v.verified is False and "had not started it by the request's deadline" in v.reason
        busy.result()
        r._child(0).submit(time.sleep, 1.4)
        with pytest.raises(Unavailable, match="had not started it") as err:
            r.geometry(held, P)
        assert err.value.status == 503
        (v,) = r.verify(held, [(blob, -30.0, 0.1)], V)  # nothing queued ahead of it now
        assert v.verified is True
        assert r.usage()["stale"] == 2 and r.restarts == 0
    finally:
        r.stop()
    with pytest.raises(ValueError, match="stale_s"):
        Registrar(1, stale_s=0)


def test_a_call_is_stale_at_its_requests_deadline_not_a_timeout_after_it_was_queued(scans):
    """A query that spent most of its timeout waiting for the encoder queued its call near
    its deadline: counted fresh for a whole timeout from there, the call ran in the child
    after the client had its 504, delaying the calls behind it. The request's deadline (the
    guard's, carried in its context) bounds it."""
    from overlapmamba.service.threads import request_deadline

    r = Registrar(1, stale_s=30.0)
    try:
        _warm(r)
        blob = r.geometry(r.prepare(scans[1], P), P)
        held = r.prepare(scans[0], P)
        r._child(0).submit(time.sleep, 1.0)  # busy past the request's deadline
        token = request_deadline.set(time.monotonic() + 0.3)
        try:
            (v,) = r.verify(held, [(blob, -30.0, 0.1)], V)
        finally:
            request_deadline.reset(token)
        assert v.verified is False and "request's deadline" in v.reason, v.reason
        assert r.usage()["stale"] == 1
        (v,) = r.verify(held, [(blob, -30.0, 0.1)], V)  # no deadline: stale_s from now
        assert v.verified is True
    finally:
        r.stop()


def test_a_child_that_hangs_is_killed_and_started_again(scans):
    """A call that answers nothing in twice ``stale_s`` (here the child sleeps in a call
    ahead of it, as a hung one would): the child is killed and started again, the waiting
    call is refused with the reason, and the next one is served by the new child. The
    retried call waits 2 ``stale_s`` plus the new child's cold start (≈ 0.7 s here), which
    must stay under the 2 ``stale_s`` that would judge the new child hung as well."""
    r = Registrar(1, stale_s=1.5)
    try:
        _warm(r)
        blob = r.geometry(r.prepare(scans[1], P), P)
        held = r.prepare(scans[0], P)
        (pid,) = r.pids()
        r._child(0).submit(time.sleep, 60)  # hangs
        t0 = time.monotonic()
        (v,) = r.verify(held, [(blob, -30.0, 0.1)], V)
        assert time.monotonic() - t0 < 10
        assert v.verified is False and "had not started it" in v.reason  # stale when retried
        assert r.restarts == 1 and pid not in r.pids()
        _warm(r)
        (v,) = r.verify(held, [(blob, -30.0, 0.1)], V)  # prepared again in the new child
        assert v.verified is True
    finally:
        r.stop()


def test_a_child_stuck_at_shutdown_is_killed_so_the_shutdown_goes_on():
    """The stop waited without bound on a child busy in a call: a registration stuck at
    SIGTERM kept the service from ever closing (and snapshotting) its maps, until the
    orchestrator killed it. The call under way gets a few seconds, then the child is
    killed; an idle child stops at once."""
    r = Registrar(1, stale_s=30.0)
    r._child(0).submit(_ping).result(timeout=60)
    (pid,) = r.pids()
    r._child(0).submit(time.sleep, 60)  # stuck
    time.sleep(0.3)
    t0 = time.monotonic()
    r.stop(wait_s=1.0)
    assert time.monotonic() - t0 < 8
    assert not Path(f"/proc/{pid}").exists() or "zombie" in Path(f"/proc/{pid}/status").read_text()
    idle = Registrar(1)
    idle._child(0).submit(_ping).result(timeout=60)
    t0 = time.monotonic()
    idle.stop(wait_s=30.0)
    assert time.monotonic() - t0 < 5 and not idle.pids()


def test_a_call_under_way_at_the_stop_fails_and_starts_no_child(scans):
    """The stop killed a stuck child; the call that ran on it then started a new child that
    nothing would stop, and ran again there, holding the process's exit. After the stop the
    call fails and no child starts."""
    import threading

    r = Registrar(1, stale_s=30.0)
    _warm(r)
    held = r.prepare(scans[0], P)
    blob = r.geometry(r.prepare(scans[1], P), P)
    r._child(0).submit(time.sleep, 60)  # stuck ahead of the call
    got: dict[str, object] = {}
    call = threading.Thread(target=lambda: got.update(v=r.verify(held, [(blob, -30.0, 0.1)], V)))
    call.start()
    time.sleep(0.3)
    r.stop(wait_s=0.5)
    call.join(20)
    (v,) = got["v"]  # type: ignore[misc]
    assert v.verified is False and "stopped" in v.reason
    assert r.pids() == [] and r._children == [None]
    with pytest.raises(Unavailable, match="stopped"):
        r.geometry(held, P)


def test_processes_must_not_be_negative():
    with pytest.raises(ValidationError, match="processes"):
        VerifySettings(processes=-1)
    with pytest.raises(ValueError, match="0 or more"):
        Registrar(-1)


@pytest.mark.anyio
@pytest.mark.parametrize("processes", [0, 2])
async def test_http_verifies_alike_in_threads_and_in_children(tmp_path, encoder, processes):
    """The same keyframe and query over HTTP: verified alike with registration in the
    server's threads and in two children; /readyz says where it runs."""
    settings = Settings(data_dir=tmp_path / "data", verify={"processes": processes})
    async with running(settings, encoder) as c:
        ready = (await c.get("/readyz")).json()["detail"]
        assert (ready["registration_processes"], ready["registration_restarts"]) == (processes, 0)
        assert (await c.put("/v1/maps/m")).status_code == 201
        params = {"keyframe_id": "k0", "timestamp": 1.0, "robot_id": "r1", "session_id": "s1"}
        body = scan(3).tobytes()
        r = await c.post("/v1/maps/m/keyframes", params=params, content=body, headers=OCTET)
        assert r.status_code == 201, r.text
        q = await c.post("/v1/maps/m/query", content=body, headers=OCTET)
        assert q.status_code == 200, q.text
        v, lc = q.json()["matches"][0]["verification"], q.json()["loop_closure"]
        assert v["verified"] is True and v["fitness"] > 0.9, v
        assert lc["verified"] is True and lc["keyframe_id"] == "k0"
        # /metrics counts the children's memory and CPU, which the process's series leave out
        text = (await c.get("/metrics")).text
        assert f"overlapmamba_registration_processes {float(processes)}" in text
        assert "overlapmamba_registration_restarts_total 0.0" in text
        assert "overlapmamba_registration_stale_total 0.0" in text
        rss = re.search(r"^overlapmamba_registration_resident_bytes (\S+)$", text, re.M)
        cpu = re.search(r"^overlapmamba_registration_cpu_seconds_total (\S+)$", text, re.M)
        assert rss and cpu
        if processes:  # two children, each holding numpy and small_gicp, that did the work
            assert float(rss[1]) > processes * 20e6 and float(cpu[1]) > 0
        else:
            assert float(rss[1]) == 0 and float(cpu[1]) == 0
        return v
