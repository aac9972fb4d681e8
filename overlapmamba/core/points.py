"""The point-cloud value type and the one place where scans are validated.

Every decoder in :mod:`overlapmamba.core.io` ends in :func:`validate`, so a file, an HTTP body and a
numpy array handed over in-process all pass the same checks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from overlapmamba.core.errors import NonFiniteError, PointCloudError, PointCountError

DEFAULT_MAX_POINTS = 2_000_000
DEFAULT_MAX_BYTES = 256 << 20


class PointLimits(BaseModel):
    """Allowed point counts. The service makes these configurable; decoders check
    ``max_points`` from a header or a byte length *before* allocating the points."""

    model_config = ConfigDict(frozen=True)

    min_points: int = Field(default=1, ge=1)
    max_points: int = Field(default=DEFAULT_MAX_POINTS, ge=1)
    # the most bytes a decoder may build from a body (a compressed PCD's data, inflated)
    max_bytes: int = Field(default=DEFAULT_MAX_BYTES, ge=1)

    @model_validator(mode="after")
    def _ordered(self) -> PointLimits:
        if self.min_points > self.max_points:
            raise ValueError(
                f"min_points ({self.min_points}) exceeds max_points ({self.max_points})"
            )
        return self

    def check_count(self, n: int, *, source: str = "scan") -> None:
        if not self.min_points <= n <= self.max_points:
            raise PointCountError(
                f"{source} has {n} points; allowed: {self.min_points} to {self.max_points}",
                points=n,
                min_points=self.min_points,
                max_points=self.max_points,
            )


DEFAULT_LIMITS = PointLimits()

# A KITTI-layout row (x, y, z, intensity float32) as two opaque fields: numpy copies a 12-byte
# field of a 16-byte row as one item, where slicing [:, :3] copies float by float (on KITTI
# 00 scans about 3 × faster, the values bit for bit the same: benchmarks/projection.py, decode)
_XYZI = np.dtype([("xyz", "V12"), ("i", "V4")])


def split_xyzi(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 4) float32, C-contiguous → C-contiguous copies of xyz (N, 3) and intensity (N,)."""
    n = rows.shape[0]
    rec = rows.view(_XYZI).reshape(n)
    xyz, intensity = np.empty(n, "V12"), np.empty(n, "V4")
    xyz[:] = rec["xyz"]
    intensity[:] = rec["i"]
    return xyz.view(np.float32).reshape(n, 3), intensity.view(np.float32)


@dataclass(frozen=True, eq=False)
class PointCloud:
    """One LiDAR scan in the sensor frame.

    xyz:       (N, 3) float32, C-contiguous, metres
    intensity: (N,) float32, or None when the source carried none
    ring:      (N,) int64 beam index as the driver numbered it (a PointCloud2's ``ring``
               field), or None: only ever checked against a named sensor, never used to
               guess one
    """

    xyz: np.ndarray
    intensity: np.ndarray | None = None
    ring: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    @property
    def has_intensity(self) -> bool:
        return self.intensity is not None

    def as_xyzi(self) -> np.ndarray:
        """(N, 4) float32 in KITTI ``.bin`` layout; missing intensity becomes 0."""
        n = len(self)
        out = np.empty((n, 4), dtype=np.float32)
        rec = out.view(_XYZI).reshape(n)
        rec["xyz"] = np.ascontiguousarray(self.xyz, dtype=np.float32).view("V12").reshape(n)
        if self.intensity is None:
            out[:, 3] = 0.0
        else:
            rec["i"] = np.ascontiguousarray(self.intensity, dtype=np.float32).view("V4")
        return out


def xyz_of(points: PointCloud | np.ndarray) -> np.ndarray:
    """(N, 3) coordinates of a cloud, or of an (N, ≥3) array's first three columns."""
    xyz = points.xyz if isinstance(points, PointCloud) else np.asarray(points)
    if xyz.ndim != 2 or xyz.shape[1] < 3:
        raise ValueError(f"points must have shape (N, 3) or (N, 4); got {xyz.shape}")
    return xyz[:, :3]


def validate(
    xyz: np.ndarray,
    intensity: np.ndarray | None = None,
    *,
    limits: PointLimits = DEFAULT_LIMITS,
    source: str = "scan",
) -> PointCloud:
    """Check shape, dtype, count and finiteness; return a float32 :class:`PointCloud`.

    Accepts xyz of shape (N, 3) or (N, 4) — the 4th column is taken as intensity — in any
    real floating dtype. Raises a :class:`~overlapmamba.core.errors.PointCloudError` subclass naming
    what was wrong and what is allowed.
    """
    xyz = np.asarray(xyz)
    if xyz.dtype.kind != "f":
        raise PointCloudError(
            f"{source} has dtype {xyz.dtype}; allowed: float32 or float64",
            dtype=str(xyz.dtype),
        )
    if xyz.ndim != 2 or xyz.shape[1] not in (3, 4):
        raise PointCloudError(
            f"{source} has shape {xyz.shape}; allowed: (N, 3) or (N, 4)", shape=list(xyz.shape)
        )
    if xyz.shape[1] == 4 and intensity is not None:
        raise PointCloudError(f"{source}: intensity given twice (4th column and argument)")
    limits.check_count(int(xyz.shape[0]), source=source)
    if xyz.shape[1] == 4:
        if xyz.dtype == np.float32 and xyz.flags.c_contiguous:  # a KITTI .bin, a raw body
            xyz, intensity = split_xyzi(xyz)
        else:
            intensity = xyz[:, 3]
            xyz = xyz[:, :3]
    with np.errstate(over="ignore"):
        xyz = np.ascontiguousarray(xyz, dtype=np.float32)
    # Check after the cast: float64 values beyond float32's range become inf here.
    if not np.isfinite(xyz).all():
        bad = int((~np.isfinite(xyz).all(axis=1)).sum())
        raise NonFiniteError(
            f"{source} has {bad} points with NaN or infinite coordinates; "
            "allowed: finite values within float32 range",
            bad_points=bad,
        )
    if intensity is not None:
        intensity = np.asarray(intensity)
        if intensity.shape != (xyz.shape[0],):
            raise PointCloudError(
                f"{source}: intensity has shape {intensity.shape}; expected ({xyz.shape[0]},)"
            )
        with np.errstate(over="ignore"):
            intensity = np.ascontiguousarray(intensity, dtype=np.float32)
        if not np.isfinite(intensity).all():
            bad = int((~np.isfinite(intensity)).sum())
            raise NonFiniteError(
                f"{source} has {bad} NaN or infinite intensities; allowed: finite values",
                bad_points=bad,
            )
    return PointCloud(xyz=xyz, intensity=intensity)
