"""``/v1/maps``: create, list, inspect, delete, snapshot; per-map stats and overview."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Body, Query, Response

from overlapmamba.service.api.openapi import error_responses
from overlapmamba.service.backends.base import check_same_settings, each_map
from overlapmamba.service.bodies import parse_mount
from overlapmamba.service.deps import CanReadMaps, CanView, CanWriteMaps, ServiceDep
from overlapmamba.service.schemas import MapList, MapOut, MapSettingsIn, SnapshotOut
from overlapmamba.service.threads import in_thread

router = APIRouter(prefix="/v1/maps", tags=["maps"])


@router.put(
    "/{map_id}",
    response_model=MapOut,
    responses={201: {"description": "created"}, **error_responses(400, 401, 403, 409, 413, 503)},
    summary="Create a map (idempotent)",
)
async def create_map(
    map_id: str,
    response: Response,
    svc: ServiceDep,
    _: CanWriteMaps,
    settings: MapSettingsIn | None = Body(None),  # noqa: B008
) -> MapOut:
    """Create the map, or return it unchanged if it exists with the same settings (200).
    Map ids: `[a-z0-9][a-z0-9_-]{0,63}`. While a map of that id is being deleted, the
    creation waits for the deletion to finish (503 `map_busy` if it takes over a minute)."""
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
