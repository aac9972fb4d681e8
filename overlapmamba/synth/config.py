"""Everything that determines a generated sequence: :class:`GenConfig` (seed, frames,
session, sensor and its mounting, world/drive/dynamics overrides, the ground-truth table's
extent)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SerializerFunctionWrapHandler,
    field_validator,
    model_serializer,
)

from overlapmamba.core.overlap import LoopParams
from overlapmamba.core.sensors.catalogue import CATALOGUE, sensor_names
from overlapmamba.synth.dynamics import DynamicsParams
from overlapmamba.synth.mounting import MOUNTINGS, Mounting
from overlapmamba.synth.trajectory import DriveParams
from overlapmamba.synth.world import WorldParams


class GenConfig(BaseModel):
    """Everything that determines a generated sequence."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    seed: int = Field(ge=0, le=2**31 - 1)
    frames: int = Field(ge=2, le=100_000)
    session: int = Field(
        default=0,
        ge=0,
        le=1000,
        description="0: the town's first drive; k > 0: another drive through the same static "
        "town (same seed) along the streets the first drive of as many frames took, in its own "
        "order and directions, with its own parked cars, traffic, people and scan noise",
    )
    sensor: str = Field(
        default="kitti-hdl64",
        description="a catalogue sensor (overlapmamba.core.sensors.catalogue); a later session may "
        "carry another one than the first",
    )
    mount: str = Field(
        default="car", description="car, robot, amr or backpack (overlapmamba.synth.mounting)"
    )
    mount_height: float | None = Field(
        default=None, gt=0.05, le=5.0, description="m above the road; None: the mounting's"
    )
    mount_pitch_deg: float | None = Field(
        default=None, ge=-30.0, le=30.0, description="positive: looks down ahead"
    )
    mount_roll_deg: float | None = Field(
        default=None, ge=-30.0, le=30.0, description="positive: left side raised"
    )
    firing_phase: Literal["locked", "drifting"] = Field(
        default="locked",
        description="locked: the head fires at the same azimuths every turn (every preset "
        "made before generator 1.8.0); drifting: each scan's firings start a random fraction "
        "of a firing's spacing later, as a real head's do from turn to turn "
        "(overlapmamba.synth.lidar)",
    )
    preset: str | None = None
    split: str = Field(default="train", description="train, val or test; test is never trained on")
    world: dict = Field(default_factory=dict, description="WorldParams overrides")
    drive: dict = Field(default_factory=dict, description="DriveParams overrides")
    dynamics: dict = Field(default_factory=dict, description="DynamicsParams overrides")
    gt_radius: float = Field(default=30.0, gt=0, le=200)
    loop_exclude: int = Field(default=100, ge=0)
    loop_min_overlap: float = Field(default=0.3, ge=0, le=1)
    pair_table: Literal["all", "loops", "none"] = Field(
        default="all",
        description="all: every pair within gt_radius (what training samples positives and "
        "near misses from); loops: only pairs more than loop_exclude frames apart, the loop "
        "table's candidates, enough for validation and test towns at a fraction of the work; "
        "none: no table (a later session only queried against another: positions are its "
        "ground truth)",
    )

    @field_validator("sensor")
    @classmethod
    def _known_sensor(cls, v: str) -> str:
        if v not in CATALOGUE:
            raise ValueError(f"unknown sensor {v!r}; allowed: {', '.join(sensor_names())}")
        return v

    @field_validator("drive")
    @classmethod
    def _no_mount_in_drive(cls, v: dict) -> dict:
        mount = sorted(k for k in v if k.startswith("mount_"))
        if mount:
            raise ValueError(
                f"drive {mount}: the mounting is the config's own (mount, mount_height, "
                "mount_pitch_deg, mount_roll_deg), so the body, the poses and the manifest agree"
            )
        return v

    @field_validator("mount")
    @classmethod
    def _known_mount(cls, v: str) -> str:
        if v not in MOUNTINGS:
            raise ValueError(f"unknown mounting {v!r}; allowed: {', '.join(MOUNTINGS)}")
        return v

    @field_validator("split")
    @classmethod
    def _known_split(cls, v: str) -> str:
        if v not in ("train", "val", "test"):
            raise ValueError(f"unknown split {v!r}; allowed: train, val, test")
        return v

    @model_serializer(mode="wrap")
    def _dump(self, handler: SerializerFunctionWrapHandler) -> Any:
        """``firing_phase`` is dumped only where it is not the default, so the manifests
        and configs of every locked town read as they did before the field existed."""
        out = handler(self)
        if isinstance(out, dict) and out.get("firing_phase") == "locked":
            out.pop("firing_phase")
        return out

    def session_seed(self) -> list[int]:
        """Entropy of everything that changes between sessions (session 0: the seed alone,
        so first sessions stay byte-identical to those of earlier generator versions)."""
        return [self.seed] if self.session == 0 else [self.seed, 0x5E55, self.session]

    def loop_params(self) -> LoopParams:
        """The loop table's rules: ``loop_exclude``, ``loop_min_overlap``, and the
        protocol's 30 m radius (or ``gt_radius`` when the pair table is smaller)."""
        return LoopParams(
            exclude_recent_frames=self.loop_exclude,
            radius=min(30.0, self.gt_radius),
            min_overlap=self.loop_min_overlap,
        )

    def world_params(self) -> WorldParams:
        return WorldParams.from_dict(self.world)

    def mounting(self) -> Mounting:
        """The mounting with this drive's height and tilt."""
        return MOUNTINGS[self.mount].with_pose(
            self.mount_height, self.mount_pitch_deg, self.mount_roll_deg
        )

    def drive_params(self) -> DriveParams:
        m = self.mounting()
        base = {
            "rate_hz": CATALOGUE[self.sensor].rate_hz,
            "mount_height": m.height,
            "mount_pitch_deg": m.pitch_deg,
            "mount_roll_deg": m.roll_deg,
        }
        return DriveParams.from_dict({**base, **self.drive})

    def dynamics_params(self) -> DynamicsParams:
        return DynamicsParams.from_dict(self.dynamics)
