"""Projection profiles: everything the range projection needs to know about a range image.

A profile is the single source of projection parameters. Training caches range images with
it, the exported ONNX model stores it in its metadata, and the service reads it back from
there, so scans are never projected differently in training and in serving.

A profile describes an image (rows, columns, a linear vertical field of view); the physical
sensors a fleet carries, with their beam tables, are :mod:`overlapmamba.core.sensors.catalogue`, and
each has a profile of its own (:meth:`~overlapmamba.core.sensors.catalogue.Sensor.profile`), which
:func:`~overlapmamba.core.sensors.catalogue.get_profile` also answers by the sensor's name.
"""

from __future__ import annotations

import math
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from overlapmamba.core.errors import ProfileError


class SensorProfile(BaseModel):
    """Projection parameters of one sensor (paper eq. 4).

    Angles are degrees, ranges metres. Points are kept where ``min_range < r < max_range``;
    pixels that receive no point hold ``empty_value``.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = Field(min_length=1, max_length=64)
    fov_up_deg: float = Field(ge=-90.0, le=90.0, description="upper edge of the vertical FOV")
    fov_down_deg: float = Field(ge=-90.0, le=90.0, description="lower edge of the vertical FOV")
    height: int = Field(gt=0, le=1024, description="rows of the range image (beams)")
    width: int = Field(gt=0, le=8192, description="columns of the range image (azimuth bins)")
    max_range: float = Field(gt=0.0, le=1000.0, description="points at or beyond are dropped")
    min_range: float = Field(default=0.0, ge=0.0, description="points at or below are dropped")
    empty_value: float = Field(default=-1.0, description="value of pixels with no return")

    @model_validator(mode="after")
    def _check_geometry(self) -> SensorProfile:
        if self.fov_up_deg <= self.fov_down_deg:
            raise ValueError(
                f"fov_up_deg ({self.fov_up_deg}) must be greater than "
                f"fov_down_deg ({self.fov_down_deg})"
            )
        if self.min_range >= self.max_range:
            raise ValueError(
                f"min_range ({self.min_range}) must be below max_range ({self.max_range})"
            )
        if not math.isfinite(self.empty_value) or 0.0 < self.empty_value < self.max_range:
            # A positive in-range empty value would be indistinguishable from a real return.
            raise ValueError(
                f"empty_value ({self.empty_value}) must be finite and not inside "
                f"(0, max_range={self.max_range}); use -1 or 0"
            )
        return self

    @property
    def fov_deg(self) -> float:
        return self.fov_up_deg - self.fov_down_deg

    def replace(self, **changes: Any) -> SensorProfile:
        """A validated copy with some fields changed (``None`` values are ignored)."""
        changes = {k: v for k, v in changes.items() if v is not None}
        if not changes:
            return self
        try:
            return SensorProfile.model_validate({**self.model_dump(), **changes})
        except ValidationError as err:
            raise ProfileError(f"invalid sensor profile override: {first_error(err)}") from err


BUILTIN_PROFILES: dict[str, SensorProfile] = {
    p.name: p
    for p in (
        # Velodyne HDL-64E as used on KITTI (OverlapNet/OverlapTransformer settings).
        SensorProfile(
            name="kitti-hdl64",
            fov_up_deg=3.0,
            fov_down_deg=-25.0,
            height=64,
            width=900,
            max_range=80.0,
        ),
        # Velodyne HDL-32E (NCLT/nuScenes) as used by SeqOT/CVTNet.
        SensorProfile(
            name="hdl32",
            fov_up_deg=10.67,
            fov_down_deg=-30.67,
            height=32,
            width=900,
            max_range=80.0,
        ),
    )
}


def first_error(err: ValidationError) -> str:
    e = err.errors()[0]
    where = ".".join(str(x) for x in e["loc"]) or "profile"
    return f"{where}: {e['msg']}"
