"""Point-cloud codecs: bytes or files in, validated :class:`~overlapmamba.core.points.PointCloud`
out.

read_points(path)                   .bin (KITTI), .npy, .pcd — chosen by suffix
decode(data, fmt, fields=...)       the same formats from bytes, for the HTTP service, and
                                    ``pointcloud2``: a CDR-serialized ROS 2 PointCloud2
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from overlapmamba.core.errors import DecodeError
from overlapmamba.core.io.npy import decode_npy
from overlapmamba.core.io.pcd import decode_pcd
from overlapmamba.core.io.pointcloud2 import decode_pointcloud2
from overlapmamba.core.io.raw import FIELD_LAYOUTS, decode_raw
from overlapmamba.core.points import DEFAULT_LIMITS, PointCloud, PointLimits

Format = Literal["raw", "npy", "pcd", "pointcloud2"]
FORMATS: tuple[str, ...] = ("raw", "npy", "pcd", "pointcloud2")
SUFFIX_FORMATS: dict[str, Format] = {".bin": "raw", ".npy": "npy", ".pcd": "pcd"}

__all__ = [
    "FIELD_LAYOUTS",
    "FORMATS",
    "SUFFIX_FORMATS",
    "decode",
    "decode_npy",
    "decode_pcd",
    "decode_pointcloud2",
    "decode_raw",
    "format_for_path",
    "read_points",
]


def decode(
    data: bytes | bytearray | memoryview,
    fmt: str,
    *,
    fields: str = "xyzi",
    limits: PointLimits = DEFAULT_LIMITS,
    source: str = "scan",
) -> PointCloud:
    """Decode a scan held in memory. ``fields`` applies to ``raw`` only."""
    if fmt == "raw":
        return decode_raw(data, fields, limits=limits, source=source)
    if fmt == "npy":
        return decode_npy(data, limits=limits, source=source)
    if fmt == "pcd":
        return decode_pcd(data, limits=limits, source=source)
    if fmt == "pointcloud2":
        return decode_pointcloud2(data, limits=limits, source=source)
    raise DecodeError(
        f"unknown point-cloud format {fmt!r}; allowed: {', '.join(FORMATS)}", allowed=FORMATS
    )


def format_for_path(path: str | Path) -> Format:
    suffix = Path(path).suffix.lower()
    if suffix not in SUFFIX_FORMATS:
        raise DecodeError(
            f"cannot tell the format of {Path(path).name!r}; allowed suffixes: "
            f"{', '.join(SUFFIX_FORMATS)}",
            allowed=list(SUFFIX_FORMATS),
        )
    return SUFFIX_FORMATS[suffix]


def read_points(
    path: str | Path, *, fields: str = "xyzi", limits: PointLimits = DEFAULT_LIMITS
) -> PointCloud:
    """Read a scan file. KITTI ``.bin`` files are raw little-endian float32 ``xyzi``."""
    path = Path(path)
    fmt = format_for_path(path)
    try:
        data = path.read_bytes()
    except OSError as err:
        raise DecodeError(f"cannot read {path}: {err.strerror}", path=str(path)) from err
    return decode(data, fmt, fields=fields, limits=limits, source=path.name)
