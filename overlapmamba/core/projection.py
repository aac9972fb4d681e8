"""Spherical range projection (paper eq. 4, OverlapNet's convention).

    u = floor(0.5 · (1 − atan2(y, x)/π) · W)                    column, clamped to [0, W−1]
    v = floor((1 − (asin(z/r) + |fov_down|)/fov) · H)           row, clamped to [0, H−1]

Points are kept where ``min_range < r < max_range``. When several points fall into one
pixel the nearest wins. Pixels without a point hold ``profile.empty_value``.

Arithmetic is float32, like the reference implementation, so pixel boundaries fall where
they fall there. Column 0 looks backwards (azimuth ±180°); the columns sweep clockwise seen
from above, so rotating a scan by +k·360°/W about z rolls the image by −k columns.

:func:`project_reference` is the slow, obvious version kept beside the fast one for tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from overlapmamba.core.points import PointCloud
from overlapmamba.core.sensors import SensorProfile

_PI = np.float32(np.pi)


@dataclass(frozen=True)
class PixelCoordinates:
    """Where each kept point lands.

    keep:  (N,) bool   points inside (min_range, max_range)
    row:   (K,) int32  v of each kept point, K = keep.sum()
    col:   (K,) int32  u of each kept point
    depth: (K,) float32 range r in metres
    azimuth_column: (K,) float32 u before the floor (sub-column views shift it:
                    :mod:`overlapmamba.core.views`)
    x, y:  (K,) float32 the kept points' coordinates (aligned columns take their bearing)
    """

    keep: np.ndarray
    row: np.ndarray
    col: np.ndarray
    depth: np.ndarray
    azimuth_column: np.ndarray
    x: np.ndarray
    y: np.ndarray


def _xyz(points: PointCloud | np.ndarray) -> np.ndarray:
    xyz = points.xyz if isinstance(points, PointCloud) else np.asarray(points)
    if xyz.ndim != 2 or xyz.shape[1] < 3:
        raise ValueError(f"points must have shape (N, 3) or (N, 4); got {xyz.shape}")
    return xyz[:, :3].astype(np.float32, copy=False)


def pixel_coordinates(points: PointCloud | np.ndarray, profile: SensorProfile) -> PixelCoordinates:
    """Row/column/depth of every point in range. Vectorised numpy, float32."""
    xyz = _xyz(points)
    # Strided column views: a transposing copy costs more than it saves (measured).
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    depth = np.sqrt(x * x + y * y + z * z)
    keep = (depth > np.float32(profile.min_range)) & (depth < np.float32(profile.max_range))
    if not keep.all():
        x, y, z, depth = x[keep], y[keep], z[keep], depth[keep]
    fov_up = np.float32(np.deg2rad(profile.fov_up_deg))
    fov_down = np.float32(np.deg2rad(profile.fov_down_deg))
    fov = fov_up - fov_down
    H, W = profile.height, profile.width
    # Same operation order as the reference so that floor() agrees at pixel boundaries.
    u = np.float32(0.5) * (-np.arctan2(y, x) / _PI + np.float32(1.0)) * np.float32(W)
    v = (np.float32(1.0) - (np.arcsin(z / depth) - fov_down) / fov) * np.float32(H)
    col = np.clip(np.floor(u), 0, W - 1).astype(np.int32)
    row = np.clip(np.floor(v), 0, H - 1).astype(np.int32)
    return PixelCoordinates(keep=keep, row=row, col=col, depth=depth, azimuth_column=u, x=x, y=y)


def pixel_index(xyz: np.ndarray, profile: SensorProfile) -> tuple[np.ndarray, np.ndarray]:
    """Flat pixel (row · W + col, intp) and depth (float32) of every point of (3, N)
    float32 coordinates, out-of-range points sent to the extra pixel H · W: the placements
    of :func:`pixel_coordinates` with the same float32 operations in the same order, in
    place and without dropping points (the overlap tables' hot loop)."""
    x, y, z = xyz
    H, W = profile.height, profile.width
    depth = x * x
    depth += y * y
    depth += z * z
    np.sqrt(depth, out=depth)
    out = depth <= np.float32(profile.min_range)
    out |= depth >= np.float32(profile.max_range)
    fov_down = np.float32(np.deg2rad(profile.fov_down_deg))
    fov = np.float32(np.deg2rad(profile.fov_up_deg)) - fov_down
    u = np.arctan2(y, x)
    u /= -_PI
    u += np.float32(1.0)
    u *= np.float32(0.5)
    u *= np.float32(W)
    v = np.divide(z, depth)
    np.arcsin(v, out=v)
    v -= fov_down
    v /= fov
    np.subtract(np.float32(1.0), v, out=v)
    v *= np.float32(H)
    # Truncation toward zero, then the clamp: floor() then the clamp for every value.
    pix = np.clip(v.astype(np.intp), 0, H - 1)
    pix *= W
    pix += np.clip(u.astype(np.intp), 0, W - 1)
    pix[out] = H * W
    return pix, depth


def project(points: PointCloud | np.ndarray, profile: SensorProfile) -> np.ndarray:
    """Range image (H, W) float32; the nearest point wins each pixel."""
    image, _ = _project(points, profile, with_index=False)
    return image


def project_with_index(
    points: PointCloud | np.ndarray, profile: SensorProfile
) -> tuple[np.ndarray, np.ndarray]:
    """Range image (H, W) float32 and, per pixel, the index of the winning point in the
    input (int64, −1 where empty). Ties at equal depth go to the lowest index."""
    image, index = _project(points, profile, with_index=True)
    assert index is not None
    return image, index


def _project(
    points: PointCloud | np.ndarray, profile: SensorProfile, *, with_index: bool
) -> tuple[np.ndarray, np.ndarray | None]:
    pc = pixel_coordinates(points, profile)
    if not with_index:
        return rasterize(pc.row, pc.col, pc.depth, profile), None
    H, W = profile.height, profile.width
    pix = pc.row.astype(np.int64) * W + pc.col
    best = _nearest(pix, pc.depth, H * W)
    winners = np.flatnonzero(pc.depth == best[pix])  # may include equal-depth ties
    kept_idx = np.flatnonzero(pc.keep)[winners]
    flat_index = np.full(H * W, -1, dtype=np.int64)
    # Reversed so that, on exact ties, the lowest input index is written last and wins.
    flat_index[pix[winners][::-1]] = kept_idx[::-1]
    best[np.isinf(best)] = np.float32(profile.empty_value)
    return best.reshape(H, W), flat_index.reshape(H, W)


def _nearest(pix: np.ndarray, depth: np.ndarray, size: int) -> np.ndarray:
    """Per flat pixel the smallest depth, +inf where none. Nearest-wins without a sort:
    ufunc.at applies min unbuffered, so duplicates are safe."""
    best = np.full(size, np.inf, dtype=np.float32)
    np.minimum.at(best, pix, depth)
    return best


def rasterize(
    row: np.ndarray, col: np.ndarray, depth: np.ndarray, profile: SensorProfile
) -> np.ndarray:
    """Range image (H, W) float32 of points already placed at (row, col): the nearest wins
    each pixel, empty pixels hold ``profile.empty_value``."""
    H, W = profile.height, profile.width
    best = _nearest(row.astype(np.int64) * W + col, depth, H * W)
    best[np.isinf(best)] = np.float32(profile.empty_value)
    return best.reshape(H, W)


def project_reference(points: PointCloud | np.ndarray, profile: SensorProfile) -> np.ndarray:
    """Slow, obvious per-point loop with the same float32 arithmetic. For tests only."""
    xyz = _xyz(points)
    H, W = profile.height, profile.width
    image = np.full((H, W), np.float32(profile.empty_value), dtype=np.float32)
    filled = np.zeros((H, W), dtype=bool)
    fov_up = np.float32(np.deg2rad(profile.fov_up_deg))
    fov_down = np.float32(np.deg2rad(profile.fov_down_deg))
    fov = fov_up - fov_down
    for x, y, z in xyz:
        r = np.sqrt(x * x + y * y + z * z)
        if not (np.float32(profile.min_range) < r < np.float32(profile.max_range)):
            continue
        u = np.float32(0.5) * (-np.arctan2(y, x) / _PI + np.float32(1.0)) * np.float32(W)
        v = (np.float32(1.0) - (np.arcsin(z / r) - fov_down) / fov) * np.float32(H)
        col = min(max(int(np.floor(u)), 0), W - 1)
        row = min(max(int(np.floor(v)), 0), H - 1)
        if not filled[row, col] or r < image[row, col]:
            image[row, col] = r
            filled[row, col] = True
    return image


def valid_mask(image: np.ndarray, profile: SensorProfile) -> np.ndarray:
    """Pixels that hold a return."""
    return image != np.float32(profile.empty_value)
