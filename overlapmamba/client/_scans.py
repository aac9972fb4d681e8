"""Scans → request bodies: float32 little-endian records, optionally zstd-compressed.

A scan is an (N, 3) or (N, 4) array (x, y, z[, intensity]) or a path to a ``.bin`` (KITTI),
``.npy`` or ``.pcd`` file, read with the shared codecs (``overlapmamba.core.io``), so the client
checks a file exactly as the service would before sending it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Union

import numpy as np
import zstandard

from overlapmamba.core.io import read_xyzi

Scan = Union[np.ndarray, str, Path]  # noqa: UP007 — the public alias reads better this way


def to_array(scan: Scan) -> np.ndarray:
    if isinstance(scan, str | Path):
        return read_xyzi(scan)
    arr = np.asarray(scan)
    if arr.ndim != 2 or arr.shape[1] not in (3, 4):
        raise ValueError(f"a scan array must have shape (N, 3) or (N, 4); got {arr.shape}")
    if arr.dtype.kind != "f":
        raise ValueError(f"a scan array must be floating point; got {arr.dtype}")
    return arr


def encode(scan: Scan, *, compress: bool = False) -> tuple[bytes, dict[str, str]]:
    """(body, headers) for one scan."""
    arr = to_array(scan)
    fields = "xyzi" if arr.shape[1] == 4 else "xyz"
    body = np.ascontiguousarray(arr, dtype="<f4").tobytes()
    headers = {"content-type": "application/octet-stream", "x-point-fields": fields}
    if compress:
        body = zstandard.ZstdCompressor(level=3).compress(body)
        headers["content-encoding"] = "zstd"
    return body, headers
