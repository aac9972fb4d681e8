"""Point-cloud codecs: bytes or files in, validated :class:`~overlapmamba.core.points.PointCloud`
out.

read_points(path)                   .bin (KITTI), .npy, .pcd — chosen by suffix
decode(data, fmt, fields=...)       the same formats from bytes, for the HTTP service, and
                                    ``pointcloud2``: a CDR-serialized ROS 2 PointCloud2
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np

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
    "read_xyzi",
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


def read_xyzi(path: str | Path, *, limits: PointLimits = DEFAULT_LIMITS) -> np.ndarray:
    """A scan file as (N, 4) float32 ``xyzi`` (missing intensity 0), the layout a service
    takes, checked as :func:`read_points` checks it. A KITTI ``.bin`` already is that layout:
    it is checked in one pass over the file's own buffer and returned without a copy (a
    replayed drive reads a scan an observation; split into a cloud and joined again it cost
    several passes over every point). Whatever that pass finds wrong, :func:`read_points`
    reads the file again and names."""
    path = Path(path)
    if format_for_path(path) == "raw":
        try:
            data = path.read_bytes()
        except OSError as err:
            raise DecodeError(f"cannot read {path}: {err.strerror}", path=str(path)) from err
        record = 4 * FIELD_LAYOUTS["xyzi"]
        n = len(data) // record
        if len(data) % record == 0 and limits.min_points <= n <= limits.max_points:
            arr = np.frombuffer(data, dtype="<f4").reshape(n, 4)
            if np.isfinite(arr).all():
                return arr
    return read_points(path, limits=limits).as_xyzi()
