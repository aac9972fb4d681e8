"""Place queries and the robot's round trip over HTTP: ``query`` and ``observe`` (the same
round trip over a WebSocket: :mod:`overlapmamba.service.api.stream`)."""

from __future__ import annotations

import json
import logging
from typing import Annotated, Literal

from fastapi import APIRouter, Header, Query, Request
from pydantic import ValidationError

from overlapmamba.core.renamed import REMOVED_IN
from overlapmamba.service.api.openapi import SCAN_BODY, MountQuery, SensorQuery, error_responses
from overlapmamba.service.auth import Action
from overlapmamba.service.bodies import read_scan
from overlapmamba.service.deps import CanEncode, ServiceDep
from overlapmamba.service.domain import POSE_FORMAT, Filters, parse_pose
from overlapmamba.service.errors import (
    BadRequest,
    PayloadTooLarge,
)
from overlapmamba.service.places import Answer, Observation, Observed
from overlapmamba.service.scans import ScanBody, decompress
from overlapmamba.service.schemas import (
    NAME_PATTERN,
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
    robot_id: Annotated[
        str | None,
        Query(
            pattern=NAME_PATTERN,
            description="the querying session's robot: exclude_recent_s leaves out that "
            "robot's session only (without it, every robot's session of that name)",
        ),
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
        robot_id=robot_id,
        timestamp=timestamp,
        time_from=time_from,
        time_to=time_to,
        max_match_distance=max_match_distance,
    )
    scan = await read_scan(request, svc.settings.limits, x_point_fields, sensor, mount)
    probe: ScanBody | list[float] = scan
    if (scan.content_type or "").split(";")[0].strip().lower() == "application/json":
        cap = min(DESCRIPTOR_QUERY_BYTES, svc.settings.limits.max_decoded_bytes)
        probe = await in_thread(_descriptor_of, scan.data, scan.encoding, cap)
    return query_out(await svc.query(m, probe, k, filters, verify=verify))


# a descriptor query's JSON: a few thousand numbers at most; a longer body would only build
# a list of millions before the descriptor's length is checked
DESCRIPTOR_QUERY_BYTES = 1 << 20


def _descriptor_of(data: bytes, encoding: str | None, cap: int) -> list[float]:
    """The descriptor of a JSON query body of at most ``cap`` bytes decoded, decoded and
    parsed (off the event loop)."""
    body = decompress(data, encoding, cap)
    if len(body) > cap:
        raise PayloadTooLarge(
            f"a descriptor query's JSON is {len(body)} bytes; allowed: at most {cap}",
            max_bytes=cap,
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
            covariance=None
            if lc.covariance is None
            else [float(x) for x in lc.covariance.reshape(-1)],
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
