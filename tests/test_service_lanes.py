"""Encoder lanes (overlapmamba.service.batcher) and the threads the service's encoder and
registration run on (overlapmamba.service.threads, verify.threads)."""

from __future__ import annotations

import asyncio
import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from overlapmamba.service.batcher import MicroBatcher
from overlapmamba.service.errors import Unavailable
from overlapmamba.service.settings import Settings, VerifySettings
from overlapmamba.service.verify import params_of


def _encode(images: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    time.sleep(0.01)
    b = images.shape[0]
    return images.reshape(b, -1)[:, :4].copy(), images[:, 0, :2].copy()


def test_batcher_lanes_encode_at_once():
    """Two lanes run two encoder calls at the same time (each waits for the other at a
    barrier); one lane runs them one after the other, and the barrier breaks."""

    def run(lanes: int) -> list[BaseException | tuple[np.ndarray, np.ndarray]]:
        barrier = threading.Barrier(2, timeout=1.0)

        def meet(images: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            barrier.wait()
            return _encode(images, offsets)

        async def main() -> list[BaseException | tuple[np.ndarray, np.ndarray]]:
            mb = MicroBatcher(meet, max_batch=1, max_wait_ms=0, lanes=lanes)
            await mb.start()
            images = [np.full((1, 2, 3), i, np.float32) for i in range(2)]
            got = await asyncio.gather(*(mb.encode(x) for x in images), return_exceptions=True)
            await mb.stop()
            return got

        return asyncio.run(main())

    both = run(2)
    assert [int(r[0][0]) for r in both if isinstance(r, tuple)] == [0, 1], both
    alone = run(1)
    assert any(isinstance(r, threading.BrokenBarrierError) for r in alone), alone
    with pytest.raises(ValueError, match="lanes"):
        MicroBatcher(_encode, lanes=0)


def test_stopping_the_batcher_answers_every_lanes_batch():
    """At shutdown each lane's batch under way is answered Unavailable, as one lane's is."""
    release = threading.Event()

    def slow(images: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        release.wait(5)
        return _encode(images, offsets)

    async def main() -> list[BaseException | tuple[np.ndarray, np.ndarray]]:
        mb = MicroBatcher(slow, max_batch=1, max_wait_ms=1, lanes=2)
        await mb.start()
        image = np.zeros((1, 2, 3), np.float32)
        calls = [asyncio.create_task(mb.encode(image, timeout_s=30)) for _ in range(3)]
        await asyncio.sleep(0.1)  # a batch under way in each lane, one scan queued
        stopping = asyncio.create_task(mb.stop())
        await asyncio.sleep(0.1)
        release.set()
        await asyncio.wait_for(stopping, 10)
        return await asyncio.wait_for(asyncio.gather(*calls, return_exceptions=True), 5)

    answers = asyncio.run(main())
    assert all(isinstance(a, Unavailable) for a in answers), answers


def test_scans_whose_requests_gave_up_are_not_waiting_and_a_stuck_lane_is_named():
    """An encoder call that never returns: every scan behind it times out. Those scans still
    counted as waiting (``overlapmamba_encoder_queue``) with no request left to answer, and
    nothing named the lane; they no longer count, are skipped once a lane is free, and
    ``stuck`` names the lane and for how long."""
    release = threading.Event()
    calls: list[int] = []

    def wedged(images: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        calls.append(images.shape[0])
        release.wait(10)
        return _encode(images, offsets)

    async def main() -> None:
        mb = MicroBatcher(wedged, max_batch=4, max_wait_ms=0, lanes=1)
        await mb.start()
        image = np.zeros((1, 2, 3), np.float32)
        first = asyncio.create_task(mb.encode(image, timeout_s=30))
        await asyncio.sleep(0.1)  # the lane is in its call
        gave_up = await asyncio.gather(
            *(mb.encode(image, timeout_s=0.2) for _ in range(3)), return_exceptions=True
        )
        assert all(type(g).__name__ == "Timeout" for g in gave_up), gave_up
        assert mb.pending == 0  # three on the queue, none waited for
        assert mb.stuck(0.1) and mb.stuck(0.1)[0][0] == 0 and not mb.stuck(30)
        waiting = asyncio.create_task(mb.encode(image, timeout_s=30))
        await asyncio.sleep(0.05)
        assert mb.pending == 1
        release.set()
        await asyncio.wait_for(asyncio.gather(first, waiting), 10)
        assert calls == [1, 1]  # the three abandoned scans were never encoded
        assert mb.pending == 0 and not mb.stuck(0)
        await mb.stop()

    asyncio.run(main())


def test_the_count_of_scans_waiting_stays_true_under_timeouts_that_race_the_lanes():
    """A request that gives up has its future cancelled at once, and its own count of an
    abandoned scan a turn later: a lane taking the scan in between took one off the count
    that had not been put on it, and the queue read as holding scans it did not. After a
    storm of requests timing out against four lanes, nothing waits and the count is 0."""
    import random

    from overlapmamba.service.errors import Timeout

    def fast(images: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        time.sleep(0.001)
        return np.zeros((len(images), 4)), np.zeros((len(images), 2, 3))

    async def main(seed: int) -> tuple[int, int, int]:
        rng = random.Random(seed)
        mb = MicroBatcher(fast, max_batch=2, max_wait_ms=0, queue_size=100_000, lanes=4)
        await mb.start()

        async def one() -> bool:
            await asyncio.sleep(rng.random() * 0.3)
            try:
                await mb.encode(np.zeros((1, 2, 2), np.float32), timeout_s=rng.random() * 0.02)
                return True
            except Timeout:
                return False

        done = await asyncio.gather(*(one() for _ in range(2000)))
        await asyncio.sleep(0.3)
        got = (mb.pending, mb._abandoned, sum(not d for d in done))
        await mb.stop()
        return got

    for seed in (2, 3):
        pending, abandoned, timed_out = asyncio.run(main(seed))
        assert timed_out > 0 and (pending, abandoned) == (0, 0), (seed, pending, abandoned)


def test_encoder_lanes_and_threads_share_the_cores(monkeypatch: pytest.MonkeyPatch):
    from overlapmamba.service import threads

    monkeypatch.setattr(threads, "cores", lambda: 4)
    assert threads.encoder_threads(0, 0) == (4, 1)  # the default: a lane a core, one thread
    assert threads.encoder_threads(1, 0) == (1, 4)  # one lane: every core in its calls
    assert threads.encoder_threads(2, 0) == (2, 2)
    assert threads.encoder_threads(8, 0) == (8, 1)  # more lanes than cores: still a thread
    assert threads.encoder_threads(0, 3) == (4, 3)  # threads given: as given
    monkeypatch.undo()
    assert threads.cores() >= 1
    with pytest.raises(ValueError):
        Settings(batching={"lanes": -1})


def test_the_cores_a_container_may_use_count_its_cpu_quota(tmp_path: Path):
    """``docker run --cpus 2`` on a 64-core host caps CPU time but leaves the affinity whole:
    the service started 64 encoder lanes (≈ 235 MB each) and was throttled or killed. The
    cgroup's quota bounds the count (v2's cpu.max, the tightest up the tree; v1's cfs)."""
    from overlapmamba.service import threads

    v2 = tmp_path / "v2"
    (v2 / "kubepods" / "pod1").mkdir(parents=True)
    (v2 / "cpu.max").write_text("max 100000\n")
    (v2 / "kubepods" / "cpu.max").write_text("150000 100000\n")  # the tighter, above
    (v2 / "kubepods" / "pod1" / "cpu.max").write_text("400000 100000\n")
    assert threads.cpu_quota(v2, "/kubepods/pod1") == 1.5
    assert threads.cpu_quota(v2, "/") is None  # the root: no limit
    v1 = tmp_path / "v1"
    (v1 / "cpu").mkdir(parents=True)
    (v1 / "cpu" / "cpu.cfs_quota_us").write_text("50000\n")
    (v1 / "cpu" / "cpu.cfs_period_us").write_text("100000\n")
    assert threads.cpu_quota(v1, "/") == 0.5
    (v1 / "cpu" / "cpu.cfs_quota_us").write_text("-1\n")
    assert threads.cpu_quota(v1, "/") is None
    assert threads.cpu_quota(tmp_path / "none", "/") is None
    real = threads.cpu_quota
    have = len(os.sched_getaffinity(0))
    try:
        for quota, want in ((1.0, 1), (0.25, 1), (512.0, have)):  # a share of a core: one
            threads.cpu_quota = lambda cgroup=None, own=None, q=quota: q  # type: ignore[assignment,misc]
            assert threads.cores() == want, quota
    finally:
        threads.cpu_quota = real  # type: ignore[assignment]


def test_registration_threads_come_from_the_settings():
    assert params_of(VerifySettings()).threads == 1  # under load the other cores encode
    assert params_of(VerifySettings(threads=2)).threads == 2
    with pytest.raises(ValueError):
        Settings(verify={"threads": 0})


def test_a_real_server_with_two_lanes_answers_each_scan_its_own_descriptor(tmp_path: Path):
    """Scans posted at once to a real server encoding in two lanes, one onnxruntime thread
    each, get the descriptors the model gives each scan alone; /readyz says how it encodes."""
    import concurrent.futures

    import httpx
    from service_kit import MODEL, OCTET, scan, server

    from overlapmamba.core.points import PointCloud
    from overlapmamba.service.encoder import Encoder

    scans = [scan(seed) for seed in range(8)]
    alone = Encoder(MODEL, intra_op_threads=1)
    want = [alone.encode(alone.project(PointCloud(s[:, :3], s[:, 3]))[None])[0][0] for s in scans]
    env = {"OVERLAPMAMBA_BATCHING__LANES": "2", "OVERLAPMAMBA_BATCHING__INTRA_OP_THREADS": "1"}
    with server(tmp_path / "data", env) as (url, _):
        ready = httpx.get(f"{url}/readyz", timeout=30).json()["detail"]
        assert (ready["lanes"], ready["threads_per_lane"]) == (2, 1)

        def post(s: np.ndarray) -> np.ndarray:
            r = httpx.post(f"{url}/v1/descriptors", content=s.tobytes(), headers=OCTET, timeout=60)
            assert r.status_code == 200, r.text
            return np.array(r.json()["descriptor"], np.float32)

        with concurrent.futures.ThreadPoolExecutor(8) as pool:
            got = list(pool.map(post, scans * 2))  # each scan twice, all at once
    for i, d in enumerate(got):
        assert float(d @ want[i % len(scans)]) > 0.9999, i
