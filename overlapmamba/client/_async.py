"""``AsyncPlaceRecognitionClient``: the asyncio client, method for method the same as the
blocking one (httpx.AsyncClient; websockets for streams)."""

from __future__ import annotations

import asyncio
import random
from collections import Counter, deque
from collections.abc import AsyncIterable, AsyncIterator, Iterable
from typing import Any

import httpx

from overlapmamba.client._base import Call, Calls, MountArg, Timeouts, check_mount
from overlapmamba.client._exceptions import APIError, ClientError
from overlapmamba.client._models import (
    BatchInsertResult,
    Descriptor,
    Keyframe,
    MapInfo,
    Observation,
    ObserveResult,
    QueryResult,
)
from overlapmamba.client._retry import (
    Retry,
    answered,
    deleted_before,
    mark_retried,
    may_have_applied,
    not_this_api,
    raise_for,
    read_answer,
    retryable,
    transport_error,
)
from overlapmamba.client._scans import Scan
from overlapmamba.client._stream import (
    check_errors,
    check_window,
    close_within,
    observation_frames,
    send_timeout,
    stream_failure,
    stream_result,
    ws_url,
)


class AsyncPlaceRecognitionClient:
    """Asyncio client of the place-recognition service. A request that carries a scan is
    built in a worker thread (``asyncio.to_thread``): reading its file and compressing it
    take milliseconds a scan (tens with zstd), which every other task on the loop would wait.

    >>> async with AsyncPlaceRecognitionClient("http://127.0.0.1:8000") as pr:
    ...     await pr.create_map("town")
    """

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8000",
        *,
        api_key: str | None = None,
        timeout: Timeouts = Timeouts(),  # noqa: B008 — frozen, shared safely
        retry: Retry = Retry(),  # noqa: B008
        compress: bool = False,
        transport: httpx.AsyncBaseTransport | None = None,
        seed: int | None = None,
        sensor: str | None = None,
        mount: MountArg = None,
        max_connections: int = 100,
    ) -> None:
        """``max_connections``: requests in flight at once (httpx's pool; more wait in the
        client for a free connection, their wait counted in their time)."""
        self.base_url = base_url.rstrip("/")
        self.api_key = api_key
        self.timeout = timeout
        self.retry = retry
        # sensor: every scan's, unless a call names its; mount: where it sits (`mount` below)
        self._calls = Calls(compress, sensor, check_mount(mount))
        self._rng = random.Random(seed)
        headers = {"x-api-key": api_key} if api_key else {}
        self._http = httpx.AsyncClient(
            base_url=self.base_url,
            timeout=timeout.httpx(),
            headers=headers,
            transport=transport,
            limits=httpx.Limits(max_connections=max_connections),
        )
        # tries that failed (by error code, or class) of calls a later try then got through:
        # a load run's refusals that retries absorbed (a call that failed for good is the
        # caller's error, not counted here)
        self.retried: Counter[str] = Counter()

    async def close(self) -> None:
        await self._http.aclose()

    async def __aenter__(self) -> AsyncPlaceRecognitionClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def _run(self, call: Call) -> Any:
        attempts = self.retry.attempts if call.idempotent else 1
        maybe_applied = False  # an earlier try may have been carried out
        failed: list[str] = []  # this call's tries that failed and were tried again
        for attempt in range(1, attempts + 1):
            try:
                try:
                    resp = await self._http.request(
                        call.method,
                        call.path,
                        params=call.params,
                        content=call.content,
                        json=call.json,
                        headers=call.headers,
                    )
                except httpx.TransportError as err:
                    raise transport_error(err) from err
                except httpx.DecodingError as err:
                    raise not_this_api(call, None, err) from err
                if not answered(call, resp):
                    raise_for(resp)
                result = mark_retried(read_answer(call, resp), maybe_applied)
                self.retried.update(failed)  # got through after them
                return result
            except ClientError as err:
                if deleted_before(call, err, maybe_applied):
                    return None
                if attempt == attempts or not retryable(err, self.retry):
                    raise
                maybe_applied = maybe_applied or may_have_applied(err)
                retry_after = err.retry_after if isinstance(err, APIError) else None
                failed.append(err.code if isinstance(err, APIError) else type(err).__name__)
                await asyncio.sleep(self.retry.delay(attempt, retry_after, self._rng))
        raise AssertionError("unreachable")

    # ---- the API ----------------------------------------------------------------------------

    async def health(self) -> dict[str, Any]:
        """``/readyz``: ``{"status": "ready", "detail": {…}}``, or while the service is not
        ready (loading, draining, failed, stuck) that status with its stage, not an error."""
        return await self._run(self._calls.health())

    async def sensors(self) -> dict[str, Any]:
        """The sensors scans may name (``/v1/sensors``): the catalogue, with each one's beam
        table and how its scans enter the model."""
        return await self._run(self._calls.sensors())

    async def describe(
        self, scan: Scan, *, sensor: str | None = None, mount: MountArg = None
    ) -> Descriptor:
        """``sensor`` and ``mount``: this scan's, when they are not the client's."""
        call = await asyncio.to_thread(self._calls.describe, scan, sensor, mount)
        return await self._run(call)

    async def describe_batch(
        self, scans: list[Scan], *, sensor: str | None = None, mount: MountArg = None
    ) -> list[Descriptor]:
        call = await asyncio.to_thread(self._calls.describe_batch, scans, sensor, mount)
        return await self._run(call)

    async def create_map(
        self,
        map_id: str,
        *,
        index: str | None = None,
        keep_geometry: bool | None = None,
        sensor: str | None = None,
        mount: MountArg = None,
    ) -> MapInfo:
        """Create a map (idempotent). ``keep_geometry=False``: a descriptor-only map, whose
        answers are never verified (default: the server's, true). ``sensor``: the sensor of
        scans sent to it that name none (default: the model's own); ``mount``
        (``"0.35"``, ``(1.8, 5.0)``: height m, pitch °, roll °): where it sits on the scans
        sent to it that declare none (default: none declared)."""
        call = self._calls.create_map(map_id, index, keep_geometry, sensor, mount)
        return await self._run(call)

    async def list_maps(self) -> list[MapInfo]:
        return await self._run(self._calls.list_maps())

    async def get_map(self, map_id: str) -> MapInfo:
        return await self._run(self._calls.get_map(map_id))

    async def delete_map(self, map_id: str) -> None:
        await self._run(self._calls.delete_map(map_id))

    async def insert_keyframe(
        self,
        map_id: str,
        scan: Scan,
        *,
        keyframe_id: str,
        timestamp: float,
        robot_id: str = "unknown",
        session_id: str = "default",
        pose: Any = None,
        sensor: str | None = None,
        mount: MountArg = None,
    ) -> Keyframe:
        call = await asyncio.to_thread(
            self._calls.insert_keyframe,
            map_id,
            scan,
            keyframe_id,
            timestamp,
            robot_id,
            session_id,
            pose,
            sensor,
            mount,
        )
        return await self._run(call)

    async def insert_descriptors(
        self, map_id: str, keyframes: list[dict[str, Any]], *, model_id: str
    ) -> BatchInsertResult:
        call = self._calls.insert_descriptors(map_id, model_id, keyframes)
        return await self._run(call)

    async def get_keyframe(self, map_id: str, keyframe_id: str) -> Keyframe:
        return await self._run(self._calls.get_keyframe(map_id, keyframe_id))

    async def delete_keyframe(self, map_id: str, keyframe_id: str) -> None:
        await self._run(self._calls.delete_keyframe(map_id, keyframe_id))

    async def query(
        self,
        map_id: str,
        scan: Scan | None = None,
        *,
        descriptor: Any = None,
        k: int = 10,
        sensor: str | None = None,
        mount: MountArg = None,
        **filters: Any,
    ) -> QueryResult:
        """Filters: exclude_session, exclude_robot, exclude_recent_s (with session_id and
        timestamp), max_match_distance, time_from, time_to; ``verify=False`` skips the geometric
        verification of a scan query's candidates; ``sensor`` and ``mount``: the scan's."""
        build = self._calls.query
        args = (map_id, scan, descriptor, k, filters, sensor, mount)
        if scan is None:  # a descriptor: nothing to read or compress
            return await self._run(build(*args))
        return await self._run(await asyncio.to_thread(build, *args))

    async def observe(
        self,
        map_id: str,
        scan: Scan,
        *,
        robot_id: str,
        timestamp: float,
        session_id: str = "default",
        pose: Any = None,
        insert: str = "auto",
        k: int = 10,
        verify: bool = True,
        sensor: str | None = None,
        mount: MountArg = None,
    ) -> ObserveResult:
        """``verify``: the server registers the top candidates against their keyframes'
        geometry (each match's ``relative_pose``/``verification``, a verified closure).
        ``sensor`` and ``mount``: the scan's, when they are not the client's."""
        call = await asyncio.to_thread(
            self._calls.observe,
            map_id,
            scan,
            robot_id,
            session_id,
            timestamp,
            pose,
            insert,
            k,
            verify,
            sensor,
            mount,
        )
        return await self._run(call)

    async def stats(self, map_id: str | None = None) -> dict[str, Any]:
        return await self._run(self._calls.stats(map_id))

    async def stream(
        self,
        map_id: str,
        observations: Iterable[Observation] | AsyncIterable[Observation],
        *,
        robot_id: str,
        session_id: str = "default",
        k: int = 10,
        window: int = 2,
        errors: str = "raise",
        sensor: str | None = None,
        mount: MountArg = None,
    ) -> AsyncIterator[ObserveResult | APIError]:
        """Observe over one WebSocket, results in order. At most ``window`` observations are
        in flight (the server closes a client that outruns it). ``errors="return"`` yields a
        refused observation's APIError instead of raising it. ``sensor`` and ``mount``: the
        stream's scans' (an observation may name its own)."""
        from websockets.asyncio.client import connect

        check_window(window)
        check_errors(errors)
        url = ws_url(
            self.base_url,
            map_id,
            robot_id=robot_id,
            session_id=session_id,
            k=k,
            sensor=sensor or self._calls.sensor,
            mount=check_mount(mount) or self._calls.mount,
        )
        headers = {"x-api-key": self.api_key} if self.api_key else {}

        async def items() -> AsyncIterator[Observation]:
            if isinstance(observations, AsyncIterable):
                async for o in observations:
                    yield o
            else:
                for o in observations:
                    yield o

        pending: deque[int] = deque()
        try:
            async with connect(
                url,
                additional_headers=headers,
                open_timeout=self.timeout.connect,
                close_timeout=close_within(self.timeout),
            ) as ws:
                async for result in self._exchange(ws, items(), window, errors, pending):
                    yield result
        except APIError as err:  # refused, errors="raise": those sent after it go unanswered
            err.unanswered = list(pending)[1:]  # type: ignore[attr-defined]
            raise
        except Exception as err:
            failure = stream_failure(err, pending)
            if failure is None:
                raise
            raise failure from err

    async def _exchange(
        self,
        ws: Any,
        observations: AsyncIterator[Observation],
        window: int,
        errors: str,
        pending: deque[int],
    ) -> AsyncIterator[ObserveResult | APIError]:
        from websockets.exceptions import ConnectionClosed

        retries: set[int] = set()  # the observations sent again (``retry``)
        try:
            async for result in self._send_and_read(
                ws, observations, window, errors, pending, retries
            ):
                yield result
        except ConnectionClosed:
            # the server closed (a restart's 1012): the answers that came before it are the
            # robot's, only the rest are unanswered
            while pending:
                try:
                    text = await asyncio.wait_for(ws.recv(), 0.1)
                except (ConnectionClosed, TimeoutError):
                    break
                yield stream_result(text, errors, pending[0] in retries, pending[0])
                pending.popleft()
            raise

    async def _send_and_read(
        self,
        ws: Any,
        observations: AsyncIterator[Observation],
        window: int,
        errors: str,
        pending: deque[int],
        retries: set[int],
    ) -> AsyncIterator[ObserveResult | APIError]:
        compress = self._calls.compress
        i = 0
        async for obs in observations:
            meta, body = await asyncio.to_thread(observation_frames, obs, i, compress)
            pending.append(i)  # before: one whose sending fails is unanswered too
            try:  # a half-open link takes no data: give up after timeout.write
                await asyncio.wait_for(_send_both(ws, meta, body), self.timeout.write)
            except TimeoutError:
                # closing would wait, without a deadline, for the same buffers to drain
                ws.transport.abort()
                raise send_timeout(self.timeout.write) from None
            if obs.retry:
                retries.add(i)
            i += 1
            while len(pending) >= window:
                text = await asyncio.wait_for(ws.recv(), self.timeout.read)
                yield stream_result(text, errors, pending[0] in retries, pending[0])
                pending.popleft()
        while pending:
            text = await asyncio.wait_for(ws.recv(), self.timeout.read)
            yield stream_result(text, errors, pending[0] in retries, pending[0])
            pending.popleft()


async def _send_both(ws: Any, meta: str, body: bytes) -> None:
    """One observation's two frames, under one deadline."""
    await ws.send(meta)
    await ws.send(body)
