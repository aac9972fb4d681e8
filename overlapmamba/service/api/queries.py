"""Place queries and the robot's round trip: ``query``, ``observe``, and the ``stream`` socket.

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
the same headers as HTTP; a refused key closes the handshake with 1008.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
from dataclasses import dataclass
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Header, Query, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from overlapmamba.core.errors import LidarCoreError
from overlapmamba.core.renamed import REMOVED_IN
from overlapmamba.service.api.openapi import SCAN_BODY, MountQuery, SensorQuery, error_responses
from overlapmamba.service.auth import Action, presented_key
from overlapmamba.service.bodies import parse_mount, read_scan
from overlapmamba.service.deps import CanEncode, ServiceDep, serving
from overlapmamba.service.domain import POSE_FORMAT, Filters, check_pose, parse_pose
from overlapmamba.service.errors import (
    BadRequest,
    PayloadTooLarge,
    ServiceError,
    error_body,
    lidar_status,
)
from overlapmamba.service.places import Answer, Observation, Observed
from overlapmamba.service.scans import ScanBody, decompress
from overlapmamba.service.schemas import (
    NAME_PATTERN,
    SENSOR_PATTERN,
    DescriptorQueryIn,
    LoopClosureOut,
    MatchOut,
    ObserveOut,
    QueryOut,
    Timings,
)
from overlapmamba.service.threads import in_thread

router = APIRouter(prefix="/v1/maps/{map_id}", tags=["queries"])
log = logging.getLogger("overlapmamba.service")
ERRORS = error_responses(400, 401, 403, 404, 409, 413, 415, 422, 503, 504)
InsertMode = Literal["auto", "always", "never"]
# 1000 bounds every server; the server's own limit (limits.max_k, 100 by default) is checked
# before the scan is read, and on a stream before it is accepted
KQuery = Annotated[
    int, Query(ge=1, le=1000, description="matches to return, at most limits.max_k (100)")
]
VERIFY_HELP = (
    "register the first verify.candidates candidates against their keyframes' geometry (a "
    "relative pose and a verified loop closure); false: the descriptor alone, faster"
)

QUERY_BODY = {
    **SCAN_BODY,
    "requestBody": {
        **SCAN_BODY["requestBody"],
        "description": SCAN_BODY["requestBody"]["description"]
        + ' Or `application/json` `{"descriptor": [256 floats]}` to query by descriptor.',
        "content": {
            **SCAN_BODY["requestBody"]["content"],
            "application/json": {
                "schema": {"$ref": "#/components/schemas/DescriptorQueryIn"},
                "example": {"descriptor": [0.0625, "…256 values"]},
            },
        },
    },
}


@router.post(
    "/query",
    response_model=QueryOut,
    openapi_extra=QUERY_BODY,
    responses=ERRORS,
    summary="Top-k places for a scan or a descriptor",
)
async def query(
    map_id: str,
    request: Request,
    svc: ServiceDep,
    who: CanEncode,
    k: KQuery = 10,
    exclude_session: Annotated[str | None, Query(pattern=NAME_PATTERN)] = None,
    exclude_robot: Annotated[str | None, Query(pattern=NAME_PATTERN)] = None,
    exclude_recent_s: Annotated[
        float | None,
        Query(ge=0, allow_inf_nan=False, description="with session_id and timestamp"),
    ] = None,
    session_id: Annotated[
        str | None, Query(pattern=NAME_PATTERN, description="the querying session")
    ] = None,
    timestamp: Annotated[
        float | None, Query(allow_inf_nan=False, description="the query's time")
    ] = None,
    max_match_distance: Annotated[
        float | None,
        Query(
            ge=0,
            le=2,
            allow_inf_nan=False,
            description="leave out matches farther than this (descriptor L2)",
        ),
    ] = None,
    max_distance: Annotated[
        float | None,
        Query(
            ge=0,
            le=2,
            allow_inf_nan=False,
            deprecated=True,
            description="the old name of max_match_distance",
        ),
    ] = None,
    time_from: Annotated[float | None, Query(allow_inf_nan=False)] = None,
    time_to: Annotated[float | None, Query(allow_inf_nan=False)] = None,
    verify: Annotated[bool, Query(description=VERIFY_HELP)] = True,
    sensor: SensorQuery = None,
    mount: MountQuery = None,
    x_point_fields: Annotated[str | None, Header(include_in_schema=False)] = None,
) -> QueryOut:
    """Nearest keyframes by descriptor distance, best first, after the filters; for a scan
    query each match carries the relative yaw from the stored yaw features, and the top
    `verify.candidates` (5) are registered against their keyframe's geometry: `relative_pose` and
    `verification`, in order until one verifies (`verify.stop_at_first`). The loop closure is
    the verified candidate (of highest fitness when `verify.stop_at_first` is false); without
    verification, the top match when its distance is under the configured threshold (and
    the margin to the runner-up is large enough). k results come back whenever k eligible
    keyframes exist."""
    svc.sensors.check(sensor)
    svc.check_k(k)
    if max_distance is not None:
        max_match_distance = renamed_query_distance(max_match_distance, max_distance)
    m = await svc.open_map(map_id)
    filters = Filters(
        exclude_session=exclude_session,
        exclude_robot=exclude_robot,
        exclude_recent_s=exclude_recent_s,
        session_id=session_id,
        timestamp=timestamp,
        time_from=time_from,
        time_to=time_to,
        max_match_distance=max_match_distance,
    )
    scan = await read_scan(request, svc.settings.limits, x_point_fields, sensor, mount)
    probe: ScanBody | list[float] = scan
    if (scan.content_type or "").split(";")[0].strip().lower() == "application/json":
        probe = await in_thread(_descriptor_of, scan.data, scan.encoding)
    return query_out(await svc.query(m, probe, k, filters, verify=verify))


# a descriptor query's JSON: a few thousand numbers at most; a longer body would only build
# a list of millions before the descriptor's length is checked
DESCRIPTOR_QUERY_BYTES = 1 << 20


def _descriptor_of(data: bytes, encoding: str | None) -> list[float]:
    """The descriptor of a JSON query body, decoded and parsed (off the event loop)."""
    body = decompress(data, encoding, DESCRIPTOR_QUERY_BYTES)
    if len(body) > DESCRIPTOR_QUERY_BYTES:
        raise PayloadTooLarge(
            f"a descriptor query's JSON is {len(body)} bytes; allowed: at most "
            f"{DESCRIPTOR_QUERY_BYTES}",
            max_bytes=DESCRIPTOR_QUERY_BYTES,
        )
    try:
        return DescriptorQueryIn.model_validate_json(body).descriptor
    except ValidationError as err:
        raise BadRequest(
            'body is not {"descriptor": [numbers]}',
            code="bad_descriptor",
            errors=json.loads(err.json(include_url=False, include_input=False)),
        ) from None


@router.post(
    "/observe",
    response_model=ObserveOut,
    openapi_extra=SCAN_BODY,
    responses=ERRORS,
    summary="The robot's round trip: query, then maybe insert",
)
async def observe(
    map_id: str,
    request: Request,
    svc: ServiceDep,
    who: CanEncode,
    timestamp: Annotated[float, Query(allow_inf_nan=False)],
    robot_id: Annotated[str, Query(pattern=NAME_PATTERN)],
    session_id: Annotated[str, Query(pattern=NAME_PATTERN)] = "default",
    pose: Annotated[str | None, Query(description=POSE_FORMAT)] = None,
    insert: InsertMode = "auto",
    k: KQuery = 10,
    verify: Annotated[bool, Query(description=VERIFY_HELP)] = True,
    sensor: SensorQuery = None,
    mount: MountQuery = None,
    x_point_fields: Annotated[str | None, Header(include_in_schema=False)] = None,
) -> ObserveOut:
    """Query the map excluding this session's own recent keyframes, then insert the scan as
    a keyframe when due (`auto`: the robot moved `observe.insert_min_distance_m` or
    `observe.insert_min_interval_s` passed since its last keyframe). The keyframe id is
    `robot:session:timestamp`, so a retried observation is not inserted twice."""
    if insert != "never":
        request.app.state.auth.authorize(who, Action.INSERT, map_id)
    svc.sensors.check(sensor)
    svc.check_k(k)
    m = await svc.open_map(map_id)
    obs = Observation(robot_id, session_id, timestamp, parse_pose(pose), insert, k, verify)
    scan = await read_scan(request, svc.settings.limits, x_point_fields, sensor, mount)
    return observe_out(await svc.observe(m, scan, obs))


def renamed_query_distance(new: float | None, old: float) -> float:
    """``max_distance``, the query filter's old name: still taken until it goes (logged once
    a process); both at once is a 400."""
    if new is not None:
        raise BadRequest(
            "give max_match_distance only; max_distance is its old name (deprecated)",
            code="conflicting_parameters",
        )
    if not _WARNED:
        _WARNED.add("max_distance")
        log.warning(
            "query parameter max_distance is deprecated and goes in %s: use max_match_distance",
            REMOVED_IN,
        )
    return old


_WARNED: set[str] = set()


def query_out(a: Answer) -> QueryOut:
    lc = a.loop_closure
    return QueryOut(
        matches=[MatchOut(**x.public()) for x in a.matches],
        loop_closure=LoopClosureOut(
            accepted=lc.accepted,
            threshold=lc.threshold,
            rule=lc.rule,
            margin_top1_top2=lc.margin,
            keyframe_id=lc.keyframe_id,
            verified=lc.verified,
            relative_pose=None
            if lc.relative_pose is None
            else [float(x) for x in lc.relative_pose.reshape(-1)],
            fitness=lc.fitness,
        ),
        timings_ms=Timings(**a.timings),
    )


def observe_out(o: Observed) -> ObserveOut:
    return ObserveOut(
        **dict(query_out(o)),
        inserted=o.inserted,
        keyframe_id=o.keyframe_id,
        insert_reason=o.reason,
    )


def _finite(value: Any) -> bool:
    """Whether a JSON value holds no NaN or infinite number (``1e999`` parses as one), so
    that it can be echoed in an answer that stays JSON."""
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, list):
        return all(_finite(v) for v in value)
    if isinstance(value, dict):
        return all(_finite(v) for v in value.values())
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
                "seq holds a NaN or infinite number, which its answer could not echo as "
                "JSON; allowed: any JSON value with finite numbers"
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


def _invalid(err: ValidationError) -> str:
    first = err.errors(include_url=False)[0]
    where = ".".join(str(p) for p in first["loc"])
    field = f" (field {where!r})" if where else ""
    return f"metadata frame is not valid{field}: {first['msg']}: this observation was not made"


async def _refuse(websocket: WebSocket, err: ServiceError) -> None:
    """The handshake refused as an HTTP route answers (status, JSON error, Retry-After),
    where the server can send a response instead of the upgrade (uvicorn can: a close
    before the accept reached a client as a bare 403); else closed with 1013 (try again
    later) for a 503 and 1008 for the rest, the reason naming the code."""
    if "websocket.http.response" in websocket.scope.get("extensions", {}):
        body = error_body(err.code, err.message, err.detail)
        await websocket.send_denial_response(
            JSONResponse(body, status_code=err.status, headers=err.headers)
        )
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
        who = app.state.auth.identify(presented_key(websocket))  # type: ignore[arg-type]
        app.state.auth.authorize(who, Action.ENCODE)
        svc.sensors.check(sensor)
        svc.check_k(k)
        stream_mount = parse_mount(mount)
        m = await svc.open_map(map_id)
    except ServiceError as err:
        await _refuse(websocket, err)
        return
    await websocket.accept()
    limit = svc.settings.observe.stream_queue
    queue: asyncio.Queue[tuple[Any, bytes | None, str | None] | None] = asyncio.Queue()

    async def process() -> None:
        nonlocal m
        while (item := await queue.get()) is not None:
            meta, scan, problem = item
            seq = meta.seq if isinstance(meta, StreamMeta) else meta
            try:
                if problem is not None:
                    raise BadRequest(problem, code="bad_stream_frame")
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
            items: list[tuple[Any, bytes | None, str | None]] = []
            if frame.get("text") is not None:
                if isinstance(pending, StreamMeta):  # its scan never came: answer its seq
                    problem = "metadata frame followed by another metadata frame, not its scan"
                    items.append((pending.seq, None, f"{problem}: this observation was not made"))
                text = frame["text"]
                if len(text) > META_FRAME_CHARS:  # parsed on the event loop: bounded first
                    items.append((None, None, _too_long(len(text))))
                    pending = _Refused(None)  # its scan follows: answered already, dropped
                else:
                    try:
                        pending = StreamMeta.model_validate_json(text)
                    except ValidationError as err:
                        refused = _Refused(_seq_of(text))
                        items.append((refused.seq, None, _invalid(err)))
                        pending = refused  # its scan follows: answered already, dropped
            elif pending is None:
                items.append((None, None, "binary frame without a metadata frame before it"))
            elif isinstance(pending, _Refused):
                pending = None
            else:
                items.append((pending, frame.get("bytes") or b"", None))
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
