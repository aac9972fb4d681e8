"""Dynamic micro-batching of encoder calls, as Triton's dynamic batcher does.

Requests put one range image each on a bounded queue and await a future. A worker takes
the first waiting image and everything queued behind it, up to ``max_batch``; it waits (at
most ``max_wait_ms``) for more only while scans are on their way — announced by the caller
with :meth:`MicroBatcher.incoming` while it decodes and projects them — so a lone scan is
encoded at once instead of waiting for company that is not coming. The batch runs in a
worker thread, off the event loop; while it encodes, the next one fills, so under load
batches grow without any added wait.

**Lanes.** ``lanes`` workers take batches from the one queue, each encoding in its own
thread, concurrently (an onnxruntime session and the scan kernel serve concurrent calls).
With as many lanes as cores and one onnxruntime thread each (the defaults), every core
encodes scans of its own instead of splitting each call's operators across the cores, which
on these small inputs spends CPU handing work between threads: on 2 cores a fleet got more
observations a second from the same CPU (``python benchmarks/fleet_views.py``, the shipped
file against one lane: ``reports/client/fleet-lanes.json``).

A full queue answers at once with :class:`~overlapmamba.service.errors.Overloaded` (503 +
Retry-After): queueing more work than can finish within a request timeout only turns 503s into 504s.
A scan whose request gave up (504, or the client gone) while it waited is skipped when a
lane takes it, and no longer counts as waiting (:attr:`MicroBatcher.pending`).
:meth:`MicroBatcher.stuck` names the lanes busy on one call for longer than a time, which
``/readyz`` and ``/healthz`` report: a call that never returns would otherwise leave the
service answering 504 to every scan while its probes say all is well.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from overlapmamba.service.errors import Overloaded, Timeout, Unavailable

# (B, V, H, W) images, (B,) column offsets → descriptors, yaw features (Encoder.encode)
EncodeFn = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass
class _Item:
    image: np.ndarray  # (V, H, W): one scan's views (Encoder.project_offset)
    offset: float  # its column offset (0 unless the model aligns columns)
    future: asyncio.Future[tuple[np.ndarray, np.ndarray]]
    taken: bool = False  # a lane took it off the queue
    abandoned: bool = False  # its request gave up while it was queued: counted as such


class MicroBatcher:
    def __init__(
        self,
        encode: EncodeFn,
        *,
        max_batch: int = 8,
        max_wait_ms: float = 2.0,
        queue_size: int = 64,
        lanes: int = 1,
        on_batch: Callable[[int, float], None] | None = None,
    ) -> None:
        if lanes < 1:
            raise ValueError(f"lanes must be at least 1; got {lanes}")
        self._encode = encode
        self.max_batch = max_batch
        self.max_wait_s = max_wait_ms / 1000.0
        self.queue_size = queue_size
        self._on_batch = on_batch
        self._queue: asyncio.Queue[_Item] | None = None
        self._coming = 0  # scans announced by incoming() and not yet queued
        self.lanes = lanes
        self._workers: list[asyncio.Task[None]] = []
        self._batches: list[list[_Item]] = [[] for _ in range(lanes)]  # each lane's, encoding
        self._busy_since: list[float | None] = [None] * lanes  # when its encoder call began
        self._abandoned = 0  # scans on the queue whose requests gave up waiting
        self._pool = ThreadPoolExecutor(max_workers=lanes, thread_name_prefix="encoder")

    async def start(self) -> None:
        self._queue = asyncio.Queue(maxsize=self.queue_size)
        self._workers = [
            asyncio.create_task(self._run(lane), name=f"micro-batcher-{lane}")
            for lane in range(self.lanes)
        ]

    async def stop(self) -> None:
        """Stop the workers; every scan still waiting, or in a batch cut off, is answered
        Unavailable at once rather than left to its caller's timeout."""
        for worker in self._workers:
            worker.cancel()
        for worker in self._workers:
            with contextlib.suppress(asyncio.CancelledError):
                await worker
        left = [item for batch in self._batches for item in batch]
        while self._queue is not None and not self._queue.empty():
            item = self._queue.get_nowait()
            item.taken = True
            left.append(item)
        self._abandoned = 0  # the queue is empty
        for item in left:
            if not item.future.done():
                item.future.set_exception(
                    Unavailable("the encoder stopped: the service is shutting down")
                )
        await asyncio.to_thread(self._pool.shutdown, wait=True)  # not on the event loop

    @contextlib.contextmanager
    def incoming(self) -> Iterator[None]:
        """Around the work that makes a scan's image (on the event loop's side): while any
        scan is announced, a started batch waits up to ``max_wait_ms`` for it."""
        self._coming += 1
        try:
            yield
        finally:
            self._coming -= 1

    @property
    def pending(self) -> int:
        """Scans on the queue whose requests still wait for them."""
        return max(0, self._queue.qsize() - self._abandoned) if self._queue is not None else 0

    def stuck(self, after_s: float) -> list[tuple[int, float]]:
        """(lane, seconds) of the lanes busy on one encoder call for longer than ``after_s``."""
        now = time.monotonic()
        return [
            (lane, now - t0)
            for lane, t0 in enumerate(self._busy_since)
            if t0 is not None and now - t0 > after_s
        ]

    async def encode(
        self, image: np.ndarray, offset: float = 0.0, *, timeout_s: float | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """One scan's (V, H, W) images and column offset → descriptor (D,), yaw features
        (C, W) in the sensor's columns."""
        assert self._queue is not None, "MicroBatcher.start() was not awaited"
        fut: asyncio.Future[tuple[np.ndarray, np.ndarray]] = (
            asyncio.get_running_loop().create_future()
        )
        item = _Item(image, offset, fut)
        try:
            self._queue.put_nowait(item)
        except asyncio.QueueFull:
            raise Overloaded(
                f"the encoder queue is full ({self.queue_size} scans waiting); retry shortly",
                queue_size=self.queue_size,
            ) from None
        try:
            return await asyncio.wait_for(fut, timeout_s)
        except TimeoutError:
            raise Timeout(f"encoding did not finish within {timeout_s} s") from None
        finally:
            if not item.taken and fut.done():  # gave up (timeout, cancelled) while queued
                item.abandoned = True
                self._abandoned += 1

    async def _run(self, lane: int) -> None:
        assert self._queue is not None
        loop = asyncio.get_running_loop()
        while True:
            first = self._take(await self._queue.get())
            if first is None:
                continue
            batch = [first]
            self._batches[lane] = batch  # filled in place: stop() answers what it holds
            deadline = loop.time() + self.max_wait_s
            while len(batch) < self.max_batch:
                try:
                    item = self._take(self._queue.get_nowait())
                    if item is not None:
                        batch.append(item)
                    continue
                except asyncio.QueueEmpty:
                    pass
                left = deadline - loop.time()
                if left <= 0 or not self._coming:  # nothing on its way: do not wait for it
                    break
                try:
                    item = self._take(await asyncio.wait_for(self._queue.get(), left))
                except TimeoutError:
                    break
                if item is not None:
                    batch.append(item)
            try:
                await self._encode_batch(batch, lane)
            except Exception as err:  # a failing batch fails its callers, not the worker
                for item in batch:
                    if not item.future.done():
                        item.future.set_exception(err)
            self._batches[lane] = []

    def _take(self, item: _Item) -> _Item | None:
        """An item off the queue; None for one whose request gave up waiting."""
        item.taken = True
        if item.future.done():  # counted only once its encode() saw it: maybe not yet
            if item.abandoned:
                self._abandoned -= 1
            return None
        return item

    async def _encode_batch(self, batch: list[_Item], lane: int = 0) -> None:
        loop = asyncio.get_running_loop()
        live = [item for item in batch if not item.future.done()]  # drop timed-out ones
        if not live:
            return
        images = np.stack([item.image for item in live])  # (B, V, H, W)
        offsets = np.array([item.offset for item in live], np.float64)
        t0 = loop.time()
        self._busy_since[lane] = time.monotonic()
        try:
            desc, yaw = await loop.run_in_executor(self._pool, self._encode, images, offsets)
        finally:
            self._busy_since[lane] = None
        elapsed = loop.time() - t0
        for i, item in enumerate(live):
            if not item.future.done():
                item.future.set_result((desc[i], yaw[i]))
        if self._on_batch is not None:
            self._on_batch(len(live), elapsed)
