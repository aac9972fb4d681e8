"""The clients at their limits, without a server: a Retry-After no robot should wait out, a
redirect, a stream error frame's status, the sync stream's mount and window, bad retry
settings and ROS time at a second's edge."""

from __future__ import annotations

import json
import time

import httpx
import pytest

from overlapmamba.client import (
    BadRequestError,
    ConnectError,
    NotFoundError,
    OverloadedError,
    PlaceRecognitionClient,
    Retry,
    ServerError,
    TransportError,
)
from overlapmamba.client._stream import stream_result


def _answers(plan: list[httpx.Response], calls: list[float]) -> httpx.MockTransport:
    def handler(request: httpx.Request) -> httpx.Response:
        calls.append(time.monotonic())
        return plan.pop(0) if plan else httpx.Response(200, json={"status": "ready"})

    return httpx.MockTransport(handler)


def _busy(retry_after: str) -> httpx.Response:
    body = {"error": {"code": "overloaded", "message": "busy", "detail": {}}}
    return httpx.Response(503, json=body, headers={"Retry-After": retry_after})


@pytest.mark.parametrize("asked", ["3600", "inf"])
def test_a_retry_after_longer_than_the_cap_is_raised_at_once(asked):
    """A proxy's Retry-After of an hour (or inf) must not hold a robot's call that long:
    past ``max_retry_after_s`` the error goes to the caller without waiting."""
    calls: list[float] = []
    retry = Retry(attempts=4, backoff_s=0.01, jitter=0.0, max_retry_after_s=5.0)
    with PlaceRecognitionClient(transport=_answers([_busy(asked)], calls), retry=retry) as pr:
        t0 = time.monotonic()
        with pytest.raises(OverloadedError) as e:
            pr.health()
        assert time.monotonic() - t0 < 2.0
    assert len(calls) == 1 and e.value.retry_after == float(asked)
    calls.clear()
    with PlaceRecognitionClient(transport=_answers([_busy("0.05")], calls), retry=retry) as pr:
        assert pr.health()["status"] == "ready"  # within the cap: waited and retried
    assert len(calls) == 2


def test_a_redirect_is_an_error_that_says_where_and_is_not_retried():
    calls: list[float] = []
    moved = httpx.Response(301, headers={"location": "https://places.example/v1/healthz"})
    with (
        PlaceRecognitionClient(transport=_answers([moved], calls)) as pr,
        pytest.raises(BadRequestError, match="redirects to https://places.example") as e,
    ):
        pr.health()
    assert e.value.code == "redirect" and len(calls) == 1


def test_retry_settings_are_checked():
    with pytest.raises(ValueError, match="attempts must be at least 1"):
        Retry(attempts=0)
    with pytest.raises(ValueError, match="max_retry_after_s=inf"):
        Retry(max_retry_after_s=float("inf"))
    with pytest.raises(ValueError, match="jitter"):
        Retry(jitter=2.0)


def test_a_stream_error_frame_keeps_its_status():
    """A stream error is the exception its HTTP status would give (503 storage_full is an
    OverloadedError a robot can wait out), not always a 400."""
    frame = {"seq": 3, "ok": False, "status": 503, "error": {"code": "storage_full"}}
    err = stream_result(json.dumps(frame), errors="return")
    assert isinstance(err, OverloadedError) and err.status == 503
    assert err.code == "storage_full" and err.detail["seq"] == 3
    frame = {"seq": 4, "ok": False, "status": 500, "error": {"code": "internal_error"}}
    with pytest.raises(ServerError):
        stream_result(json.dumps(frame))
    older = {"seq": 5, "ok": False, "error": {"code": "bad_stream_frame", "message": "m"}}
    assert stream_result(json.dumps(older), errors="return").status == 400  # type: ignore[union-attr]


def test_the_sync_stream_sends_the_clients_mount_and_checks_its_window(monkeypatch):
    import websockets.sync.client as ws_client

    urls: list[str] = []

    def refused(url: str, **_: object) -> None:
        urls.append(url)
        raise ConnectionRefusedError("no server here")

    monkeypatch.setattr(ws_client, "connect", refused)
    with PlaceRecognitionClient("http://test", mount="0.7,5") as pr:
        with pytest.raises(ConnectError, match="cannot connect the stream: no server here"):
            list(pr.stream("town", [], robot_id="r1"))
        assert "mount=" in urls[0] and "0.7" in urls[0]
        with pytest.raises(ValueError, match="window must be a whole number ≥ 1"):
            list(pr.stream("town", [], robot_id="r1", window=0))


def test_ros_time_rounds_across_a_seconds_edge():
    from overlapmamba.client.recording import _time

    assert _time(1.9999999999) == {"sec": 2, "nsec": 0}
    assert _time(3.25) == {"sec": 3, "nsec": 250_000_000}


class _ClosingSocket:
    """A stream socket that takes observations and then is closed by the server: 1013, the
    client outran it."""

    def __init__(self, *_: object, **__: object) -> None:
        self.sent = 0

    def __enter__(self) -> _ClosingSocket:
        return self

    def __exit__(self, *_: object) -> None:
        return None

    def send(self, _: object) -> None:
        self.sent += 1

    def recv(self, timeout: float | None = None) -> str:
        from websockets.exceptions import ConnectionClosedError
        from websockets.frames import Close

        raise ConnectionClosedError(Close(1013, "client outran the server"), None)


def test_a_stream_the_server_closes_is_a_client_error_naming_what_went_unanswered(
    monkeypatch,
):
    """The socket's own failures come as the library's errors (a robot's ``except
    ClientError`` catches them), saying which observations were sent and never answered."""
    import numpy as np
    import websockets.sync.client as ws_client

    from overlapmamba.client import Observation

    monkeypatch.setattr(ws_client, "connect", _ClosingSocket)
    scan = np.zeros((10, 4), np.float32)
    obs = [Observation(scan=scan, timestamp=float(t)) for t in range(3)]
    with (
        PlaceRecognitionClient("http://test") as pr,
        pytest.raises(TransportError, match="1013 client outran the server") as e,
    ):
        list(pr.stream("town", obs, robot_id="r1", window=2))
    assert e.value.unanswered == [0, 1]  # type: ignore[attr-defined]


@pytest.mark.parametrize("kind", ["sync", "async"])
def test_a_stream_whose_server_takes_no_data_gives_up_after_the_write_timeout(kind):
    """A half-open link (the server's machine gone) takes no more data: the socket's buffers
    fill and a send would wait until TCP gives up, many minutes on. Here a real WebSocket
    server stops reading after the handshake; either client's stream raises the library's
    Timeout, naming timeout.write and what went unanswered, within the write timeout."""
    import asyncio
    import threading

    import numpy as np
    from websockets.sync.server import serve

    from overlapmamba.client import AsyncPlaceRecognitionClient, Observation, Timeout, Timeouts

    release = threading.Event()
    scan = np.random.default_rng(0).normal(size=(400_000, 4)).astype(np.float32)  # 6.4 MB
    # more than a socket's buffers take whatever their size (tcp_rmem's top is 32 MB here),
    # all in flight at once so that the stream never stops to read
    obs = [Observation(scan=scan, timestamp=float(t)) for t in range(16)]
    timeouts = Timeouts(write=0.5, read=30.0)
    outcome: list[BaseException | None] = []

    async def async_robot(url: str) -> None:
        async with AsyncPlaceRecognitionClient(url, timeout=timeouts) as pr:
            async for _ in pr.stream("town", obs, robot_id="r1", window=len(obs)):
                pass

    def robot(url: str) -> None:
        try:
            if kind == "sync":
                with PlaceRecognitionClient(url, timeout=timeouts) as pr:
                    list(pr.stream("town", obs, robot_id="r1", window=len(obs)))
            else:
                asyncio.run(async_robot(url))
            outcome.append(None)
        except BaseException as err:
            outcome.append(err)

    handler = lambda ws: release.wait(20)  # noqa: E731 — reads nothing after the handshake
    with serve(handler, "127.0.0.1", 0, max_queue=1, max_size=None, close_timeout=1) as srv:
        threading.Thread(target=srv.serve_forever, daemon=True).start()
        url = f"http://127.0.0.1:{srv.socket.getsockname()[1]}"
        t0 = time.monotonic()
        worker = threading.Thread(target=robot, args=(url,), daemon=True)
        worker.start()
        worker.join(10)
        stuck, took = worker.is_alive(), time.monotonic() - t0
        release.set()
        srv.shutdown()
    assert not stuck and took < 10, "the stream's send still waits on a server taking no data"
    err = outcome[0]
    assert isinstance(err, Timeout), err
    assert "could not be sent within 0.5 s (timeout.write)" in str(err)
    # those sent in full before the stall (none when the first scan already filled the
    # buffers: how much a socket takes is the kernel's to size)
    sent = err.unanswered  # type: ignore[attr-defined]
    assert sent == list(range(len(sent))) and len(sent) < len(obs)


def test_a_refused_stream_handshake_says_the_servers_status_and_error():
    """The server refuses a stream's handshake as a route answers (its status and JSON
    error): the client's ConnectError carries both, not websockets' bare 'HTTP 404'."""
    from websockets.datastructures import Headers
    from websockets.exceptions import InvalidStatus
    from websockets.http11 import Response

    from overlapmamba.client._stream import stream_failure

    body = b'{"error": {"code": "map_not_found", "message": "map \'x\' does not exist"}}'
    err = stream_failure(InvalidStatus(Response(404, "Not Found", Headers(), body)), [])
    assert isinstance(err, ConnectError)
    assert "404 map_not_found: map 'x' does not exist" in str(err), err
    bare = stream_failure(InvalidStatus(Response(403, "Forbidden", Headers(), b"")), [])
    assert "403" in str(bare)


def test_ids_that_are_path_steps_are_refused_before_anything_is_sent():
    """``delete_keyframe("town", "..")`` went out as ``DELETE /v1/maps/town`` (httpx reads
    ``..`` as a step up): the whole map was deleted. ``.``, ``..`` and empty ids are refused."""
    calls: list[float] = []
    with PlaceRecognitionClient(transport=_answers([], calls)) as pr:
        for call in (
            lambda: pr.delete_keyframe("town", ".."),
            lambda: pr.delete_keyframe("town", "."),
            lambda: pr.get_keyframe("town", ".."),
            lambda: pr.delete_map(".."),
            lambda: pr.get_map(""),
        ):
            with pytest.raises(ValueError, match="is not an id"):
                call()
    assert calls == []


def test_a_misspelt_query_filter_is_an_error_not_an_unfiltered_answer():
    calls: list[float] = []
    with (
        PlaceRecognitionClient(transport=_answers([], calls)) as pr,
        pytest.raises(TypeError, match="exclude_sessions.*allowed: exclude_recent_s"),
    ):
        pr.query("town", descriptor=[1.0] * 4, exclude_sessions="s1")
    assert calls == []


def test_a_503_an_operator_must_mend_and_an_http_date_past_the_cap_are_raised_at_once():
    """``storage_full`` and ``start_failed`` say Retry-After 30: every call waited 3 × 30 s
    for what only an operator mends. An HTTP-date Retry-After (a proxy's) was not read, and
    the call retried at once however long it asked."""
    from email.utils import format_datetime

    calls: list[float] = []
    full = httpx.Response(
        503,
        json={"error": {"code": "storage_full", "message": "disk full", "detail": {}}},
        headers={"Retry-After": "30"},
    )
    with (
        PlaceRecognitionClient(transport=_answers([full], calls)) as pr,
        pytest.raises(OverloadedError) as e,
    ):
        pr.health()
    assert len(calls) == 1 and e.value.code == "storage_full"
    calls.clear()
    later = format_datetime(
        __import__("datetime").datetime.now(__import__("datetime").UTC)
        + __import__("datetime").timedelta(hours=1),
        usegmt=True,
    )
    with (
        PlaceRecognitionClient(transport=_answers([_busy(later)], calls)) as pr,
        pytest.raises(OverloadedError) as e,
    ):
        pr.health()
    assert len(calls) == 1 and 3500 < (e.value.retry_after or 0) <= 3600


def test_health_answers_a_service_that_is_not_ready_with_its_status():
    """``/readyz`` says 503 with its status and stage while the maps load: ``health()``
    retried it four times and raised an OverloadedError ``http_error`` with the stage lost."""
    calls: list[float] = []
    loading = httpx.Response(
        503,
        json={"status": "loading", "detail": {"stage": "loading maps"}},
        headers={"Retry-After": "1"},
    )
    with PlaceRecognitionClient(transport=_answers([loading], calls)) as pr:
        got = pr.health()
    assert got == {"status": "loading", "detail": {"stage": "loading maps"}} and len(calls) == 1


def test_a_url_or_key_that_can_never_be_sent_is_not_retried(monkeypatch):
    """A URL without its scheme, or a key read from a file with its newline, can never be
    sent: each was tried four times, with backoff, as if the network had failed."""
    import http.server
    import threading

    from overlapmamba.client import _sync

    waits: list[float] = []  # the backoff between tries: none, for one try
    monkeypatch.setattr(_sync.time, "sleep", waits.append)
    srv = http.server.HTTPServer(("127.0.0.1", 0), http.server.BaseHTTPRequestHandler)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        here = f"http://127.0.0.1:{srv.server_address[1]}"
        for url, key in (("localhost:8000", None), (here, "s3cret\n")):
            with PlaceRecognitionClient(url, api_key=key) as pr, pytest.raises(TransportError):
                pr.health()
            assert waits == [], url
    finally:
        srv.shutdown()
        srv.server_close()


def test_a_stream_checks_its_ids_and_k_before_it_connects(monkeypatch):
    import websockets.sync.client as ws_client

    def never(url: str, **_: object) -> None:
        raise AssertionError("connected")

    monkeypatch.setattr(ws_client, "connect", never)
    with PlaceRecognitionClient("http://test") as pr:
        with pytest.raises(ValueError, match="robot_id 'robot 1' is not allowed"):
            list(pr.stream("town", [], robot_id="robot 1"))
        with pytest.raises(ValueError, match="k=0"):
            list(pr.stream("town", [], robot_id="r1", k=0))


def test_a_pose_as_the_server_writes_it_and_a_numpy_timestamp_are_taken():
    import numpy as np

    sent: list[httpx.Request] = []

    def handler(request: httpx.Request) -> httpx.Response:
        sent.append(request)
        kf = {
            "keyframe_id": "a",
            "timestamp": 1.0,
            "robot_id": "r",
            "session_id": "s",
            "pose": None,
            "created": True,
        }
        return httpx.Response(200, json={"inserted": 1, "existing": 0, "keyframes": [kf]})

    with PlaceRecognitionClient(transport=httpx.MockTransport(handler)) as pr:
        row = {
            "keyframe_id": "a",
            "timestamp": np.float32(1.5),
            "robot_id": "r",
            "session_id": "s",
            "pose": None,
            "descriptor": np.ones(4),
        }
        pr.insert_descriptors("town", [row], model_id="m")
        assert json.loads(sent[0].content)["keyframes"][0]["timestamp"] == 1.5
        with pytest.raises(ValueError, match="pose must be 7 numbers"):
            pr.observe(
                "town", np.ones((10, 4), np.float32), robot_id="r", timestamp=1.0, pose="1,2"
            )
    from overlapmamba.client._base import _pose

    assert _pose("1,2,3, 0,0,0,1") == "1.0,2.0,3.0,0.0,0.0,0.0,1.0"  # the server's own form


def _answers_then_restarts(answers: int):
    """A stream server that answers the first ``answers`` observations, then closes 1012 (a
    restart) while the client still sends; (url, stop)."""
    import threading

    from websockets.sync.server import serve

    lc = {"accepted": False, "keyframe_id": None, "threshold": 0.1, "margin_top1_top2": None}

    def handler(ws):
        for i in range(answers):
            ws.recv()
            ws.recv()
            ws.send(
                json.dumps(
                    {"seq": i, "ok": True, "matches": [], "loop_closure": lc, "keyframe": None,
                     "inserted": False, "timings_ms": {}}
                )
            )  # fmt: skip
        time.sleep(0.2)  # both answers on their way before the close
        ws.close(1012)

    server = serve(handler, "127.0.0.1", 0)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return f"http://127.0.0.1:{server.socket.getsockname()[1]}", server.shutdown


def test_answers_received_before_a_restart_are_yielded_not_called_unanswered():
    """Found in review: a stream whose server closed (1012, a restart) while the client was
    still sending reported as unanswered the observations whose answers had already come
    (read only once the window filled), so a robot would send them again."""
    import numpy as np

    from overlapmamba.client import Observation

    url, stop = _answers_then_restarts(2)
    scan = np.zeros((10, 4), np.float32)

    def observations():
        yield Observation(scan, 0.0)
        yield Observation(scan, 1.0)
        time.sleep(0.6)  # the third comes once the server has answered both and closed
        yield Observation(scan, 2.0)

    got = []
    try:
        with PlaceRecognitionClient(url) as pr, pytest.raises(TransportError) as err:
            for result in pr.stream("m", observations(), robot_id="r", window=3):
                got.append(result)
    finally:
        stop()
    assert len(got) == 2 and err.value.unanswered == [2]


def test_an_answer_under_another_seq_than_the_one_due_is_refused_not_misattributed():
    """Found in review: the clients matched answers to observations by their order alone; an
    answer out of order (a proxy reordering frames) would have put one scan's loop closure on
    another's pose. A refusal whose seq could not be read (null) is taken as the one due."""
    from overlapmamba.client._exceptions import ResponseError
    from overlapmamba.client._stream import stream_result

    lc = {"accepted": False, "keyframe_id": None, "threshold": 0.1, "margin_top1_top2": None}
    answer = {"ok": True, "matches": [], "loop_closure": lc, "keyframe": None,
              "inserted": False, "timings_ms": {}}  # fmt: skip
    assert stream_result(json.dumps({**answer, "seq": 3}), expected=3).seq == 3
    with pytest.raises(ResponseError, match="answered seq 4 where 3 was due"):
        stream_result(json.dumps({**answer, "seq": 4}), expected=3)
    refused = {"seq": None, "ok": False, "status": 400, "error": {"code": "bad_stream_frame"}}
    assert stream_result(json.dumps(refused), errors="return", expected=3).status == 400  # type: ignore[union-attr]


def test_an_error_page_that_is_not_the_services_says_so():
    """Found in review: a URL that is some other web server answered a 404 HTML page, which
    the client raised as the error's message, 500 characters of markup and no word of
    what was wrong. It says the answer is not the service's, and how the body began."""
    page = "<!DOCTYPE HTML><html><head><title>Error response</title></head>" + "x" * 2000
    answer = httpx.Response(404, text=page, headers={"content-type": "text/html"})
    client = PlaceRecognitionClient(transport=_answers([answer], []))
    with client as pr, pytest.raises(NotFoundError) as e:
        pr.list_maps()
    said = str(e.value)
    assert "is the URL the place-recognition service's" in said and "text/html" in said
    assert "<!DOCTYPE HTML>" in said and len(said) < 600


def test_a_stream_closed_for_a_frame_too_large_names_the_servers_limit():
    """A scan frame past the server's socket cap (its body limit + 64 KiB) is closed with
    1009 by the websocket layer, before the service can answer 413. The error names the
    setting that bounds it (checked by hand against a real server: the reason websockets
    gives is "frame with N bytes exceeds limit of M bytes", M not the setting itself)."""
    from websockets.exceptions import ConnectionClosedError
    from websockets.frames import Close

    from overlapmamba.client._stream import stream_failure

    closed = Close(1009, "frame with 1357123 bytes exceeds limit of 165536 bytes")
    err = stream_failure(ConnectionClosedError(closed, None), [0, 1])
    assert isinstance(err, TransportError)
    assert "exceeds limit of 165536 bytes" in str(err) and "limits.max_body_bytes" in str(err)
    assert err.unanswered == [0, 1]  # type: ignore[attr-defined]
    other = stream_failure(ConnectionClosedError(Close(1013, "outran"), None), [])
    assert "max_body_bytes" not in str(other)
    # the client's own cap on an answer (closed by it first, echoed by the server) is not
    # the server's limit
    ours = Close(1009, "frame with 2000000 bytes exceeds limit of 1048576 bytes")
    echoed = stream_failure(ConnectionClosedError(ours, ours, rcvd_then_sent=False), [3])
    assert "max_body_bytes" not in str(echoed) and "1009" in str(echoed)
    theirs = ConnectionClosedError(closed, closed, rcvd_then_sent=True)
    assert "max_body_bytes" in str(stream_failure(theirs, [3]))
