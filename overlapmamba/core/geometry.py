"""A keyframe's compact geometry: what a loop-closure check registers a query scan against.

A scan of 120k points is ≈ 2 MB; a map keeps one small copy per keyframe instead:

1. **Voxel grid** (``voxel`` metres, default 2.0): one point per occupied voxel, the mean of
   the points in it. Registration works on such a grid anyway (GICP's covariances come from
   neighbourhoods of this size), so little is lost: ≈ 1,300 points for a KITTI scan, 8 KB.
2. **Cap** (``max_points``, default 8,192): a larger grid keeps an evenly spread subset (the
   voxels in a fixed pseudo-random order, so the same scan always gives the same bytes).
3. **Quantised** to int16 centimetres in the sensor frame: ±327.67 m, 1 cm steps (under half
   a centimetre of error, well below what registration resolves). Points farther away are
   dropped.

:func:`encode_geometry` makes the grid here (numpy: one sort of the points' voxel keys);
:func:`pack_geometry` takes a grid already made — the service keeps the grid its
registration prepared for the scan anyway (``overlapmamba.service.registration.keyframe_geometry``).

Format, little-endian: ``b"OMG1"``, the voxel size (float32), the point count (uint32), then
count × 3 int16 (x, y, z in cm). At the cap that is 12 + 49,152 bytes: under the 64 KB a
keyframe may spend on geometry.
"""

from __future__ import annotations

import struct

import numpy as np

MAGIC = b"OMG1"
_HEADER = struct.Struct("<4sfI")
SCALE = 100.0  # int16 units per metre
LIMIT_M = np.iinfo(np.int16).max / SCALE  # 327.67 m


class GeometryError(ValueError):
    """A geometry blob that cannot be read (the message says what is wrong)."""


def voxel_means(xyz: np.ndarray, voxel: float) -> np.ndarray:
    """(N, 3) points → (M, 3) float64: the mean of the points in each occupied voxel, in the
    order of the voxels' keys. Voxel indices are packed into one int64 (21 bits per axis:
    ±1M voxels, ±1,000 km at 1 m), so the grouping is one sort of N integers."""
    pts = np.asarray(xyz, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f"points must be (N, 3) or wider; got {pts.shape}")
    pts = pts[:, :3]
    pts = pts[np.isfinite(pts).all(axis=1)]
    idx = np.floor(pts / voxel).astype(np.int64) + (1 << 20)
    inside = ((idx >= 0) & (idx < (1 << 21))).all(axis=1)
    pts, idx = pts[inside], idx[inside]
    if not len(pts):
        return np.empty((0, 3))
    keys = (idx[:, 0] << 42) | (idx[:, 1] << 21) | idx[:, 2]
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    sums = np.stack([np.bincount(inverse, weights=pts[:, a]) for a in range(3)], axis=1)
    return sums / counts[:, None]


def encode_geometry(xyz: np.ndarray, *, voxel: float = 2.0, max_points: int = 8192) -> bytes:
    """Points in the sensor frame → the compact blob (see the module notes)."""
    if not 0.05 <= voxel <= 10.0:
        raise ValueError(f"voxel {voxel} m is out of range; allowed: 0.05 to 10 m")
    return pack_geometry(voxel_means(xyz, voxel), voxel=voxel, max_points=max_points)


def pack_geometry(grid: np.ndarray, *, voxel: float, max_points: int = 8192) -> bytes:
    """Grid points already made (one per voxel, e.g. a registration library's voxel grid)
    → the blob: capped, quantised, with its header."""
    if max_points < 1:
        raise ValueError(f"max_points must be ≥ 1; got {max_points}")
    means = np.asarray(grid, dtype=np.float64)[:, :3]
    means = means[np.isfinite(means).all(axis=1) & (np.abs(means) < LIMIT_M).all(axis=1)]
    if len(means) > max_points:
        order = np.random.default_rng(len(means)).permutation(len(means))
        means = means[np.sort(order[:max_points])]
    q = np.round(means * SCALE).astype("<i2")
    return _HEADER.pack(MAGIC, voxel, len(q)) + q.tobytes()


def decode_geometry(blob: bytes) -> tuple[np.ndarray, float]:
    """The blob → (points (N, 3) float64 in metres, voxel size)."""
    if len(blob) < _HEADER.size:
        raise GeometryError(f"geometry blob of {len(blob)} bytes is shorter than its header")
    magic, voxel, n = _HEADER.unpack_from(blob)
    if magic != MAGIC:
        raise GeometryError(f"geometry blob starts with {magic!r}, not {MAGIC!r}")
    want = _HEADER.size + 6 * n
    if len(blob) != want:
        raise GeometryError(f"geometry blob of {len(blob)} bytes; {n} points need {want}")
    q = np.frombuffer(blob, dtype="<i2", offset=_HEADER.size).reshape(n, 3)
    return q.astype(np.float64) / SCALE, float(voxel)
