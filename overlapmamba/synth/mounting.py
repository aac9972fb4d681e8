"""Where a LiDAR sits: on what platform, how high above the road, tilted how far.

A :class:`Mounting` is the platform's body (boxes that hide the rays entering them, in the
platform's frame: x forward, y left, z up, from the sensor), the sensor's height above the
road and its tilt: pitch positive when the sensor looks down ahead, roll positive when its
left side is raised (it looks down to its right). The sensor frame is the tilted one: scans
are expressed in it and the poses a drive writes are its poses, so the overlap ground truth
and every consumer see the sensor as mounted.

| mounting | height | tilt | body |
|---|---|---|---|
| car      | 1.73 m (KITTI's roof) | — | KITTI's car: roof, hood, boot |
| robot    | 0.70 m | — | a sidewalk delivery robot, 0.8 × 0.6 m, 0.6 m tall |
| amr      | 0.35 m | — | a warehouse AMR, 1.0 × 0.7 m, 0.3 m tall |
| backpack | 1.80 m | pitched 5° down | the person carrying it, behind the sensor |

Heights and tilts can be set per drive (``GenConfig.mount_height`` / ``mount_pitch_deg`` /
``mount_roll_deg``); a body is given relative to the sensor, so it keeps its place below it
at any height.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from overlapmamba.core.sensors.mount import platform_from_sensor

# A box of the body: x min, x max (forward), y half-width, its top relative to the sensor
# (negative: below it). Boxes reach the ground.
Box = tuple[float, float, float, float]


@dataclass(frozen=True)
class Mounting:
    name: str
    height: float  # sensor above the road, m
    pitch_deg: float = 0.0  # positive: the sensor looks down ahead
    roll_deg: float = 0.0  # positive: its left side raised
    body: tuple[Box, ...] = ()

    def tilt(self) -> np.ndarray | None:
        """(3, 3) rotation platform ← sensor, or None when the sensor sits level."""
        return tilt_matrix(self.pitch_deg, self.roll_deg)

    def with_pose(
        self, height: float | None = None, pitch: float | None = None, roll: float | None = None
    ) -> Mounting:
        """A copy at another height or tilt (``None``: unchanged)."""
        return replace(
            self,
            height=self.height if height is None else float(height),
            pitch_deg=self.pitch_deg if pitch is None else float(pitch),
            roll_deg=self.roll_deg if roll is None else float(roll),
        )

    def blocked(self, d: np.ndarray) -> np.ndarray:
        """(…, 3) directions in the platform frame, from the sensor → (…,) bool: the ray
        enters the body."""
        blocked = np.zeros(d.shape[:-1], bool)
        down = d[..., 2] < -1e-6
        for x0, x1, hw, top in self.body:
            # Where a downward ray crosses the box's top face (boxes reach the ground).
            t = top / np.where(down, d[..., 2], -1.0)
            x, y = d[..., 0] * t, d[..., 1] * t
            blocked |= down & (x > x0) & (x < x1) & (np.abs(y) < hw)
        return blocked


def tilt_matrix(pitch_deg: float, roll_deg: float) -> np.ndarray | None:
    """(3, 3) rotation platform ← sensor for a pitch and a roll in degrees (see the module
    notes for their signs), or None when both are 0: a level sensor's rays stay as they are,
    bit for bit. The service levels a declared mount with the same rotation."""
    return platform_from_sensor(pitch_deg, roll_deg)


MOUNTINGS: dict[str, Mounting] = {
    m.name: m
    for m in (
        # KITTI's car in the sensor frame: rays that enter it return nothing, as in KITTI,
        # whose lowest beams reach the road only to the sides (checked against the real
        # scans by `sim-report`).
        Mounting(
            "car",
            1.73,
            body=((-1.3, 0.5, 0.8, -0.42), (0.5, 2.3, 0.9, -0.95), (-2.6, -1.3, 0.9, -0.85)),
        ),
        Mounting("robot", 0.70, body=((-0.5, 0.3, 0.3, -0.10),)),
        Mounting("amr", 0.35, body=((-0.5, 0.5, 0.35, -0.05),)),
        Mounting("backpack", 1.80, pitch_deg=5.0, body=((-0.45, -0.05, 0.25, -0.15),)),
    )
}


def get_mounting(name: str) -> Mounting:
    if name not in MOUNTINGS:
        raise ValueError(f"unknown mounting {name!r}; allowed: {', '.join(MOUNTINGS)}")
    return MOUNTINGS[name]
