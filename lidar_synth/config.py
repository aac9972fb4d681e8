"""Everything that determines a generated sequence: :class:`GenConfig` (seed, frames,
session, sensor, world/drive/dynamics overrides, the ground-truth table's extent)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from lidar_core.overlap import LoopParams
from lidar_synth.dynamics import DynamicsParams
from lidar_synth.lidar import LIDAR_MODELS, get_lidar
from lidar_synth.trajectory import DriveParams
from lidar_synth.world import WorldParams


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
    sensor: str = "kitti-hdl64"
    preset: str | None = None
    split: str = Field(default="train", description="train, val or test; test is never trained on")
    world: dict = Field(default_factory=dict, description="WorldParams overrides")
    drive: dict = Field(default_factory=dict, description="DriveParams overrides")
    dynamics: dict = Field(default_factory=dict, description="DynamicsParams overrides")
    gt_radius: float = Field(default=30.0, gt=0, le=200)
    loop_exclude: int = Field(default=100, ge=0)
    loop_min_overlap: float = Field(default=0.3, ge=0, le=1)
    pair_table: Literal["all", "loops"] = Field(
        default="all",
        description="all: every pair within gt_radius (what training samples positives and "
        "near misses from); loops: only pairs more than loop_exclude frames apart, the loop "
        "table's candidates, enough for validation and test towns at a fraction of the work",
    )

    @field_validator("sensor")
    @classmethod
    def _known_sensor(cls, v: str) -> str:
        if v not in LIDAR_MODELS:
            raise ValueError(f"unknown sensor {v!r}; allowed: {', '.join(LIDAR_MODELS)}")
        return v

    @field_validator("split")
    @classmethod
    def _known_split(cls, v: str) -> str:
        if v not in ("train", "val", "test"):
            raise ValueError(f"unknown split {v!r}; allowed: train, val, test")
        return v

    def session_seed(self) -> list[int]:
        """Entropy of everything that changes between sessions (session 0: the seed alone,
        so first sessions stay byte-identical to those of earlier generator versions)."""
        return [self.seed] if self.session == 0 else [self.seed, 0x5E55, self.session]

    def loop_params(self) -> LoopParams:
        """The loop table's rules: ``loop_exclude``, ``loop_min_overlap``, and the
        protocol's 30 m radius (or ``gt_radius`` when the pair table is smaller)."""
        return LoopParams(
            exclude_recent=self.loop_exclude,
            radius=min(30.0, self.gt_radius),
            min_overlap=self.loop_min_overlap,
        )

    def world_params(self) -> WorldParams:
        return WorldParams.from_dict(self.world)

    def drive_params(self) -> DriveParams:
        lidar = get_lidar(self.sensor)
        base = {"rate_hz": lidar.rate_hz, "mount_height": lidar.mount_height}
        return DriveParams.from_dict({**base, **self.drive})

    def dynamics_params(self) -> DynamicsParams:
        return DynamicsParams.from_dict(self.dynamics)
