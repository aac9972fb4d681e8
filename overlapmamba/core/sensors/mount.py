"""Where a scan's sensor sits, and its points as seen from where the model's sensor sat.

A :class:`Mount` is a sensor's height above the ground and its tilt: pitch positive when the
sensor looks down ahead, roll positive when its left side is raised (the simulator's
conventions, :mod:`overlapmamba.synth.mounting`). A robot knows it from its description (the
transform from ``base_footprint`` to the LiDAR's frame).

The model was trained on scans from a level sensor :data:`REFERENCE_HEIGHT` above the road
(KITTI's car roof, where every synthetic training town puts it). A scan from elsewhere sees
the same street from another point: a wall 10 m away spans other elevations from 0.35 m than
from 1.73 m, and a tilted sensor's horizon is a sine over azimuth. :func:`to_reference` puts
the scan's points where a level sensor at the reference height would have them: turned level,
then moved up or down. What the lower sensor could not see stays unseen, and what it saw
that the higher one would not (under a parked car) stays seen; the rest lands where the
model expects it.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

REFERENCE_HEIGHT = 1.73  # m: the training towns' sensor, on KITTI's car roof, level
# m above the reference mount's ground: below it, the ``structure`` and bird's-eye inputs drop
# a return (overlapmamba.core.sensors.input)
GROUND_CLEARANCE = 0.3


class Mount(BaseModel):
    """A sensor's place on its platform: height above the ground and tilt, in degrees."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    height: float = Field(gt=0.0, le=10.0, description="the sensor above the ground, m")
    pitch_deg: float = Field(default=0.0, ge=-45.0, le=45.0, description="+: looks down ahead")
    roll_deg: float = Field(default=0.0, ge=-45.0, le=45.0, description="+: left side raised")

    @classmethod
    def parse(cls, text: str) -> Mount:
        """``HEIGHT[,PITCH[,ROLL]]`` (metres, degrees), as a query parameter gives it."""
        parts = [p.strip() for p in text.split(",")]
        if not 1 <= len(parts) <= 3:
            raise ValueError(f"mount {text!r}: give HEIGHT[,PITCH[,ROLL]] (m, degrees)")
        try:
            values = [float(p) for p in parts]
        except ValueError:
            raise ValueError(f"mount {text!r}: give HEIGHT[,PITCH[,ROLL]] as numbers") from None
        return cls(**dict(zip(("height", "pitch_deg", "roll_deg"), values, strict=False)))

    def key(self) -> dict[str, float]:
        return self.model_dump()

    def text(self) -> str:
        """``HEIGHT,PITCH,ROLL``, as :meth:`parse` takes it."""
        return f"{self.height:g},{self.pitch_deg:g},{self.roll_deg:g}"

    @property
    def at_reference(self) -> bool:
        """Where the model's sensor sat (level, :data:`REFERENCE_HEIGHT` up): nothing to move."""
        level = self.pitch_deg == 0.0 and self.roll_deg == 0.0
        return level and abs(self.height - REFERENCE_HEIGHT) < 1e-6


def platform_from_sensor(pitch_deg: float, roll_deg: float) -> np.ndarray | None:
    """(3, 3) rotation platform ← sensor (a level frame from the tilted sensor's), or None
    when the sensor sits level."""
    if pitch_deg == 0.0 and roll_deg == 0.0:
        return None
    p, r = np.radians(pitch_deg), np.radians(roll_deg)
    # Pitch: a rotation about y that takes the sensor's x axis to (cos p, 0, −sin p).
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    # Roll: a rotation about x that takes the sensor's y axis to (0, cos r, sin r).
    rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    return ry @ rx


def to_reference(
    xyz: np.ndarray, mount: Mount, reference_height: float = REFERENCE_HEIGHT
) -> np.ndarray:
    """(N, 3) points in the mounted sensor's frame → float32 (N, 3) in a level frame
    ``reference_height`` above the ground, straight above or below the sensor."""
    out = np.asarray(xyz, np.float32)[:, :3]
    tilt = platform_from_sensor(mount.pitch_deg, mount.roll_deg)
    out = out @ tilt.T.astype(np.float32) if tilt is not None else out.copy()
    out[:, 2] -= np.float32(reference_height - mount.height)
    return out
