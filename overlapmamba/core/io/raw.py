"""Raw little-endian float32 records: KITTI ``.bin`` files and the service's binary bodies."""

from __future__ import annotations

import numpy as np

from overlapmamba.core.errors import DecodeError
from overlapmamba.core.points import DEFAULT_LIMITS, PointCloud, PointLimits, validate

# layout name -> number of float32 values per point
FIELD_LAYOUTS: dict[str, int] = {"xyz": 3, "xyzi": 4}


def decode_raw(
    data: bytes | bytearray | memoryview,
    fields: str = "xyzi",
    *,
    limits: PointLimits = DEFAULT_LIMITS,
    source: str = "scan",
) -> PointCloud:
    """Decode ``len(data) / (4·C)`` records of C little-endian float32 values.

    The count is checked against ``limits`` from the byte length alone, before any copy.
    """
    if fields not in FIELD_LAYOUTS:
        raise DecodeError(
            f"unknown point field layout {fields!r}; allowed: {', '.join(FIELD_LAYOUTS)}",
            allowed=list(FIELD_LAYOUTS),
        )
    record = 4 * FIELD_LAYOUTS[fields]
    view = memoryview(data)
    if not view.c_contiguous:
        raise DecodeError(f"{source}: the point buffer must be contiguous")
    nbytes = view.nbytes
    if nbytes % record:
        raise DecodeError(
            f"{source} is {nbytes} bytes, not a multiple of the {record}-byte {fields} record "
            f"(float32 ×{FIELD_LAYOUTS[fields]}); the body is truncated or the layout is wrong",
            bytes=nbytes,
            record_bytes=record,
        )
    limits.check_count(nbytes // record, source=source)
    arr = np.frombuffer(data, dtype="<f4").reshape(-1, FIELD_LAYOUTS[fields])
    return validate(arr, limits=limits, source=source)
