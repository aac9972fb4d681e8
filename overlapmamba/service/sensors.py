"""Which sensor a scan came from, and how its points become this model's input.

A scan names its sensor (the ``sensor`` query parameter, a stream frame's ``sensor``), or
its map does (declared when the map is created), or it is the model's own sensor (the one
its profile describes: ``kitti-hdl64`` for the shipped model). Names come from the sensor
catalogue (:mod:`overlapmamba.core.sensors.catalogue`) and from the operator's own sensor files
(``sensors.files``); anything else is a 400 that lists the known names. Nothing is guessed
from the points.

The projection is the model's (:class:`overlapmamba.core.sensors.input.SensorInput`: the model's
profile, views and ``sensor_input`` mode, the scan's beam table), made once per sensor.
"""

from __future__ import annotations

from pathlib import Path

from overlapmamba.core.errors import ProfileError
from overlapmamba.core.modelmeta import EncoderMetadata
from overlapmamba.core.sensors import CATALOGUE, Sensor, load_sensor, sensor_of_profile
from overlapmamba.core.sensors.input import SensorInput
from overlapmamba.core.sensors.mount import Mount
from overlapmamba.service.errors import BadRequest, Conflict


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
                SensorInput(meta.profile, s, meta.sensor_input)
            except ValueError as err:
                raise ProfileError(f"sensor file {path}: {err}") from None
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
        ``mount`` when the scan declares where its sensor sits."""
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
