"""``/v1/descriptors``: scan → descriptor, one scan or a length-prefixed batch; ``/v1/sensors``:
the sensors scans may come from."""

from __future__ import annotations

import asyncio
import struct
from typing import Annotated

from fastapi import APIRouter, Header, Request

from overlapmamba.service.api.openapi import SCAN_BODY, MountQuery, SensorQuery, error_responses
from overlapmamba.service.bodies import parse_mount, read_body, read_scan
from overlapmamba.service.deps import CanEncode, ServiceDep
from overlapmamba.service.errors import BadRequest, PayloadTooLarge, UnsupportedMediaType
from overlapmamba.service.scans import SCAN_TYPES, ScanBody
from overlapmamba.service.schemas import (
    DescriptorBatchOut,
    DescriptorOut,
    SensorList,
    SensorOut,
    Timings,
)

router = APIRouter(prefix="/v1", tags=["descriptors"])
BATCH_TYPE = "application/x-scan-batch"
ERRORS = error_responses(400, 401, 403, 413, 415, 422, 503, 504)


@router.post(
    "/descriptors",
    response_model=DescriptorOut,
    openapi_extra=SCAN_BODY,
    responses=ERRORS,
    summary="Describe one scan",
)
async def describe(
    request: Request,
    svc: ServiceDep,
    _: CanEncode,
    sensor: SensorQuery = None,
    mount: MountQuery = None,
    x_point_fields: Annotated[str | None, Header(include_in_schema=False)] = None,
) -> DescriptorOut:
    """The 256-d place descriptor of one scan, with per-stage timings."""
    svc.sensors.check(sensor)
    d = await svc.describe(
        await read_scan(request, svc.settings.limits, x_point_fields, sensor, mount)
    )
    return DescriptorOut(
        descriptor=d.descriptor.tolist(), model_id=svc.model_id, timings_ms=Timings(**d.timings)
    )


@router.get(
    "/sensors",
    response_model=SensorList,
    responses=error_responses(401, 403),
    summary="The sensors scans may come from",
)
async def sensors(svc: ServiceDep, _: CanEncode) -> SensorList:
    """Every sensor a scan's `sensor` parameter (or a map's) may name: the catalogue and the
    operator's own, each with its beam table, the manual its figures come from, and how its
    scans enter this model."""
    s = svc.sensors
    return SensorList(
        model_sensor=s.model_sensor.name,
        sensors=[
            SensorOut(
                name=name,
                title=s.known[name].title,
                beams=s.known[name].beams,
                elevations_deg=list(s.known[name].elevations_deg),
                columns=s.known[name].columns,
                min_range=s.known[name].min_range,
                max_range=s.known[name].max_range,
                source=s.known[name].source,
                projection=s.input(name).kind,
                descriptor_map=getattr(svc.encoder.meta.sensor_maps.get(name), "how", None),
            )
            for name in s.names()
        ],
    )


def split_batch(body: bytes, max_scans: int) -> list[bytes]:
    """Records of ``uint32 little-endian length`` + that many bytes, back to back."""
    out: list[bytes] = []
    pos = 0
    while pos < len(body):
        if pos + 4 > len(body):
            raise BadRequest(f"scan batch is truncated at byte {pos}: a 4-byte length is cut off")
        (n,) = struct.unpack_from("<I", body, pos)
        pos += 4
        if pos + n > len(body):
            raise BadRequest(
                f"scan {len(out)} declares {n} bytes but only {len(body) - pos} remain: "
                "the batch is truncated"
            )
        out.append(body[pos : pos + n])
        pos += n
        if len(out) > max_scans:
            raise PayloadTooLarge(
                f"scan batch has more than {max_scans} scans", max_batch_scans=max_scans
            )
    if not out:
        raise BadRequest("scan batch is empty; allowed: 1 or more length-prefixed scans")
    return out


@router.post(
    "/descriptors:batch",
    response_model=DescriptorBatchOut,
    responses=ERRORS,
    summary="Describe several scans in one request",
    openapi_extra={
        "requestBody": {
            "required": True,
            "description": (
                f"Content-Type `{BATCH_TYPE}; format=<scan type>` where the scan type is one "
                "of application/octet-stream (default), application/x-npy, application/x-pcd, "
                "application/x-ros2-pointcloud2. "
                "The body is the scans back to back, each as a little-endian uint32 byte "
                "length followed by that many bytes. X-Point-Fields and Content-Encoding "
                "apply as for one scan (the encoding to the whole body)."
            ),
            "content": {BATCH_TYPE: {"schema": {"type": "string", "format": "binary"}}},
        }
    },
)
async def describe_batch(
    request: Request,
    svc: ServiceDep,
    _: CanEncode,
    sensor: SensorQuery = None,
    mount: MountQuery = None,
    x_point_fields: Annotated[str | None, Header(include_in_schema=False)] = None,
) -> DescriptorBatchOut:
    """Descriptors of several scans of one sensor, in order. The scans share the encoder's
    micro-batches."""
    svc.sensors.check(sensor)
    declared = parse_mount(mount)
    ctype = request.headers.get("content-type", "")
    media, _sep, params = ctype.partition(";")
    if media.strip().lower() != BATCH_TYPE:
        raise UnsupportedMediaType(
            f"content type {media.strip() or '(none)'!r} is not a scan batch; allowed: "
            f"{BATCH_TYPE}; format=<{' | '.join(SCAN_TYPES)}>",
            allowed=[BATCH_TYPE],
        )
    fmt = "application/octet-stream"
    for p in params.split(";"):
        key, _eq, value = p.strip().partition("=")
        if key.lower() == "format" and value:
            fmt = value.strip().strip('"')
    body = await read_body(request, svc.settings.limits)
    scans = split_batch(body, svc.settings.limits.max_batch_scans)
    # In waves of one encoder batch a lane, so one big request cannot fill the shared queue.
    step = svc.settings.batching.max_batch * svc.pipeline.batcher.lanes
    results = []
    for start in range(0, len(scans), step):
        results += await asyncio.gather(
            *(
                svc.describe(
                    ScanBody(
                        s,
                        fmt,
                        x_point_fields,
                        source=f"scan {start + i}",
                        sensor=sensor,
                        mount=declared,
                    )
                )
                for i, s in enumerate(scans[start : start + step])
            )
        )
    return DescriptorBatchOut(
        descriptors=[d.descriptor.tolist() for d in results],
        model_id=svc.model_id,
        timings_ms=[Timings(**d.timings) for d in results],
    )
