"""Sensors: the projection profiles of range images (:mod:`.profile`), the LiDARs fleets
carry with their beam tables (:mod:`.catalogue`), and how a scan of any of them becomes a
model's input (:mod:`.input`: by its beams, :mod:`.beams`, or bird's-eye, :mod:`.bev`)."""

from overlapmamba.core.sensors.catalogue import (
    CATALOGUE,
    Sensor,
    get_profile,
    get_sensor,
    load_profile,
    load_sensor,
    sensor_names,
    sensor_of_profile,
)
from overlapmamba.core.sensors.profile import BUILTIN_PROFILES, SensorProfile

__all__ = [
    "BUILTIN_PROFILES",
    "CATALOGUE",
    "Sensor",
    "SensorProfile",
    "get_profile",
    "get_sensor",
    "load_profile",
    "load_sensor",
    "sensor_names",
    "sensor_of_profile",
]
