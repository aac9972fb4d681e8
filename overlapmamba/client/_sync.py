"""``PlaceRecognitionClient``: the blocking client (httpx.Client; websockets for streams)."""

from __future__ import annotations

import random
import time
from collections import deque
from collections.abc import Iterable, Iterator
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
    send_within,
    stream_failure,
    stream_result,
    ws_url,
)


class PlaceRecognitionClient:
    """Blocking client of the place-recognition service.

    >>> with PlaceRecognitionClient("http://127.0.0.1:8000") as pr:
    ...     pr.create_map("town")
    """

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8000",
        *,
        api_key: str | None = None,
        timeout: Timeouts = Timeouts(),  # noqa: B008 — frozen, shared safely
        retry: Retry = Retry(),  # noqa: B008
        compress: bool = False,
        transport: httpx.BaseTransport | None = None,
        seed: int | None = None,
        sensor: str | None = None,
        mount: MountArg = None,
    ) -> None:
        self.base_url = base_url.rstrip("/")
        self.api_key = api_key
        self.timeout = timeout
        self.retry = retry
        # sensor: every scan's, unless a call names its; mount: where it sits (`mount` below)
        self._calls = Calls(compress, sensor, check_mount(mount))
        self._rng = random.Random(seed)
        headers = {"x-api-key": api_key} if api_key else {}
        self._http = httpx.Client(
            base_url=self.base_url, timeout=timeout.httpx(), headers=headers, transport=transport
        )

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> PlaceRecognitionClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _run(self, call: Call) -> Any:
        attempts = self.retry.attempts if call.idempotent else 1
        maybe_applied = False  # an earlier try may have been carried out
        for attempt in range(1, attempts + 1):
            try:
                try:
                    resp = self._http.request(
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
                return mark_retried(read_answer(call, resp), maybe_applied)
            except ClientError as err:
                if deleted_before(call, err, maybe_applied):
                    return None
                if attempt == attempts or not retryable(err, self.retry):
                    raise
                maybe_applied = maybe_applied or may_have_applied(err)
                retry_after = err.retry_after if isinstance(err, APIError) else None
                time.sleep(self.retry.delay(attempt, retry_after, self._rng))
        raise AssertionError("unreachable")

    # ---- the API ----------------------------------------------------------------------------

    def health(self) -> dict[str, Any]:
        """``/readyz``: ``{"status": "ready", "detail": {…}}``, or while the service is not
        ready (loading, draining, failed, stuck) that status with its stage, not an error."""
        return self._run(self._calls.health())

    def sensors(self) -> dict[str, Any]:
        """The sensors scans may name (``/v1/sensors``): the catalogue, with each one's beam
        table and how its scans enter the model."""
        return self._run(self._calls.sensors())

    def describe(
        self, scan: Scan, *, sensor: str | None = None, mount: MountArg = None
    ) -> Descriptor:
        """``sensor`` and ``mount``: this scan's, when they are not the client's."""
        return self._run(self._calls.describe(scan, sensor, mount))

    def describe_batch(
        self, scans: list[Scan], *, sensor: str | None = None, mount: MountArg = None
    ) -> list[Descriptor]:
        return self._run(self._calls.describe_batch(scans, sensor, mount))

    def create_map(
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
        return self._run(call)

    def list_maps(self) -> list[MapInfo]:
        return self._run(self._calls.list_maps())

    def get_map(self, map_id: str) -> MapInfo:
        return self._run(self._calls.get_map(map_id))

    def delete_map(self, map_id: str) -> None:
        self._run(self._calls.delete_map(map_id))

    def insert_keyframe(
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
        call = self._calls.insert_keyframe(
            map_id, scan, keyframe_id, timestamp, robot_id, session_id, pose, sensor, mount
        )
        return self._run(call)

    def insert_descriptors(
        self, map_id: str, keyframes: list[dict[str, Any]], *, model_id: str
    ) -> BatchInsertResult:
        call = self._calls.insert_descriptors(map_id, model_id, keyframes)
        return self._run(call)

    def get_keyframe(self, map_id: str, keyframe_id: str) -> Keyframe:
        return self._run(self._calls.get_keyframe(map_id, keyframe_id))

    def delete_keyframe(self, map_id: str, keyframe_id: str) -> None:
        self._run(self._calls.delete_keyframe(map_id, keyframe_id))

    def query(
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
        return self._run(self._calls.query(map_id, scan, descriptor, k, filters, sensor, mount))

    def observe(
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
        call = self._calls.observe(
            map_id, scan, robot_id, session_id, timestamp, pose, insert, k, verify, sensor, mount
        )
        return self._run(call)

    def stats(self, map_id: str | None = None) -> dict[str, Any]:
        return self._run(self._calls.stats(map_id))

    def stream(
        self,
        map_id: str,
        observations: Iterable[Observation],
        *,
        robot_id: str,
        session_id: str = "default",
        k: int = 10,
        window: int = 2,
        errors: str = "raise",
        sensor: str | None = None,
        mount: MountArg = None,
    ) -> Iterator[ObserveResult | APIError]:
        """Observe over one WebSocket, results in order. At most ``window`` observations are
        in flight (the server closes a client that outruns it). ``errors="return"`` yields a
        refused observation's APIError instead of raising it. ``sensor`` and ``mount``: the
        stream's scans' (an observation may name its own)."""
        from websockets.sync.client import connect

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
        pending: deque[int] = deque()
        try:
            yield from self._stream(connect, url, headers, observations, window, errors, pending)
        except APIError as err:  # refused, errors="raise": those sent after it go unanswered
            err.unanswered = list(pending)[1:]  # type: ignore[attr-defined]
            raise
        except Exception as err:
            failure = stream_failure(err, pending)
            if failure is None:
                raise
            raise failure from err

    def _stream(
        self,
        connect: Any,
        url: str,
        headers: dict[str, str],
        observations: Iterable[Observation],
        window: int,
        errors: str,
        pending: deque[int],
    ) -> Iterator[ObserveResult | APIError]:
        from websockets.exceptions import ConnectionClosed

        compress = self._calls.compress
        retries: set[int] = set()  # the observations sent again (``retry``)
        with connect(
            url,
            additional_headers=headers,
            open_timeout=self.timeout.connect,
            close_timeout=close_within(self.timeout),
        ) as ws:
            try:
                for i, obs in enumerate(observations):
                    pending.append(i)  # before: one whose sending fails is unanswered too
                    send_within(ws, observation_frames(obs, i, compress), self.timeout.write)
                    if obs.retry:
                        retries.add(i)
                    while len(pending) >= window:
                        text = ws.recv(timeout=self.timeout.read)
                        yield stream_result(text, errors, pending[0] in retries, pending[0])
                        pending.popleft()
                while pending:
                    text = ws.recv(timeout=self.timeout.read)
                    yield stream_result(text, errors, pending[0] in retries, pending[0])
                    pending.popleft()
            except ConnectionClosed:
                # the server closed (a restart's 1012): the answers that came before it are
                # the robot's, only the rest are unanswered
                while pending:
                    try:
                        text = ws.recv(timeout=0)
                    except (ConnectionClosed, TimeoutError):
                        break
                    yield stream_result(text, errors, pending[0] in retries, pending[0])
                    pending.popleft()
                raise
