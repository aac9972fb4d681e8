"""The observe stream over one WebSocket, shared by both clients: its URL, an observation's
two frames, a result frame, a deadline on a send, and the socket's failures as the
library's errors."""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import json
import socket
import threading
from collections.abc import Iterable
from typing import Any
from urllib.parse import quote

import httpx

from overlapmamba.client._base import NAME, Timeouts, _m, _pose, check_mount
from overlapmamba.client._exceptions import (
    APIError,
    ClientError,
    ConnectError,
    ResponseError,
    Timeout,
    TransportError,
    error_for,
)
from overlapmamba.client._models import Observation, ObserveResult
from overlapmamba.client._scans import encode


def ws_url(base_url: str, map_id: str, **params: Any) -> str:
    """The stream's URL; its ids and ``k`` checked first, as the server checks them (a
    refused handshake reads as a bare 403 where the server cannot answer it as a route)."""
    for name in ("robot_id", "session_id"):
        value = params.get(name)
        if value is not None and not NAME.fullmatch(str(value)):
            raise ValueError(
                f"{name} {value!r} is not allowed; allowed: a letter or digit, then up to 99 "
                "letters, digits and _.@-"
            )
    k = params.get("k")
    if k is not None and (isinstance(k, bool) or not isinstance(k, int) or k < 1):
        raise ValueError(f"k={k!r}; allowed: a whole number from 1 (the server's limits.max_k)")
    url = httpx.URL(base_url)
    scheme = "wss" if url.scheme == "https" else "ws"
    query = "&".join(f"{k}={quote(str(v), safe='')}" for k, v in params.items() if v is not None)
    path = url.path.rstrip("/") + f"/v1/maps/{_m(map_id)}/stream"
    return f"{scheme}://{url.netloc.decode()}{path}?{query}"


def observation_frames(obs: Observation, seq: Any, compress: bool) -> tuple[str, bytes]:
    """The two WebSocket frames of one observation at place ``seq`` in its stream (see the
    service's stream protocol); its ``sensor`` and ``mount`` are sent when they are not the
    stream's."""
    body, headers = encode(obs.scan, compress=compress)
    meta = {
        "seq": seq,
        "timestamp": float(obs.timestamp),
        "pose": _pose(obs.pose),
        "insert": obs.insert,
        "verify": obs.verify,
        "content_type": headers["content-type"],
        "fields": headers["x-point-fields"],
        "encoding": headers.get("content-encoding", "identity"),
    }
    if obs.sensor is not None:
        meta["sensor"] = obs.sensor
    if obs.mount is not None:
        meta["mount"] = check_mount(obs.mount)
    return json.dumps(meta), body


_NETWORK_ERRNOS = {errno.ENETUNREACH, errno.EHOSTUNREACH, errno.ETIMEDOUT, errno.ENETDOWN}


def stream_failure(err: Exception, unanswered: Iterable[int]) -> ClientError | None:
    """A stream's socket failure → the library's error (ConnectError, Timeout or
    TransportError) naming the observations, by their place in the stream, that were sent
    and never answered (``unanswered`` on the error too); None for any other error."""
    from websockets.exceptions import ConnectionClosed, InvalidHandshake

    left = list(unanswered)
    lost = f"; observations {left} were sent and not answered" if left else ""
    out: ClientError
    if isinstance(err, ConnectionClosed):
        got = err.rcvd
        why = f"{got.code} {got.reason}".strip() if got is not None else "no close frame"
        server_first = err.sent is None or bool(err.rcvd_then_sent)  # (not its echo of ours)
        if got is not None and got.code == 1009 and server_first:  # its socket's own cap
            why += ": a frame past what the server takes; its limits.max_body_bytes bounds a scan"
        out = TransportError(f"the stream closed ({why}){lost}")
    elif isinstance(err, InvalidHandshake):
        out = ConnectError(f"the server refused the stream: {_refusal(err)}{lost}")
    elif isinstance(err, TimeoutError):
        out = Timeout(f"{str(err) or 'no answer in time'} on the stream{lost}")
    elif isinstance(err, (ConnectionError, socket.gaierror, socket.herror)) or (
        isinstance(err, OSError) and err.errno in _NETWORK_ERRNOS
    ):  # not any OSError: a drive's missing scan file is the caller's own error
        never = isinstance(err, ConnectionRefusedError | socket.gaierror | socket.herror)
        what = "cannot connect the stream" if never else "the stream's connection failed"
        out = ConnectError(f"{what}: {err}{lost}")
    else:
        return None
    out.unanswered = left  # type: ignore[attr-defined]
    return out


def _refusal(err: Exception) -> str:
    """A refused handshake as the server said it: its status and JSON error (code and
    message), as an HTTP route's answer reads, where it sent one."""
    response = getattr(err, "response", None)
    status = getattr(response, "status_code", None)
    try:
        error = json.loads(getattr(response, "body", b"") or b"")["error"]
        return f"{status} {error['code']}: {error['message']}"
    except (ValueError, KeyError, TypeError):
        return str(err)


def send_timeout(seconds: float) -> TimeoutError:
    """What a stream raises when an observation could not be sent within ``seconds``
    (``timeout.write``): a link gone half-open fills the socket's buffers and would hold the
    send until TCP gives up, many minutes later."""
    return TimeoutError(f"an observation could not be sent within {seconds:g} s (timeout.write)")


def close_within(timeouts: Timeouts) -> float:
    """How long closing a stream waits for the server's close frame: websockets' own 10 s,
    or less where ``timeout.write`` is shorter."""
    return min(10.0, timeouts.write)


def check_errors(errors: str) -> str:
    """A stream's ``errors``: "raise" a refused observation's APIError, or "return" it."""
    if errors not in ("raise", "return"):
        raise ValueError(f"errors must be 'raise' or 'return'; got {errors!r}")
    return errors


def check_window(window: int) -> int:
    """A stream's ``window``: how many observations may be in flight, at least 1."""
    if isinstance(window, bool) or not isinstance(window, int) or window < 1:
        raise ValueError(
            f"window must be a whole number ≥ 1 (observations in flight); got {window!r}"
        )
    return window


def stream_result(
    text: str | bytes, errors: str = "raise", retried: bool = False, expected: Any = None
) -> ObserveResult | APIError:
    """One result frame of the stream → its result; a refused observation's APIError is
    raised, or returned with ``errors="return"``. A frame that is not this API's raises
    :class:`ResponseError`. ``retried``: the observation was sent again (``retry``).
    ``expected``: the ``seq`` due (the oldest observation unanswered); an answer under
    another is a :class:`ResponseError`, never matched to the wrong scan (a SLAM back end
    would add its loop closure to another pose). A refusal of a frame whose seq could not
    be read (null) is taken as the one due."""
    try:
        d = json.loads(text)
        if not isinstance(d, dict):
            raise TypeError(f"a JSON {type(d).__name__}, not an object")
        if expected is not None and d.get("seq") not in (expected, None):
            raise ResponseError(
                f"the stream answered seq {d.get('seq')!r} where {expected!r} was due: an "
                "answer out of order cannot be matched to its scan (a proxy that reorders "
                "frames, or not this API's stream)"
            )
        if d.get("ok"):
            result = ObserveResult.from_json(d)
            return dataclasses.replace(result, retried=True) if retried else result
        e = d.get("error", {})
        status = int(d.get("status") or 400)  # that error's HTTP status (servers before: none)
        code, message = e.get("code", "stream_error"), e.get("message", "")
    except (ValueError, KeyError, TypeError, AttributeError) as bad:
        head = text[:200] if isinstance(text, str) else text[:200].decode("utf-8", "replace")
        raise ResponseError(
            f"a stream frame that is not this API's result ({type(bad).__name__}: {bad}); "
            f"expected the service's JSON result frame. The frame began: {head!r}"
        ) from bad
    err = error_for(status)(status, code, message, e.get("detail"))
    err.detail.setdefault("seq", d.get("seq"))
    if errors == "raise":
        raise err
    return err


def send_within(ws: Any, frames: Iterable[str | bytes], seconds: float) -> None:
    """Send one observation's ``frames`` on a websockets sync connection, or raise
    ``TimeoutError`` when they are not sent within ``seconds``: its send has no deadline of
    its own, and a half-open link (the server's machine gone) fills the socket's buffers and
    holds it until TCP gives up. At the deadline the socket is shut down, which ends the
    send; the stream is over. A send that finished first is never cut."""
    lock = threading.Lock()
    state = {"done": False, "late": False}

    def abort() -> None:
        with lock:  # the send's end and the deadline decide once, in one order
            if state["done"]:
                return
            state["late"] = True
        with contextlib.suppress(OSError):
            ws.socket.shutdown(socket.SHUT_RDWR)

    timer = threading.Timer(seconds, abort)
    timer.daemon = True
    timer.start()
    try:
        for frame in frames:
            ws.send(frame)
    except Exception:
        if state["late"]:
            raise send_timeout(seconds) from None
        raise
    finally:
        with lock:
            state["done"] = True
        timer.cancel()
    if state["late"]:  # shut down as the last frame went out: the stream cannot go on
        raise send_timeout(seconds)
