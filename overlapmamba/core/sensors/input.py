"""A scan of any sensor → a model's input range image: the model's profile says the image
(rows, columns, range), the scan's sensor says where its beams point.

    native     the sensor's own profile is the model's (a KITTI HDL-64E scan into the
               HDL-64E model): :func:`overlapmamba.core.views.project_views`, exactly
    elevation  every point goes to its beam (the nearest elevation of the sensor's table),
               and each row of the model takes the beam nearest its own elevation when that
               beam lies within half a beam gap (or half a row) of it; rows the sensor has
               no beam for stay empty. Rows keep their elevation: a VLP-16's beams land
               where an HDL-64E's would
    elevation-lerp
               the scan made into the model's own sensor's: each of its beams takes a range
               interpolated between the two of the sensor's beams around its elevation (or the
               nearest, at an edge: :func:`lerp_rows`), and lands in its row as the model's own
               projection puts it. A sensor with fewer beams then shows the rows, and the
               rows left empty, of the model's own sensor. The model's own sensor is taken
               natively, as in ``elevation``
    elevation-fill
               ``elevation``, then every one-column gap in a row of another sensor's image
               (an empty cell between two returns) takes the nearer of the two
               (:mod:`overlapmamba.core.sensors.gaps`): a sensor firing about once a column,
               as the 1,024-column Ousters do into 900 columns, leaves a hole at every lost
               return, where the model's own sensor covers it with another firing. The model's
               own sensor is taken natively, as in ``elevation``
    elevation-reach
               ``elevation-fill`` with every scan, the model's own sensor's too, cut at
               :data:`COMMON_MAX_RANGE`: a map made by a sensor that sees to 80 m and a
               query by one that sees to 50 m then show the same returns (the model's own
               scans are no longer taken natively, their gaps still not filled)
    rows       the sensor's beams, highest first, stretched over the model's rows (row r
               takes beam ⌊(r + ½)·B / H⌋): every row filled, elevations not kept (the
               sensor-transfer check ``eval-real`` ran on nuScenes' HDL-32E before sensors
               had tables)
    common     every sensor, the model's own too, first keeps only its beams nearest the
               elevations of a common sensor (:data:`COMMON_SENSOR`'s, within
               :data:`COMMON_TOLERANCE_DEG`; a point's beam is the nearest elevation of its
               sensor's table, found in the sensor's own frame), and those points are then
               projected as the common sensor's scan (``elevation``). Every sensor's image
               shows the same rings at the same rows; the model's own scans lose most of
               theirs (the KITTI HDL-64E keeps 10 of 64). Measured with the shipped weights
               by ``benchmarks/common_beams.py``
    structure  ``common``, then only what stands above the ground and within a common range:
               after levelling, a return less than :data:`GROUND_CLEARANCE` above the
               reference mount's ground (:data:`~overlapmamba.core.sensors.mount.REFERENCE_HEIGHT`
               below the sensor) or beyond :data:`COMMON_MAX_RANGE` is dropped. The ground is
               where sensors disagree most: a beam 0.2° off another's meets a flat road 3 m
               nearer or farther at −3°, while a wall is at its range from every beam; and an
               OS0-128 sees nothing beyond 50 m
    bev        a polar bird's-eye view instead of a range image, from every return of any
               sensor (none thinned), levelled at the reference mount: rows are rings of
               horizontal range (:data:`BEV_RINGS` of ``COMMON_MAX_RANGE / BEV_RINGS`` m,
               nearest first) × height bands above the reference ground
               (:data:`BEV_BANDS`, each ring's bands on consecutive rows, lowest first),
               columns the model's azimuth columns, and a cell is 1 where any return falls
               in it, ``empty_value`` elsewhere. Which cells a wall or a trunk occupies does
               not depend on how many beams hit it, where a range image's rows do; the
               ground is left out and so is what only some sensors reach (above the top band,
               beyond :data:`COMMON_MAX_RANGE` in range). Its layout measured against
               others by a hand-made spectrum on the validation drive and its renderings
               (``benchmarks/bev_input.py``)
    bev-soft   ``bev`` with each return shared between the two columns nearest its azimuth
    bev-span   ``bev`` with each cell showing how much of its column its returns' spans (a
               column wide each) cover. Under a turn a ``bev`` image keeps a return in its
               column until it jumps to the next; these two move with the turn
               (:mod:`overlapmamba.core.sensors.bev` says what their cells show)

A scan whose sensor sits elsewhere than the model's did (``mount``: height and tilt,
:mod:`overlapmamba.core.sensors.mount`) is first levelled and moved to the model's height, in
every mode.

Which one a model takes is its own (``EncoderMetadata.sensor_input``): the projection of a
scan is never chosen by its consumer. Columns, sub-column views and the range limits are
the model's in every mode, so yaw features keep their meaning.

:func:`project_input_reference` is the slow per-point version kept beside the fast one for
tests. The constants named above are defined where they belong: ``COMMON_MAX_RANGE`` with the
catalogue (:mod:`overlapmamba.core.sensors.catalogue`), ``GROUND_CLEARANCE`` with the
reference mount (:mod:`overlapmamba.core.sensors.mount`), ``BEV_RINGS`` and ``BEV_BANDS``
with the bird's-eye inputs (:mod:`overlapmamba.core.sensors.bev`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property
from typing import Literal, get_args

import numpy as np

from overlapmamba.core.points import PointCloud, xyz_of
from overlapmamba.core.sensors.beams import (
    COMMON_TOLERANCE_DEG,
    LerpPlan,
    beam_of,
    beams_near,
    lerp_rows,
    on_beams,
    row_beams,
)
from overlapmamba.core.sensors.bev import (
    BEV_BANDS,
    BEV_MODES,
    BEV_RINGS,
    bev_rows,
    project_bev_offset,
)
from overlapmamba.core.sensors.catalogue import (
    CATALOGUE,
    COMMON_MAX_RANGE,
    Sensor,
    sensor_of_profile,
)
from overlapmamba.core.sensors.gaps import fill_gaps
from overlapmamba.core.sensors.mount import (
    GROUND_CLEARANCE,
    REFERENCE_HEIGHT,
    Mount,
    to_reference,
)
from overlapmamba.core.sensors.profile import SensorProfile
from overlapmamba.core.views import check_views, project_views_offset, scan_offset

Mode = Literal[
    "elevation",
    "elevation-lerp",
    "elevation-fill",
    "elevation-reach",
    "rows",
    "common",
    "structure",
    "bev",
    "bev-soft",
    "bev-span",
]
MODES: tuple[str, ...] = get_args(Mode)
COMMON_MODES = ("common", "structure")  # the modes that thin every scan to common beams
# the modes every scan goes through, the model's own sensor's too (none is taken natively)
ALL_SCANS_MODES = (*COMMON_MODES, "elevation-reach", *BEV_MODES)
# the modes that fill other sensors' one-column gaps (overlapmamba.core.sensors.gaps)
FILL_MODES = ("elevation-fill", "elevation-reach")
# the modes that level a scan and move it to the reference mount's height (their ground is
# that mount's): the others take scans as recorded
LEVELLED_MODES = ("structure", *BEV_MODES)
COMMON_SENSOR = "vlp16"  # the sparsest spinning sensor of the catalogue: 16 beams, 2° apart
_PI = np.float32(np.pi)


def check_mode(mode: str) -> Mode:
    if mode not in MODES:
        raise ValueError(f"sensor input mode {mode!r} is not known; allowed: {', '.join(MODES)}")
    return mode  # type: ignore[return-value]


def common_beams(sensor: Sensor) -> np.ndarray:
    """Indices of ``sensor``'s beams nearest each of the common sensor's elevations, where
    one lies within :data:`COMMON_TOLERANCE_DEG` (sorted, highest first)."""
    return beams_near(sensor, CATALOGUE[COMMON_SENSOR])


def above_ground(xyz: np.ndarray) -> np.ndarray:
    """(M, 3) the points of ``xyz`` (N, ≥3), seen from the reference mount, that stand at
    least :data:`GROUND_CLEARANCE` above its ground and lie nearer than
    :data:`COMMON_MAX_RANGE` (the ``structure`` input)."""
    xyz = np.asarray(xyz)[:, :3]
    r = np.linalg.norm(xyz, axis=1)
    return xyz[(xyz[:, 2] >= GROUND_CLEARANCE - REFERENCE_HEIGHT) & (r < COMMON_MAX_RANGE)]


@dataclass(frozen=True)
class SensorInput:
    """How scans of ``sensor`` become the input of a model trained on ``model``."""

    model: SensorProfile
    sensor: Sensor
    mode: Mode
    mount: Mount | None = None  # None: where the model's sensor sat (level, its height)

    def __post_init__(self) -> None:
        check_mode(self.mode)
        if self.mode in BEV_MODES:
            bev_rows(self.model)
        if self.mode in COMMON_MODES and not common_beams(self.sensor).size:
            raise ValueError(
                f"sensor {self.sensor.name!r} has no beam within {COMMON_TOLERANCE_DEG}° of "
                f"the common elevations ({COMMON_SENSOR}'s): a model taking common beams "
                "cannot read its scans"
            )

    @cached_property
    def own_sensor(self) -> bool:
        """The scans are of the model's own sensor (its profile is the model's); made once a
        pairing, not once a scan."""
        return self.sensor.profile() == self.model

    @cached_property
    def _elevation(self) -> SensorInput:
        """The fill modes' projection before the fill: this pairing by ``elevation``."""
        return replace(self, mode="elevation")

    @property
    def native(self) -> bool:
        """The model's own sensor, taken exactly as the model was trained (no mount, and
        not thinned to common beams)."""
        return self.mode not in ALL_SCANS_MODES and self.own_sensor and self.mount is None

    @property
    def kind(self) -> str:
        """native or the mode (elevation, rows, common, structure, bev…): what this pairing
        does (with ``+mount`` when the scan is first moved to the model's mount)."""
        own = self.own_sensor and self.mode not in ALL_SCANS_MODES
        return ("native" if own else self.mode) + ("+mount" if self.mount is not None else "")

    @property
    def reach(self) -> tuple[float, float]:
        """The ranges (m) whose returns enter the model's input: the model's own, cut at
        :data:`COMMON_MAX_RANGE` in the modes that cut every sensor there."""
        if self.mode in ("elevation-reach", "structure", *BEV_MODES):
            return self.model.min_range, COMMON_MAX_RANGE
        return self.model.min_range, self.model.max_range

    @classmethod
    def own(cls, model: SensorProfile, mode: Mode = "elevation") -> SensorInput:
        """The model's own sensor into it: the plain projection, unless the model takes every
        sensor's common beams."""
        return cls(model, sensor_of_profile(model), mode)

    def rows(self) -> np.ndarray:
        """(H,) the beam each model row shows (−1: empty); in the common modes, the common
        sensor's beam. The ``bev`` input's rows are rings and height bands, not beams."""
        if self.mode in BEV_MODES:
            raise ValueError(
                f"the {self.mode} input's rows are rings of range × height bands, not beams"
            )
        if self.mode in COMMON_MODES:
            return row_beams(self.model, CATALOGUE[COMMON_SENSOR], "elevation")
        return row_beams(self.model, self.sensor, self.mode)

    @cached_property
    def lerp_plan(self) -> LerpPlan | None:
        """``elevation-lerp``'s plan for this sensor (made once per pairing, not per scan);
        None in the other modes."""
        return LerpPlan.of(self.model, self.sensor) if self.mode == "elevation-lerp" else None

    def key(self) -> dict[str, object]:
        """What the images depend on beyond the model's profile (for caches)."""
        if self.native:
            return {}
        key: dict[str, object] = {"sensor": self.sensor.model_dump(mode="json"), "mode": self.mode}
        if self.mode in COMMON_MODES:
            key["common"] = {"sensor": COMMON_SENSOR, "tolerance_deg": COMMON_TOLERANCE_DEG}
        if self.mode == "elevation-reach":
            key["reach_m"] = COMMON_MAX_RANGE
        if self.mode in BEV_MODES:
            key["bev"] = {
                "bands_m": list(BEV_BANDS),
                "rings": BEV_RINGS,
                "ground_m": REFERENCE_HEIGHT,
                "max_range_m": COMMON_MAX_RANGE,
                **({"cells": self.mode.removeprefix("bev-")} if self.mode != "bev" else {}),
            }
        if self.mode == "structure":
            key["structure"] = {
                "clearance_m": GROUND_CLEARANCE,
                "ground_m": REFERENCE_HEIGHT,
                "max_range_m": COMMON_MAX_RANGE,
            }
        if self.mount is not None:
            key["mount"] = self.mount.key()
        return key

    def project(
        self, points: PointCloud | np.ndarray, views: int = 1, *, aligned: bool = False
    ) -> np.ndarray:
        """(views, H, W) float32 in the model's profile; view 0 as :func:`project_input`.
        ``aligned``: the columns start where the scan's mean bearing puts them
        (:mod:`overlapmamba.core.views`; :meth:`project_offset` also says by how much)."""
        return self.project_offset(points, views, aligned=aligned)[0]

    def project_offset(
        self, points: PointCloud | np.ndarray, views: int = 1, *, aligned: bool = False
    ) -> tuple[np.ndarray, float]:
        """:meth:`project` and the column offset of its images (0 unless ``aligned``)."""
        if self.mode in FILL_MODES:
            if self.mode == "elevation-reach":
                xyz = xyz_of(points)
                points = xyz[np.linalg.norm(xyz, axis=1) < COMMON_MAX_RANGE]
            images, offset = self._elevation.project_offset(points, views, aligned=aligned)
            filled = images if self.own_sensor else fill_gaps(images, self.model.empty_value)
            return filled, offset
        if self.mode in BEV_MODES:
            xyz = xyz_of(points)
            xyz = to_reference(xyz, self.mount) if self.mount is not None else xyz
            return project_bev_offset(xyz, self.model, views, mode=self.mode, aligned=aligned)
        if self.mount is not None or self.mode in COMMON_MODES:
            xyz = points.xyz if isinstance(points, PointCloud) else np.asarray(points)
            if xyz.ndim != 2 or xyz.shape[1] < 3:
                raise ValueError(f"points must have shape (N, 3) or (N, 4); got {xyz.shape}")
            if self.mode in COMMON_MODES:  # the beams are the sensor's: found before levelling
                xyz = on_beams(xyz, self.sensor, common_beams(self.sensor))
            points = to_reference(xyz, self.mount) if self.mount is not None else xyz
            if self.mode == "structure":  # the ground is the reference mount's: after it
                points = above_ground(points)
        if self.mode in COMMON_MODES:
            common = CATALOGUE[COMMON_SENSOR]
            return _project_beams(points, self.model, common, self.rows(), views, aligned)
        if self.own_sensor:
            return project_views_offset(points, self.model, views, aligned=aligned)
        return _project_beams(
            points, self.model, self.sensor, self.rows(), views, aligned, plan=self.lerp_plan
        )


def _project_beams(
    points: PointCloud | np.ndarray,
    model: SensorProfile,
    sensor: Sensor,
    rows: np.ndarray,
    views: int,
    aligned: bool = False,
    *,
    plan: LerpPlan | None = None,
) -> tuple[np.ndarray, float]:
    views = check_views(views)
    xyz = points.xyz if isinstance(points, PointCloud) else np.asarray(points)
    if xyz.ndim != 2 or xyz.shape[1] < 3:
        raise ValueError(f"points must have shape (N, 3) or (N, 4); got {xyz.shape}")
    xyz = xyz[:, :3].astype(np.float32, copy=False)
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    depth = np.sqrt(x * x + y * y + z * z)
    keep = (depth > np.float32(model.min_range)) & (depth < np.float32(model.max_range))
    x, y, z, depth = x[keep], y[keep], z[keep], depth[keep]
    B, H, W = sensor.beams, model.height, model.width
    beam = beam_of(np.degrees(np.arcsin(z / depth)), sensor).astype(np.int64)
    # The column coordinate as overlapmamba.core.projection computes it (same float32 order).
    u = np.float32(0.5) * (-np.arctan2(y, x) / _PI + np.float32(1.0)) * np.float32(W)
    offset = scan_offset(x, y, depth, W) if aligned else 0.0
    if aligned:
        u = u + np.float32(offset)
    out = np.full((views, H, W), np.float32(model.empty_value), np.float32)
    filled = rows >= 0
    for j in range(views):
        shifted = u + np.float32(j / views) if j else u
        col = np.floor(shifted).astype(np.int64)
        col = np.clip(col, 0, W - 1) if j == 0 and not aligned else col % W
        ring = np.full(B * W, np.inf, np.float32)
        np.minimum.at(ring, beam * W + col, depth)
        ring[np.isinf(ring)] = np.float32(model.empty_value)
        if plan is not None:
            out[j] = lerp_rows(
                ring.reshape(B, W), plan, sensor.elevations_deg, H, model.empty_value
            )
        else:
            out[j, filled] = ring.reshape(B, W)[rows[filled]]
    return out, offset


def project_input_reference(
    points: PointCloud | np.ndarray, model: SensorProfile, sensor: Sensor, mode: Mode
) -> np.ndarray:
    """Slow, obvious version of one view for tests (no mount): per point, its beam by the
    smallest elevation difference; per model row, the points of the beam that row shows. In
    ``common`` mode a point off the common beams is dropped, and a kept one takes the common
    sensor's beam nearest its elevation; in ``structure`` mode a point below the clearance
    above the reference ground, or beyond the common range, is dropped too."""
    xyz = points.xyz if isinstance(points, PointCloud) else np.asarray(points)
    keep = common_beams(sensor) if mode in COMMON_MODES else None
    structure = mode == "structure"
    orig_table = np.asarray(sensor.elevations_deg)
    if mode in COMMON_MODES:
        sensor, mode = CATALOGUE[COMMON_SENSOR], "elevation"
    rows = row_beams(model, sensor, mode)
    H, W = model.height, model.width
    image = np.full((H, W), np.float32(model.empty_value), np.float32)
    el_table = np.asarray(sensor.elevations_deg)
    for x, y, z in np.asarray(xyz, np.float32)[:, :3]:
        r = np.sqrt(x * x + y * y + z * z)
        if not (np.float32(model.min_range) < r < np.float32(model.max_range)):
            continue
        el = float(np.degrees(np.arcsin(z / r)))
        if keep is not None and _nearest(el, orig_table) not in keep:
            continue
        if structure and (z < GROUND_CLEARANCE - REFERENCE_HEIGHT or r >= COMMON_MAX_RANGE):
            continue
        beam = _nearest(el, el_table)
        u = np.float32(0.5) * (-np.arctan2(y, x) / _PI + np.float32(1.0)) * np.float32(W)
        col = min(max(int(np.floor(u)), 0), W - 1)
        for row in np.flatnonzero(rows == beam):
            if image[row, col] == model.empty_value or r < image[row, col]:
                image[row, col] = r
    return image


def _nearest(el: float, table: np.ndarray) -> int:
    gap = np.abs(table - el)
    return int(np.flatnonzero(gap == gap.min())[-1])  # halfway: the lower beam
