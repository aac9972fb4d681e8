"""``/v1/maps``: create, list, inspect, delete, snapshot; per-map stats and overview."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Query, Request, Response

from overlapmamba.service.api.openapi import error_responses
from overlapmamba.service.backends.base import check_same_settings, each_map
from overlapmamba.service.bodies import parse_json, parse_mount, read_body
from overlapmamba.service.deps import CanReadMaps, CanView, CanWriteMaps, ServiceDep
from overlapmamba.service.schemas import MapList, MapOut, MapSettingsIn, SnapshotOut
from overlapmamba.service.settings import LimitSettings
from overlapmamba.service.threads import in_thread

router = APIRouter(prefix="/v1/maps", tags=["maps"])


# a map's settings are a few fields: a longer body is refused before it is parsed
SETTINGS_BODY_BYTES = 64 << 10


@router.put(
    "/{map_id}",
    response_model=MapOut,
    responses={
        201: {"description": "created"},
        **error_responses(400, 401, 403, 409, 413, 422, 503),
    },
    summary="Create a map (idempotent)",
    openapi_extra={
        "requestBody": {
            "required": False,
            "content": {
                "application/json": {"schema": {"$ref": "#/components/schemas/MapSettingsIn"}}
            },
        }
    },
)
async def create_map(
    map_id: str, request: Request, response: Response, svc: ServiceDep, _: CanWriteMaps
) -> MapOut:
    """Create the map, or return it unchanged if it exists with the same settings (200).
    Map ids: `[a-z0-9][a-z0-9_-]{0,63}`. While a map of that id is being deleted, the
    creation waits for the deletion to finish (503 `map_busy` if it takes over a minute).
    The body (optional) is read only after the key is checked, and at most 64 KiB of it."""
    settings = await _map_settings(request, svc.settings.limits)
    wanted = settings.sensor if settings else None
    sensor = svc.sensors.declared(wanted)  # the model's own is stored as None
    mount = parse_mount(settings.mount if settings else None)
    m, created = await in_thread(
        svc.registry.create,
        map_id,
        settings.index if settings else None,
        settings.keep_geometry if settings else None,
        sensor,
        mount,
    )
    if wanted is not None and sensor is None and m.sensor is not None:  # the backend saw None
        check_same_settings(m, None, wanted)
    response.status_code = 201 if created else 200
    return MapOut(**await in_thread(m.info), created=created)


@router.get("", response_model=MapList, responses=error_responses(401, 403), summary="List maps")
async def list_maps(svc: ServiceDep, _: CanReadMaps) -> MapList:
    infos = await in_thread(lambda: each_map(svc.registry, lambda m: m.info()))
    return MapList(maps=[MapOut(**i) for i in infos.values()])


@router.get(
    "/{map_id}",
    response_model=MapOut,
    responses=error_responses(400, 401, 403, 404),
    summary="A map's info and counts",
)
async def get_map(map_id: str, svc: ServiceDep, _: CanReadMaps) -> MapOut:
    m = await svc.map(map_id)
    return MapOut(**await in_thread(m.info))


@router.delete(
    "/{map_id}",
    status_code=204,
    responses=error_responses(400, 401, 403, 404),
    summary="Delete a map and everything in it",
)
async def delete_map(map_id: str, svc: ServiceDep, _: CanWriteMaps) -> Response:
    await in_thread(svc.registry.delete, map_id)
    svc.forget_map(map_id)
    return Response(status_code=204)


@router.post(
    "/{map_id}/snapshot",
    response_model=SnapshotOut,
    responses=error_responses(400, 401, 403, 404),
    summary="Write the map's index snapshot now",
)
async def snapshot(map_id: str, svc: ServiceDep, _: CanWriteMaps) -> SnapshotOut:
    """Atomically writes the FAISS index and the store sequence number it reflects; a
    restart then replays only later writes. The store itself is always durable."""
    m = await svc.map(map_id)
    return SnapshotOut(**await in_thread(m.snapshot))


@router.get(
    "/{map_id}/stats",
    responses=error_responses(400, 401, 403, 404),
    summary="Recognition statistics of one map",
)
async def map_stats(map_id: str, svc: ServiceDep, _: CanView) -> dict[str, Any]:
    m = await svc.map(map_id)
    return {**svc.stats.public(map_id), "map": await in_thread(m.info)}


@router.get(
    "/{map_id}/overview",
    responses=error_responses(400, 401, 403, 404),
    summary="A bird's-eye picture of a map: keyframes, robot tracks, loop-closure edges",
)
async def map_overview(
    map_id: str,
    svc: ServiceDep,
    _: CanView,
    limit: int = Query(5000, ge=1, le=100_000, description="keyframes drawn, latest first"),
) -> dict[str, Any]:
    """`keyframes`: {robot: [[x, y], …]} of the latest `limit` keyframes with a pose;
    `tracks`: {robot: [[x, y], …]}, the latest 300 observed positions of each robot;
    `closures`: [{robot_id, from: [x, y], to: [x, y], keyframe_id, verified}], the latest
    1,000 accepted loop closures whose two ends have poses (verified: null when decided by
    the descriptor alone). Tracks and closures are this process's traffic since it started."""
    m = await svc.map(map_id)
    positions = await in_thread(m.positions, limit)
    return svc.overview.public(map_id, positions)


async def _map_settings(request: Request, limits: LimitSettings) -> MapSettingsIn | None:
    """The PUT's settings, or None for an empty body."""
    small = limits.model_copy(
        update={
            "max_body_bytes": min(limits.max_body_bytes, SETTINGS_BODY_BYTES),
            "max_decoded_bytes": min(limits.max_decoded_bytes, SETTINGS_BODY_BYTES),
        }
    )
    body = await read_body(request, small)
    if not body.strip() or body.strip() == b"null":  # none, as JSON's null says too
        return None
    return parse_json(body, MapSettingsIn, "map settings")
