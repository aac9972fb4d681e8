"""Which sensor a scan came from, and how its points become this model's input.

A scan names its sensor (the ``sensor`` query parameter, a stream frame's ``sensor``), or
its map does (declared when the map is created), or it is the model's own sensor (the one
its profile describes: ``kitti-hdl64`` for the shipped model). Names come from the sensor
catalogue (:mod:`overlapmamba.core.sensors.catalogue`) and from the operator's own sensor files
(``sensors.files``); anything else is a 400 that lists the known names. Nothing is guessed
from the points.

The projection is the model's (:class:`overlapmamba.core.sensors.input.SensorInput`: the model's
profile, views and ``sensor_input`` mode, the scan's beam table), made once per sensor. A
keyframe's sensor's field of view (:class:`FieldOfView`, :meth:`Sensors.view`) is what
verification scores a query from another sensor within.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from overlapmamba.core.errors import ProfileError
from overlapmamba.core.modelmeta import EncoderMetadata
from overlapmamba.core.sensors import CATALOGUE, Sensor, load_sensor, sensor_of_profile
from overlapmamba.core.sensors.input import BEV_MODES, SensorInput
from overlapmamba.core.sensors.mount import Mount
from overlapmamba.service.errors import BadRequest, Conflict


@dataclass(frozen=True)
class FieldOfView:
    """What a keyframe's sensor sees from where it stood: elevations from ``low_deg`` to
    ``high_deg`` in its own frame, out to ``max_range_m``. Registering a query of another
    sensor, fitness scores only the query's points inside it (aligned into the keyframe's
    frame): a VLP-16's ±15° or an OS1-128's ±22.5° hold walls above what an HDL-64E's +3°
    top beam reached, and those points find no partner however right the pose is."""

    low_deg: float
    high_deg: float
    max_range_m: float
    margin_deg: float = 2.0  # the 2 m grid's points are cell means: their angles blur

    @classmethod
    def of(cls, elevations_deg: tuple[float, ...], max_range_m: float) -> FieldOfView:
        return cls(min(elevations_deg), max(elevations_deg), max_range_m)

    def inside(self, pts: np.ndarray) -> np.ndarray:
        """(N,) bool: points (N, 3) in the sensor's frame that it could have returned."""
        r_xy = np.hypot(pts[:, 0], pts[:, 1])
        el = np.degrees(np.arctan2(pts[:, 2], r_xy))
        lo, hi = self.low_deg - self.margin_deg, self.high_deg + self.margin_deg
        return (el >= lo) & (el <= hi) & (np.hypot(r_xy, pts[:, 2]) <= self.max_range_m)


class Sensors:
    """The sensors this service accepts scans from, for one model."""

    def __init__(self, meta: EncoderMetadata, files: list[Path] | None = None) -> None:
        self.meta = meta
        self.model_sensor = sensor_of_profile(meta.profile)  # never shadows a catalogue name
        known: dict[str, Sensor] = dict(CATALOGUE)
        known[self.model_sensor.name] = self.model_sensor
        for path in files or []:
            s = load_sensor(path)  # ProfileError names the file: the service does not start
            if s.name in known:
                raise ProfileError(
                    f"sensor file {path} names {s.name!r}, which is already known; give it "
                    "a name of its own"
                )
            try:  # a sensor this model's input cannot take (no common beam) stops the start
                taken = SensorInput(meta.profile, s, meta.sensor_input)
            except ValueError as err:
                raise ProfileError(f"sensor file {path}: {err}") from None
            if meta.sensor_input not in BEV_MODES and not (taken.rows() >= 0).any():
                raise ProfileError(  # every scan of it would be an empty image
                    f"sensor file {path}: none of {s.name!r}'s beams "
                    f"({s.elevations_deg[0]:g}° to {s.elevations_deg[-1]:g}°) falls in the "
                    f"model's image ({meta.profile.fov_up_deg:g}° to "
                    f"{meta.profile.fov_down_deg:g}°): the model cannot read its scans"
                )
            known[s.name] = s
        self.known = known
        self._inputs: dict[tuple[str, Mount | None], SensorInput] = {}

    def names(self) -> list[str]:
        return sorted(self.known)

    def check(self, name: str | None) -> str | None:
        """``name`` if known (None passes: the map's or the model's sensor), else a 400."""
        if name is not None and name not in self.known:
            raise BadRequest(
                f"unknown sensor {name!r}; allowed: {', '.join(self.names())}",
                code="unknown_sensor",
                allowed=self.names(),
            )
        return name

    def resolve(self, scan: str | None, map_sensor: str | None = None) -> str:
        """The sensor a scan is projected as: its own, else its map's, else the model's. A
        map whose sensor this service does not know (a sensor file since removed, a map
        imported from another service) is a 409 naming the map, not the client's fault."""
        if scan is not None:
            return self.check(scan) or scan
        if map_sensor is not None and map_sensor not in self.known:
            raise Conflict(
                f"this map declares sensor {map_sensor!r}, which this service does not know "
                f"(allowed: {', '.join(self.names())}); name the scan's sensor, or add the "
                "sensor's file to [sensors] files",
                code="unknown_map_sensor",
                sensor=map_sensor,
                allowed=self.names(),
            )
        return map_sensor or self.model_sensor.name

    def declared(self, name: str | None) -> str | None:
        """A map's sensor as stored: the model's own is None (so a map made before sensors
        existed and one made naming the model's own sensor are the same map)."""
        self.check(name)
        return None if name is None or self.is_model_sensor(name) else name

    def input(self, name: str, mount: Mount | None = None) -> SensorInput:
        """The projection of ``name``'s scans into this model's input (cached), from
        ``mount`` when the scan declares where its sensor sits. The model's own mount,
        declared, is no mount: the scan is taken as it is (a car's drive sent into a map
        whose robots sit lower names it, so that the map's does not stand in)."""
        if mount is not None and mount.at_reference:
            mount = None
        key = (name, mount)
        if key not in self._inputs:
            self.check(name)
            if len(self._inputs) >= 256:  # mounts come from clients: keep the cache bounded
                self._inputs.clear()
            self._inputs[key] = SensorInput(
                self.meta.profile, self.known[name], self.meta.sensor_input, mount
            )
        return self._inputs[key]

    def is_model_sensor(self, name: str) -> bool:
        return name == self.model_sensor.name

    def view(self, keyframe_sensor: str | None, query_sensor: str | None) -> FieldOfView | None:
        """The keyframe's sensor's field of view when the query came from another sensor
        (fitness then scores what both could see: :class:`FieldOfView`), else None. A
        keyframe that recorded no sensor came from the model's own (it predates the record)."""
        kf = keyframe_sensor or self.model_sensor.name
        if query_sensor is None or kf == query_sensor or kf not in self.known:
            return None
        s = self.known[kf]
        return FieldOfView.of(s.elevations_deg, s.max_range)
