"""The LiDARs fleets carry: each one's beam table, columns, range and noise, from its manual.

A :class:`Sensor` is the physical instrument: one elevation per beam (row 0 the highest),
firings per turn, the range it reports and its range noise. The simulator renders it
(:mod:`overlapmamba.synth.lidar`), the service and the evaluation project its scans into a model's
input (:mod:`overlapmamba.core.sensors.input`), and its :meth:`Sensor.profile` is the range image of
its own (a row per beam) that the overlap ground truth of its drives is computed with.

Where a manual gives a table per laser (VLP-16, VLP-32C) the table is the manual's, sorted
from the highest beam down; where it gives a field of view and a uniform spacing (HDL-32E,
Ouster, Hesai XT32), the table is that spacing. Range noise is the manual's typical accuracy,
taken as the 1σ of a Gaussian; that is generous where a manual states a bound rather than a
deviation. Every entry names its source in :attr:`Sensor.source`.

Firings per turn follow from the firing cycle a manual gives (VLP-16/32C: 55.296 µs, 1,808
a turn at 10 Hz; HDL-32E: 46.08 µs, 2,170; HDL-64E S2: 48 µs a block, 2,083; XT32: 50 µs,
2,000); Ouster's are its lidar mode (1024 × 10 Hz). Real units carry their own calibrated
tables, which differ from the nominal one by a few tenths of a degree (an Ouster OS1-128's
spans 42.4–43.0° against the datasheet's 42.4°): the catalogue holds the nominal tables,
which is what a user who names a sensor can rely on.

Not here: Livox Mid-360 (360° × −7°…+52°, 200,000 points a second). Its non-repetitive
rosette is published only as a table of firing directions for Livox's Gazebo plugin
(Livox-SDK/livox_laser_simulation, ``scan_mode/mid360.csv``), which this project could not
obtain intact; rendered without it, a "Mid-360" would be a guess with its name on it.

A user-defined sensor is a TOML or JSON file with the same fields (or ``base = "vlp16"`` and
the fields that differ): :func:`get_sensor`.
"""

from __future__ import annotations

import json
import re
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from overlapmamba.core.errors import ProfileError
from overlapmamba.core.sensors.profile import BUILTIN_PROFILES, SensorProfile, first_error

NAME_PATTERN = r"^[a-z0-9][a-z0-9._-]{0,63}$"
# The projection convention of this project: images stop at 80 m (KITTI's profile), so a
# sensor's own profile reaches at most that far.
PROFILE_MAX_RANGE = 80.0
PROFILE_COLUMNS = 900


class Sensor(BaseModel):
    """One spinning LiDAR. Angles in degrees, ranges in metres."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = Field(pattern=NAME_PATTERN, description="catalogue key, as the wire names it")
    title: str = Field(min_length=1, max_length=120, description="maker and model")
    source: str = Field(min_length=1, description="the manual the figures come from")
    elevations_deg: tuple[float, ...] = Field(
        min_length=1, max_length=256, description="one per beam, highest first"
    )
    columns: int = Field(gt=0, le=8192, description="firings per turn at rate_hz")
    rate_hz: float = Field(default=10.0, gt=0.0, le=50.0, description="turns per second")
    min_range: float = Field(ge=0.0, description="nearer returns are not reported")
    max_range: float = Field(gt=0.0, le=1000.0, description="farther returns are not reported")
    range_sigma: float = Field(ge=0.0, le=1.0, description="range noise, 1σ")
    projection: SensorProfile | None = Field(
        default=None,
        description="the range image of the sensor's own; default a row per beam over its "
        "beams' span (kitti-hdl64 and hdl32 keep the profiles models were trained and "
        "checked with)",
    )

    @model_validator(mode="after")
    def _check(self) -> Sensor:
        el = np.asarray(self.elevations_deg)
        if not np.isfinite(el).all() or np.abs(el).max() > 90.0:
            raise ValueError("elevations_deg must be finite angles within ±90°")
        if len(el) > 1 and not (np.diff(el) < 0).all():
            raise ValueError("elevations_deg must be distinct and sorted from the highest down")
        if self.min_range >= self.max_range:
            raise ValueError(
                f"min_range ({self.min_range}) must be below max_range ({self.max_range})"
            )
        if self.projection is None and self.min_range >= PROFILE_MAX_RANGE:
            raise ValueError(
                f"min_range ({self.min_range}) must be below {PROFILE_MAX_RANGE:g} m, where the "
                "sensor's own range image ends (or give it a projection of its own)"
            )
        try:  # what the service builds for every sensor it lists: never a failure later
            self.profile()
        except ValueError as err:
            raise ValueError(f"the sensor's own range image cannot be made: {err}") from None
        return self

    @property
    def beams(self) -> int:
        return len(self.elevations_deg)

    @property
    def returns_per_turn(self) -> int:
        """Beams × columns: the most points one turn can hold (single return)."""
        return self.beams * self.columns

    def profile(self) -> SensorProfile:
        """The sensor's own range image: :attr:`projection`, or a row per beam whose field of
        view reaches half a spacing beyond the outer beams, 900 columns, at most 80 m."""
        if self.projection is not None:
            return self.projection
        el = np.asarray(self.elevations_deg, np.float64)
        top = float(el[0] - el[1]) / 2 if len(el) > 1 else 0.5
        bottom = float(el[-2] - el[-1]) / 2 if len(el) > 1 else 0.5
        return SensorProfile(  # a dome's outer beams at ±90°: its image ends there
            name=self.name,
            fov_up_deg=min(90.0, round(float(el[0]) + top, 4)),
            fov_down_deg=max(-90.0, round(float(el[-1]) - bottom, 4)),
            height=self.beams,
            width=PROFILE_COLUMNS,
            max_range=min(self.max_range, PROFILE_MAX_RANGE),
            min_range=self.min_range,
        )


def _uniform(top: float, bottom: float, beams: int) -> tuple[float, ...]:
    return tuple(round(float(x), 4) for x in np.linspace(top, bottom, beams))


def _hdl64_kitti() -> tuple[float, ...]:
    # The HDL-64E S2 manual's two blocks (32 lasers ≈1/3° apart above, 32 ≈1/2° apart
    # below, +2°…−24.8°) as KITTI's car carries it: real KITTI 00 scans span ≈+2.8°…−24.9°
    # (0.1–99.9 % quantiles of asin(z/r)), the mount being slightly tilted. The shipped model
    # was trained on drives rendered with this table.
    upper = np.linspace(2.7, -7.9, 32)
    lower = np.linspace(-8.4, -24.9, 32)
    return tuple(float(x) for x in np.concatenate([upper, lower]))


def _sorted(angles: list[float]) -> tuple[float, ...]:
    return tuple(sorted(angles, reverse=True))


_VELODYNE = "Velodyne LiDAR"
_OUSTER = "Ouster"

CATALOGUE: dict[str, Sensor] = {
    s.name: s
    for s in (
        Sensor(
            name="kitti-hdl64",
            title="Velodyne HDL-64E S2, as mounted on the KITTI car",
            source=f"{_VELODYNE}, HDL-64E S2 User's Manual and Programming Guide (63-HDL64ES2): "
            "two blocks of 32 lasers, 1/3° and 1/2° apart, +2°…−24.8°, ≈1.3 M points/s, "
            "120 m, < 2 cm; the blocks' span fitted to real KITTI 00 scans",
            elevations_deg=_hdl64_kitti(),
            columns=2083,
            min_range=0.9,
            max_range=120.0,
            range_sigma=0.02,
            projection=BUILTIN_PROFILES["kitti-hdl64"],
        ),
        Sensor(
            name="hdl64e",
            title="Velodyne HDL-64E S2",
            source=f"{_VELODYNE}, HDL-64E S2 User's Manual (63-HDL64ES2): upper block of 32 "
            "lasers +2°…−8.33° at 1/3°, lower block of 32 −8.83°…−24.33° at 1/2°; "
            "≈1.3 M points/s (2,083 firings a turn at 10 Hz), 120 m, < 2 cm",
            elevations_deg=(*_uniform(2.0, 2.0 - 31 / 3, 32), *_uniform(-8.8333, -24.3333, 32)),
            columns=2083,
            min_range=0.9,
            max_range=120.0,
            range_sigma=0.02,
        ),
        Sensor(
            name="hdl32",
            title="Velodyne HDL-32E",
            source=f"{_VELODYNE}, HDL-32E User's Manual (63-9113): 32 lasers +10.67°…−30.67° "
            "(4/3° apart), a 46.08 µs firing cycle (2,170 a turn at 10 Hz, 0.166°), usable "
            "returns to 100 m, < 2 cm",
            elevations_deg=_uniform(10.67, -30.67, 32),
            columns=2170,
            min_range=1.0,
            max_range=100.0,
            range_sigma=0.02,
            projection=BUILTIN_PROFILES["hdl32"],
        ),
        Sensor(
            name="vlp16",
            title="Velodyne VLP-16 (Puck)",
            source=f"{_VELODYNE}, VLP-16 User Manual (63-9243): 16 lasers −15°…+15° 2° apart "
            "(laser IDs 0–15: −15, 1, −13, 3, …, −1, 15), a 55.296 µs firing cycle (1,808 a "
            "turn at 10 Hz, 0.2°), 1–100 m, ±3 cm typical",
            elevations_deg=_uniform(15.0, -15.0, 16),
            columns=1808,
            min_range=1.0,
            max_range=100.0,
            range_sigma=0.03,
        ),
        Sensor(
            name="vlp32c",
            title="Velodyne VLP-32C (Ultra Puck)",
            source=f"{_VELODYNE}, VLP-32C User Manual (63-9325): 32 lasers −25°…+15°, 1/3° "
            "apart from −5.33° to +4.67° and sparser beyond, the vertical angle of each laser "
            "ID from its table; a 55.296 µs firing cycle (1,808 a turn at 10 Hz), 200 m, "
            "±3 cm typical",
            elevations_deg=_sorted(
                [
                    *(-25.0, -1.0, -1.667, -15.639, -11.31, 0.0, -0.667, -8.843),
                    *(-7.254, 0.333, -0.333, -6.148, -5.333, 1.333, 0.667, -4.0),
                    *(-4.667, 1.667, 1.0, -3.667, -3.333, 3.333, 2.333, -2.667),
                    *(-3.0, 7.0, 4.667, -2.333, -2.0, 15.0, 10.333, -1.333),
                ]
            ),
            columns=1808,
            min_range=1.0,
            max_range=200.0,
            range_sigma=0.03,
        ),
        Sensor(
            name="os1-64",
            title="Ouster OS1-64 (Rev 7)",
            source=f"{_OUSTER}, OS1 Mid-Range High-Resolution Imaging Lidar datasheet (Rev 7): "
            "64 channels uniform over 42.4° (+21.2°…−21.2°), lidar mode 1024 × 10 Hz, "
            "0.5–120 m (80 % reflectivity, the Rev 6 figure), precision ±1–3 cm",
            elevations_deg=_uniform(21.2, -21.2, 64),
            columns=1024,
            min_range=0.5,
            max_range=120.0,
            range_sigma=0.03,
        ),
        Sensor(
            name="os1-128",
            title="Ouster OS1-128 (Rev 7)",
            source=f"{_OUSTER}, OS1 datasheet (Rev 7): 128 channels uniform over 42.4° "
            "(+21.2°…−21.2°), lidar mode 1024 × 10 Hz, 0.5–120 m, precision ±1–3 cm",
            elevations_deg=_uniform(21.2, -21.2, 128),
            columns=1024,
            min_range=0.5,
            max_range=120.0,
            range_sigma=0.03,
        ),
        Sensor(
            name="os0-128",
            title="Ouster OS0-128 (Rev 6)",
            source=f"{_OUSTER}, OS0 Ultra-Wide View High-Resolution Imaging Lidar datasheet "
            "(Rev 6): 128 channels uniform over 90° (+45°…−45°), lidar mode 1024 × 10 Hz, "
            "0.5–50 m, precision ±1.5–5 cm",
            elevations_deg=_uniform(45.0, -45.0, 128),
            columns=1024,
            min_range=0.5,
            max_range=50.0,
            range_sigma=0.03,
        ),
        Sensor(
            name="os2-128",
            title="Ouster OS2-128 (Rev 6)",
            source=f"{_OUSTER}, OS2 Long-Range High-Resolution Imaging Lidar datasheet "
            "(Rev 6): 128 channels uniform over 22.5° (+11.25°…−11.25°), lidar mode "
            "1024 × 10 Hz, 0.8–240 m, precision ±2.5–8 cm",
            elevations_deg=_uniform(11.25, -11.25, 128),
            columns=1024,
            min_range=0.8,
            max_range=240.0,
            range_sigma=0.05,
        ),
        Sensor(
            name="xt32",
            title="Hesai PandarXT-32",
            source="Hesai Technology, PandarXT 32-Channel Mid-Range Mechanical Lidar User "
            "Manual: 32 channels +15°…−16° 1° apart, a firing block every 50 µs (2,000 a turn "
            "at 10 Hz, 0.18°), 0.05–120 m, ±1 cm typical",
            elevations_deg=_uniform(15.0, -16.0, 32),
            columns=2000,
            min_range=0.05,
            max_range=120.0,
            range_sigma=0.01,
        ),
    )
}
# m: the shortest reach of a catalogue spinning sensor (OS0-128): the inputs that cut every
# sensor's scans to one reach cut them here (overlapmamba.core.sensors.input)
COMMON_MAX_RANGE = 50.0


def sensor_names() -> list[str]:
    return sorted(CATALOGUE)


def get_profile(name_or_path: str | Path | SensorProfile) -> SensorProfile:
    """A built-in profile by name, a catalogue sensor's own profile by the sensor's name, or
    a custom one from a ``.json``/``.toml`` file."""
    if isinstance(name_or_path, SensorProfile):
        return name_or_path
    key = str(name_or_path)
    if key in BUILTIN_PROFILES:
        return BUILTIN_PROFILES[key]
    if key in CATALOGUE:
        return CATALOGUE[key].profile()
    path = Path(key)
    if path.suffix.lower() in {".json", ".toml"}:
        return load_profile(path)
    allowed = sorted(set(BUILTIN_PROFILES) | set(CATALOGUE))
    raise ProfileError(
        f"unknown sensor profile {key!r}; allowed: {', '.join(allowed)}, "
        "or a path to a .json/.toml profile file",
        allowed=allowed,
    )


def _sensor_table(data: Any, path: Path) -> Any:
    """The fields a file holds: its ``[sensor]`` table when it has one, which must then be
    all it holds (a key beside it would be dropped without a word)."""
    if isinstance(data, dict) and isinstance(data.get("sensor"), dict):
        beside = sorted(k for k in data if k != "sensor")
        if beside:
            raise ProfileError(
                f"sensor file {path}: keys {beside} lie outside its [sensor] table, where they "
                "would be ignored; put them inside [sensor]"
            )
        return data["sensor"]
    return data


def load_profile(path: str | Path, _chain: tuple[Path, ...] = ()) -> SensorProfile:
    """Read a custom profile; a TOML file may hold it at top level or under ``[sensor]``.
    A ``base`` that is a file is read beside this one (a relative path from its folder)."""
    path = Path(path)
    if path.resolve() in _chain:
        loop = " → ".join(str(p) for p in (*_chain, path.resolve()))
        raise ProfileError(f"sensor profile files name each other as base in a loop: {loop}")
    try:
        text = path.read_text()
    except OSError as err:
        raise ProfileError(f"cannot read sensor profile file {path}: {err.strerror}") from err
    try:
        data: Any = tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as err:
        raise ProfileError(f"sensor profile file {path} is not valid: {err}") from err
    data = _sensor_table(data, path)
    if isinstance(data, dict) and "base" in data:
        name = str(data.pop("base"))
        if Path(name).suffix.lower() in {".json", ".toml"}:
            beside = path.parent / name
            base = load_profile(beside, (*_chain, path.resolve()))
        else:
            base = get_profile(name)
        try:
            return base.replace(**data)
        except ProfileError as err:
            raise ProfileError(f"sensor profile file {path}: {err}") from None
    try:
        return SensorProfile.model_validate(data)
    except ValidationError as err:
        raise ProfileError(f"sensor profile file {path}: {first_error(err)}") from err


def get_sensor(name_or_path: str | Path | Sensor) -> Sensor:
    """A catalogue sensor by name, or a user-defined one from a ``.toml``/``.json`` file."""
    if isinstance(name_or_path, Sensor):
        return name_or_path
    key = str(name_or_path)
    if key in CATALOGUE:
        return CATALOGUE[key]
    if Path(key).suffix.lower() in {".json", ".toml"}:
        return load_sensor(key)
    raise ProfileError(
        f"unknown sensor {key!r}; allowed: {', '.join(sensor_names())}, or a path to a "
        ".toml/.json sensor file",
        allowed=sensor_names(),
    )


def catalogue_name(name: str) -> str:
    """``name`` when the catalogue has it, else a ProfileError listing the names (a sensor
    file is for the service's ``[sensors] files``, which carry their own tables)."""
    if name not in CATALOGUE:
        raise ProfileError(
            f"unknown sensor {name!r}; allowed: {', '.join(sensor_names())}",
            allowed=sensor_names(),
        )
    return name


def load_sensor(path: str | Path) -> Sensor:
    """A user-defined sensor: the fields of :class:`Sensor` at top level or under
    ``[sensor]``; with ``base = "<catalogue name>"`` only the fields that differ."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as err:
        raise ProfileError(f"cannot read sensor file {path}: {err.strerror}") from err
    try:
        data: Any = tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as err:
        raise ProfileError(f"sensor file {path} is not valid: {err}") from err
    data = _sensor_table(data, path)
    if not isinstance(data, dict):
        raise ProfileError(f"sensor file {path} must hold a table of sensor fields")
    if "base" in data:
        base = str(data.pop("base"))
        if base not in CATALOGUE:
            raise ProfileError(
                f"sensor file {path}: base {base!r} is not in the catalogue; allowed: "
                f"{', '.join(sensor_names())}",
                allowed=sensor_names(),
            )
        data = {**CATALOGUE[base].model_dump(exclude={"projection"}), **data}
    try:
        return Sensor.model_validate(data)
    except ValidationError as err:
        raise ProfileError(f"sensor file {path}: {first_error(err)}") from err


def sensor_of_profile(profile: SensorProfile) -> Sensor:
    """The sensor a model's own profile describes: the catalogue entry whose profile it is,
    else one with a beam per row spread uniformly over the profile's field of view (a model
    trained on a custom profile still has a sensor of its own, projected natively)."""
    for s in CATALOGUE.values():
        if s.profile() == profile:
            return s
    pitch = (profile.fov_up_deg - profile.fov_down_deg) / profile.height
    top = profile.fov_up_deg - pitch / 2
    name = re.sub(r"[^a-z0-9._-]", "-", profile.name.lower()).strip("-._")[:58] or "model"
    if name in CATALOGUE:  # another table under a catalogue name: keep both addressable
        name += "-model"
    try:
        return Sensor(
            name=name,
            title=f"the sensor of profile {profile.name}",
            source="a uniform beam per row of the model's own profile",
            elevations_deg=_uniform(top, top - pitch * (profile.height - 1), profile.height),
            columns=profile.width,
            min_range=profile.min_range,
            max_range=profile.max_range,
            range_sigma=0.0,
            projection=profile,
        )
    except ValidationError as err:  # e.g. more rows than a sensor may have beams (256)
        raise ProfileError(
            f"profile {profile.name!r} ({profile.height} rows, {profile.width} columns) has no "
            f"sensor a model could take as its own: {first_error(err)}"
        ) from None
