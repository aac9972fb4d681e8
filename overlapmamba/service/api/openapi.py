"""OpenAPI fragments shared by routes that take a scan body (FastAPI cannot infer them)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import Query

from overlapmamba.service.schemas import SENSOR_PATTERN

SENSOR_HELP = (
    "the sensor the scan came from (GET /v1/sensors lists the known ones: vlp16, os1-64, "
    "hdl32, …); it decides how the scan is projected into the model's input. Default: the "
    "map's sensor, else the model's own. An unknown name is a 400 that lists the known ones"
)
# The `sensor` query parameter of every route that takes a scan.
SensorQuery = Annotated[str | None, Query(pattern=SENSOR_PATTERN, description=SENSOR_HELP)]
MOUNT_HELP = (
    "where the sensor sits: HEIGHT[,PITCH[,ROLL]] — metres above the ground, degrees of "
    "pitch (positive: looks down ahead) and roll (positive: left side raised), e.g. 0.7 for a "
    "delivery robot's roof or 1.8,5 for a backpack. The scan is levelled and moved to the "
    "height the model's sensor had (1.73 m, a car's roof) before it is projected, so a low or "
    "tilted sensor's scan lands where the map's does. Default: none (taken as it is)"
)
# The `mount` query parameter of every route that takes a scan (parsed by
# overlapmamba.service.bodies.parse_mount: a 400 that says what is allowed).
MountQuery = Annotated[str | None, Query(max_length=64, description=MOUNT_HELP)]

SCAN_BODY: dict[str, Any] = {
    "requestBody": {
        "required": True,
        "description": (
            "One LiDAR scan in the sensor frame. `application/octet-stream`: little-endian "
            "float32 records, layout from `X-Point-Fields` (`xyzi`, the KITTI .bin layout and "
            "the default, or `xyz`); `application/x-npy`: an (N, 3|4) float array; "
            "`application/x-pcd`: a PCD file (ascii, binary, binary_compressed); "
            "`application/x-ros2-pointcloud2`: a CDR-serialized ROS 2 "
            "`sensor_msgs/msg/PointCloud2`, the message bytes a ROS 2 node received (x/y/z "
            "float32 or float64, optional intensity, padding, organised or not, either byte "
            "order; NaN points of a cloud that is not dense are dropped). "
            "`Content-Encoding: gzip` or `zstd` may compress any of them."
        ),
        "content": {
            "application/octet-stream": {
                "schema": {"type": "string", "format": "binary"},
                "example": "<N×16 bytes: x y z intensity as float32>",
            },
            "application/x-npy": {"schema": {"type": "string", "format": "binary"}},
            "application/x-pcd": {"schema": {"type": "string", "format": "binary"}},
            "application/x-ros2-pointcloud2": {"schema": {"type": "string", "format": "binary"}},
        },
    },
    "parameters": [
        {
            "name": "X-Point-Fields",
            "in": "header",
            "required": False,
            "schema": {"type": "string", "enum": ["xyzi", "xyz"], "default": "xyzi"},
            "description": "record layout of an application/octet-stream body",
        },
        {
            "name": "Content-Encoding",
            "in": "header",
            "required": False,
            "schema": {"type": "string", "enum": ["identity", "gzip", "zstd"]},
        },
    ],
}


def error_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    meaning = {
        400: "malformed input: the message names the field and what is allowed",
        401: "missing or unknown API key",
        403: "the key's role does not allow this",
        404: "unknown map or keyframe",
        409: "keyframe id conflict, or map of another model",
        413: "body, decompressed body or point count too large",
        415: "content type or encoding not supported",
        422: "invalid values (non-finite points, wrong descriptor size, …)",
        503: "not ready, or the encoder queue is full (see Retry-After)",
        504: "the request ran past its timeout",
    }
    example = {
        "error": {"code": "map_not_found", "message": "map 'x' does not exist", "detail": {}}
    }
    return {
        c: {"description": meaning[c], "content": {"application/json": {"example": example}}}
        for c in codes
    }
