"""The robot's round trip over one WebSocket: the ``stream`` socket.

WebSocket protocol (``/v1/maps/{map_id}/stream?robot_id=&session_id=&k=&sensor=``):
each observation is two frames from the client —

1. a text frame, JSON: ``{"seq": any, "timestamp": float, "pose": "x,y,z,qx,qy,qz,qw" |
   [7 numbers] | null, "insert": "auto"|"always"|"never", "verify": bool, "content_type":
   "application/octet-stream"|"application/x-npy"|"application/x-pcd"|
   "application/x-ros2-pointcloud2", "fields":
   "xyzi"|"xyz", "encoding": "identity"|"gzip"|"zstd", "sensor": a known sensor}`` (all but
   ``timestamp`` optional; ``sensor`` defaults to the stream's ``sensor`` parameter, else the
   map's);
2. a binary frame: the scan bytes.

For each observation the server sends one text frame, in the order received:
``{"seq", "ok": true, ...the observe answer}`` or ``{"seq", "ok": false, "status": the HTTP
status the same error would have, "error": {...}}``.
A bad observation gets an error frame and the stream goes on; a metadata frame that does
not validate is answered under its ``seq`` (where it can be read), and the scan after it
is dropped unanswered, so each observation gets one answer. Backpressure: at most
``observe.stream_queue`` observations may wait; a client that sends more before reading
its results is closed with code 1013 (try again later) and a reason. Authentication uses
the same headers as HTTP (HTTP Basic excepted); a refused handshake is answered as a route
would be (status, JSON error, Retry-After), or closed with 1008 (1013 for a 503) where the
server cannot send a response in place of the upgrade. A metadata frame longer than
``META_FRAME_CHARS`` is answered with an error, unparsed, and a scan frame longer than
``limits.max_body_bytes`` with a 413 under its ``seq``, as HTTP refuses such a body.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import APIRouter, Query, WebSocket, WebSocketDisconnect
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from overlapmamba.core.errors import LidarCoreError
from overlapmamba.service.api.openapi import MountQuery, SensorQuery
from overlapmamba.service.api.queries import InsertMode, KQuery, observe_out
from overlapmamba.service.auth import Action, presented_key
from overlapmamba.service.bodies import parse_mount
from overlapmamba.service.deps import serving
from overlapmamba.service.domain import check_pose, parse_pose
from overlapmamba.service.errors import (
    BadRequest,
    PayloadTooLarge,
    ServiceError,
    error_body,
    lidar_status,
)
from overlapmamba.service.guard import error_response
from overlapmamba.service.origins import cross_origin, foreign_origin
from overlapmamba.service.places import Observation
from overlapmamba.service.scans import ScanBody
from overlapmamba.service.schemas import NAME_PATTERN, SENSOR_PATTERN

router = APIRouter(prefix="/v1/maps/{map_id}", tags=["queries"])
log = logging.getLogger("overlapmamba.service")


SEQ_DEPTH = 32  # a seq nested deeper is not echoed: a robot's seq is a number or a small record


def _finite(value: Any) -> bool:
    """Whether a JSON value holds no NaN or infinite number (``1e999`` parses as one) and is
    nested at most :data:`SEQ_DEPTH` deep, so that it can be echoed in an answer that stays
    JSON. Walked without recursion: a value nested 900 deep (the parser takes 1,000) ended
    the stream's receive loop with a RecursionError."""
    stack = [(value, 0)]
    while stack:
        v, depth = stack.pop()
        if depth > SEQ_DEPTH:
            return False
        if isinstance(v, float) and not math.isfinite(v):
            return False
        if isinstance(v, list | dict):
            stack.extend((x, depth + 1) for x in (v.values() if isinstance(v, dict) else v))
    return True


class StreamMeta(BaseModel):
    model_config = ConfigDict(extra="forbid")
    seq: Any = None
    timestamp: float = Field(allow_inf_nan=False)
    pose: str | list[float] | None = None
    insert: InsertMode = "auto"
    verify: bool = True
    content_type: str = "application/octet-stream"
    fields: str = "xyzi"
    encoding: str = "identity"
    sensor: str | None = Field(None, pattern=SENSOR_PATTERN)
    mount: str | None = Field(None, max_length=64)

    @field_validator("seq")
    @classmethod
    def _echoable(cls, value: Any) -> Any:
        if not _finite(value):
            raise ValueError(
                "seq holds a NaN or infinite number, or is nested deeper than "
                f"{SEQ_DEPTH} levels, which its answer could not echo as JSON; allowed: any "
                f"JSON value with finite numbers, at most {SEQ_DEPTH} levels deep"
            )
        return value


@dataclass(frozen=True)
class _Refused:
    """A metadata frame that did not validate, answered already under its ``seq``: the
    binary frame after it is its scan, dropped without a second answer."""

    seq: Any


def _seq_of(text: str) -> Any:
    """The ``seq`` of a metadata frame that did not validate, where it can be read (so the
    robot's answer carries it); None where the frame is not a JSON object."""
    try:
        frame = json.loads(text)
    except (ValueError, RecursionError):  # a frame nested past the parser's depth
        return None
    seq = frame.get("seq") if isinstance(frame, dict) else None
    return seq if _finite(seq) else None


# a metadata frame is a few hundred characters; it is parsed, and its seq echoed, on the
# event loop, so one of megabytes would hold every other request up meanwhile
META_FRAME_CHARS = 64 << 10


def _too_long(chars: int) -> str:
    return (
        f"metadata frame is {chars} characters; allowed: at most {META_FRAME_CHARS}: this "
        "observation was not made"
    )


def _bad(message: str) -> BadRequest:
    return BadRequest(message, code="bad_stream_frame")


def _over(size: int, max_body: int) -> PayloadTooLarge:
    """A scan frame past ``limits.max_body_bytes``: refused as an HTTP body that size is."""
    return PayloadTooLarge(
        f"scan frame is {size} bytes; allowed: at most {max_body}: this observation was not made",
        max_body_bytes=max_body,
    )


def _invalid(err: ValidationError) -> str:
    first = err.errors(include_url=False)[0]
    where = ".".join(str(p) for p in first["loc"])
    field = f" (field {where!r})" if where else ""
    return f"metadata frame is not valid{field}: {first['msg']}: this observation was not made"


async def refuse(websocket: WebSocket, err: ServiceError) -> None:
    """The handshake refused as an HTTP route answers (status, JSON error, Retry-After),
    where the server can send a response instead of the upgrade (uvicorn can: a close
    before the accept reached a client as a bare 403); else closed with 1013 (try again
    later) for a 503 and 1008 for the rest, the reason naming the code."""
    if "websocket.http.response" in websocket.scope.get("extensions", {}):
        denial = error_response(err.status, err.code, err.message, err.detail, err.headers)
        await websocket.send_denial_response(denial)
        return
    code = 1013 if err.status == 503 else 1008
    await websocket.close(code=code, reason=f"{err.code}: {err.message}"[:120])


@router.websocket("/stream")
async def stream(
    websocket: WebSocket,
    map_id: str,
    robot_id: Annotated[str, Query(pattern=NAME_PATTERN)],
    session_id: Annotated[str, Query(pattern=NAME_PATTERN)] = "default",
    k: KQuery = 10,
    sensor: SensorQuery = None,
    mount: MountQuery = None,
) -> None:
    """Observations over one WebSocket; see the module docstring for the frame format."""
    app = websocket.app
    try:
        svc = serving(app.state)
        auth, origin = svc.settings.auth, websocket.headers.get("origin")
        host = websocket.headers.get("host", "")
        if foreign_origin(origin, host, auth.allowed_origins, keyless=not auth.keys):
            raise cross_origin(str(origin))
        who = app.state.auth.identify(presented_key(websocket))  # type: ignore[arg-type]
        app.state.auth.authorize(who, Action.ENCODE, map_id)
        svc.sensors.check(sensor)
        svc.check_k(k)
        stream_mount = parse_mount(mount)
        m = await svc.open_map(map_id)
    except ServiceError as err:
        await refuse(websocket, err)
        return
    await websocket.accept()
    limit = svc.settings.observe.stream_queue
    max_body = svc.settings.limits.max_body_bytes
    queue: asyncio.Queue[tuple[Any, bytes | None, ServiceError | None] | None] = asyncio.Queue()

    async def process() -> None:
        nonlocal m
        while (item := await queue.get()) is not None:
            meta, scan, problem = item
            seq = meta.seq if isinstance(meta, StreamMeta) else meta
            try:
                if problem is not None:
                    raise problem
                assert isinstance(meta, StreamMeta) and scan is not None
                if meta.insert != "never":
                    app.state.auth.authorize(who, Action.INSERT, map_id)
                pose = (
                    check_pose(meta.pose) if isinstance(meta.pose, list) else parse_pose(meta.pose)
                )
                obs = Observation(
                    robot_id, session_id, meta.timestamp, pose, meta.insert, k, meta.verify
                )
                body = ScanBody(
                    scan,
                    meta.content_type,
                    meta.fields,
                    meta.encoding,
                    sensor=svc.sensors.check(meta.sensor) or sensor,
                    mount=parse_mount(meta.mount) if meta.mount is not None else stream_mount,
                )
                if m.retired:  # deleted since the stream opened: the map of that id now,
                    m = await svc.open_map(map_id)  # if it was made again (else 404)
                o = await svc.observe(m, body, obs)
                msg = {"seq": seq, "ok": True, **observe_out(o).model_dump(mode="json")}
            except ServiceError as err:
                msg = {"seq": seq, "ok": False, "status": err.status}
                msg |= error_body(err.code, err.message, err.detail)
            except LidarCoreError as err:
                msg = {"seq": seq, "ok": False, "status": lidar_status(err)}
                msg |= error_body(err.code, err.message, err.detail)
            except Exception as err:  # e.g. the store's disk full: answered, logged, go on
                log.exception(
                    "stream of map %s, robot %s: observation %r failed", map_id, robot_id, seq
                )
                message = f"internal error: {type(err).__name__}"
                msg = {"seq": seq, "ok": False, "status": 500}
                msg |= error_body("internal_error", message, None)
            await websocket.send_text(json.dumps(msg))

    worker = asyncio.create_task(process())
    pending: StreamMeta | _Refused | None = None
    try:
        while True:
            frame = await websocket.receive()
            if frame["type"] == "websocket.disconnect":
                break
            if worker.done():  # the sender failed (client gone)
                break
            items: list[tuple[Any, bytes | None, ServiceError | None]] = []
            if frame.get("text") is not None:
                if isinstance(pending, StreamMeta):  # its scan never came: answer its seq
                    problem = "metadata frame followed by another metadata frame, not its scan"
                    items.append(
                        (pending.seq, None, _bad(f"{problem}: this observation was not made"))
                    )
                text = frame["text"]
                if len(text) > META_FRAME_CHARS:  # parsed on the event loop: bounded first
                    items.append((None, None, _bad(_too_long(len(text)))))
                    pending = _Refused(None)  # its scan follows: answered already, dropped
                else:
                    try:
                        pending = StreamMeta.model_validate_json(text)
                    except ValidationError as err:
                        refused = _Refused(_seq_of(text))
                        items.append((refused.seq, None, _bad(_invalid(err))))
                        pending = refused  # its scan follows: answered already, dropped
            elif pending is None:
                items.append((None, None, _bad("binary frame without a metadata frame before it")))
            elif isinstance(pending, _Refused):
                pending = None
            else:
                data = frame.get("bytes") or b""
                if len(data) > max_body:  # as HTTP refuses it (the socket takes 64 KiB more)
                    items.append((pending.seq, None, _over(len(data), max_body)))
                else:
                    items.append((pending, data, None))
                pending = None
            if items and queue.qsize() + len(items) > limit:
                await websocket.close(
                    code=1013,
                    reason=f"client outran the server: {limit} observations pending",
                )
                break
            for item in items:
                queue.put_nowait(item)
    except WebSocketDisconnect:
        pass
    finally:
        queue.put_nowait(None)
        with contextlib.suppress(Exception):
            await asyncio.wait_for(worker, timeout=svc.settings.limits.request_timeout_s)
