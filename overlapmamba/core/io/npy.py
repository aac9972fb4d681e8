"""NumPy ``.npy`` scans: (N, 3) or (N, 4), float32 or float64, never pickles.

The header is parsed first, so an absurd declared shape is refused before any allocation.
"""

from __future__ import annotations

import io

import numpy as np

from overlapmamba.core.errors import DecodeError
from overlapmamba.core.points import DEFAULT_LIMITS, PointCloud, PointLimits, validate


def decode_npy(
    data: bytes | bytearray | memoryview,
    *,
    limits: PointLimits = DEFAULT_LIMITS,
    source: str = "scan",
) -> PointCloud:
    buf = io.BytesIO(data)
    try:
        version = np.lib.format.read_magic(buf)
        if version not in ((1, 0), (2, 0)):
            raise DecodeError(f"{source}: .npy format version {version}; allowed: 1.0, 2.0")
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(buf)
        else:
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(buf)
    except DecodeError:
        raise
    except Exception as err:  # numpy raises ValueError/SyntaxError/... on junk headers
        raise DecodeError(f"{source} is not a valid .npy file: {err}") from err
    if dtype.hasobject or dtype.kind != "f" or dtype.itemsize not in (4, 8):
        raise DecodeError(
            f"{source} has dtype {dtype}; allowed: float32 or float64 (no object arrays)",
            dtype=str(dtype),
        )
    if len(shape) != 2 or shape[1] not in (3, 4) or any(type(d) is not int for d in shape):
        raise DecodeError(
            f"{source} has shape {shape}; allowed: (N, 3) or (N, 4)", shape=list(shape)
        )
    limits.check_count(int(shape[0]), source=source)
    body = memoryview(data)[buf.tell() :]
    expected = int(shape[0]) * int(shape[1]) * dtype.itemsize
    if len(body) != expected:
        raise DecodeError(
            f"{source} declares {shape} {dtype} ({expected} bytes) but holds {len(body)} bytes",
            expected_bytes=expected,
            actual_bytes=len(body),
        )
    arr = np.frombuffer(body, dtype=dtype)
    arr = arr.reshape(shape, order="F" if fortran else "C")
    return validate(arr, limits=limits, source=source)
