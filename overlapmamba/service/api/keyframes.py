"""``/v1/maps/{map_id}/keyframes``: insert (scan or precomputed batch), get, delete."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Header, Query, Request, Response

from overlapmamba.service.api.openapi import SCAN_BODY, MountQuery, SensorQuery, error_responses
from overlapmamba.service.auth import Action
from overlapmamba.service.bodies import parse_json, read_body, read_scan
from overlapmamba.service.deps import CanInsert, CanReadMaps, CanWriteMaps, ServiceDep
from overlapmamba.service.domain import POSE_FORMAT, parse_pose
from overlapmamba.service.errors import NotFound, PayloadTooLarge
from overlapmamba.service.places import Observation
from overlapmamba.service.schemas import (
    KEYFRAME_ID_PATTERN,
    NAME_PATTERN,
    KeyframeBatchIn,
    KeyframeBatchOut,
    KeyframeOut,
)
from overlapmamba.service.threads import in_thread

router = APIRouter(prefix="/v1/maps/{map_id}", tags=["keyframes"])


def _out(kf: object, created: bool | None = None) -> KeyframeOut:
    return KeyframeOut(**kf.public(), created=created)  # type: ignore[attr-defined]


@router.post(
    "/keyframes",
    response_model=KeyframeOut,
    openapi_extra=SCAN_BODY,
    responses={
        201: {"description": "inserted"},
        **error_responses(400, 401, 403, 404, 409, 413, 415, 422, 503),
    },
    summary="Insert one keyframe from a scan",
)
async def insert_keyframe(
    map_id: str,
    request: Request,
    response: Response,
    svc: ServiceDep,
    who: CanInsert,
    keyframe_id: Annotated[str, Query(pattern=KEYFRAME_ID_PATTERN)],
    timestamp: Annotated[float, Query(allow_inf_nan=False, description="seconds")],
    robot_id: Annotated[str, Query(pattern=NAME_PATTERN)] = "unknown",
    session_id: Annotated[str, Query(pattern=NAME_PATTERN)] = "default",
    pose: Annotated[str | None, Query(description=POSE_FORMAT)] = None,
    sensor: SensorQuery = None,
    mount: MountQuery = None,
    x_point_fields: Annotated[str | None, Header(include_in_schema=False)] = None,
) -> KeyframeOut:
    """Encode the scan and store it as a keyframe: descriptor, yaw features, metadata.
    Idempotent on `keyframe_id`: the same id with the same scan and metadata returns the
    stored keyframe (200, `created: false`); with anything different, 409."""
    request.app.state.auth.authorize(who, Action.INSERT, map_id)
    svc.sensors.check(sensor)
    m = await svc.open_map(map_id)
    obs = Observation(robot_id, session_id, timestamp, parse_pose(pose))
    scan = await read_scan(request, svc.settings.limits, x_point_fields, sensor, mount)
    result = (await svc.insert_scan(m, scan, keyframe_id, obs)).result
    response.status_code = 201 if result.created else 200
    return _out(result.keyframe, result.created)


@router.post(
    "/keyframes:batch",
    response_model=KeyframeBatchOut,
    responses=error_responses(400, 401, 403, 404, 409, 413, 422),
    summary="Insert precomputed descriptors (offline map building)",
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {
                "application/json": {"schema": {"$ref": "#/components/schemas/KeyframeBatchIn"}}
            },
        }
    },
)
async def insert_batch(
    map_id: str, request: Request, svc: ServiceDep, _: CanWriteMaps
) -> KeyframeBatchOut:
    """All or nothing (faiss backend: one transaction; qdrant: checked whole first, then
    written in chunks, so a concurrent conflicting insert from another replica can refuse
    the batch after part of it landed; retrying the batch completes it). The batch's
    `model_id` must be the map's model; known keyframe ids with identical content are
    reported as existing, with other content the whole batch is refused (409). The body is
    read only after the key is checked, and parsed off the event loop."""
    m = await svc.open_map(map_id)
    body = await read_body(request, svc.settings.limits)
    batch = await in_thread(_parse_batch, body, svc.settings.limits.max_batch_keyframes)
    results = await svc.insert_descriptors(m, batch.model_id, batch.keyframes)
    inserted = sum(r.created for r in results)
    return KeyframeBatchOut(
        inserted=inserted,
        existing=len(results) - inserted,
        keyframes=[_out(r.keyframe, r.created) for r in results],
    )


def _parse_batch(body: bytes, limit: int) -> KeyframeBatchIn:
    batch = parse_json(body, KeyframeBatchIn, "keyframe batch")
    if len(batch.keyframes) > limit:
        raise PayloadTooLarge(
            f"batch has {len(batch.keyframes)} keyframes; allowed: at most {limit}",
            max_batch_keyframes=limit,
        )
    return batch


@router.get(
    "/keyframes/{keyframe_id}",
    response_model=KeyframeOut,
    responses=error_responses(400, 401, 403, 404),
    summary="One keyframe's metadata",
)
async def get_keyframe(
    map_id: str, keyframe_id: str, svc: ServiceDep, _: CanReadMaps
) -> KeyframeOut:
    m = await svc.map(map_id)
    kf = await in_thread(m.get, keyframe_id)
    if kf is None:
        raise NotFound(f"map {map_id!r} has no keyframe {keyframe_id!r}", code="keyframe_not_found")
    return _out(kf)


@router.delete(
    "/keyframes/{keyframe_id}",
    status_code=204,
    responses=error_responses(400, 401, 403, 404),
    summary="Delete one keyframe",
)
async def delete_keyframe(
    map_id: str, keyframe_id: str, svc: ServiceDep, _: CanWriteMaps
) -> Response:
    await svc.delete_keyframe(await svc.map(map_id), keyframe_id)
    return Response(status_code=204)
