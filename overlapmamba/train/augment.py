"""Training augmentation on range images: what a deployed sensor does to its scans.

Every transform works on a batch of cached range images (B, H, W), with the epoch's own
random generator (so ``--resume`` stays exact), and draws its strength per scan between none
and the configured maximum, so a batch always mixes clean and degraded scans.

- ``tilt_deg``: the sensor tilted by up to this angle about a random horizontal axis (a
  mount that is not level, a vehicle pitching or rolling). A point at azimuth θ changes
  elevation by ≈ τ·cos(θ − φ), so every column shifts vertically by its own number of rows;
  rows shifted in from outside the field of view are empty.
- ``yaw_jitter``: a turn by a fraction of a column. A turn by a whole number of columns rolls
  the image, which the circular network ignores exactly; a fraction of a column re-bins
  every point. Each pixel takes its value from the previous column with probability equal to
  the fraction, as the points of a re-binned pixel come from either neighbour.
- ``yaw_roll``: whole-column rolls. They teach the circular network nothing (it is exactly
  invariant to them), so by default only non-circular models get them.
- ``dropout``: up to this share of the returns lost (rain, dust, a dirty window, a sparser
  driver setting).
- ``beam_dropout``: up to this share of the rows emptied whole (a sensor with fewer beams, or
  beams that another sensor's elevation grid leaves out).
- ``sensor_like``: the probability that a scan is seen as another catalogue sensor sees it
  (drawn uniformly among ``sensor_like_names``, default every catalogue sensor whose profile
  is not the model's): each row of the model's input takes the row nearest the elevation of
  the beam that sensor's scan would put there (:func:`~overlapmamba.core.sensors.beams.row_beams`,
  as the service projects it), rows it has no beam for are emptied, and so are returns
  beyond its range limits and columns its firings per turn do not reach (at a random phase).
  Row for row, the same image the service makes from that sensor's scan of the same place,
  but for the beams' exact elevations (within half a row) and the mount. Only scans of the
  model's own sensor are seen so (the ``native`` mask of a batch): a scan of another sensor
  already has its sensor's look.
- ``far_loss``: returns lost in proportion to their range, up to this share at the model's
  maximum range (a weaker laser, a darker surface: far returns go first). Other sensors'
  renderings lose far returns so (an Ouster's markedly more than the HDL-64E's scans of
  the same place), and a network trained without it moves far from a scan with them
  missing.
- ``range_cut``: the probability that a scan loses every return at or beyond a range drawn
  between ``range_cut_min_m`` and the model's maximum range (a sensor that reaches less far:
  an OS0-128 sees nothing beyond 50 m, where an HDL-64E's map holds returns to 80 m). Where
  the ``elevation-reach`` input cuts every scan at 50 m, always, and so loses what sensors that
  do see far agree on, this asks the network to place a scan near its place whether or not
  its far returns are there. The image keeps each cell's nearest return, so emptying the
  cells at or beyond the cut is cutting the scan's points there.
- ``range_noise``: Gaussian range noise with σ up to this many metres.
- ``fov_crop``: the probability that a scan keeps only a sector of its horizontal field of
  view, between ``fov_min_deg`` and 360° (a sensor partly occluded by the vehicle or a
  neighbouring mount).

Measured on 2 cores, batch 16 of 64 × 900 images: see ``benchmarks/training.py``.
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np
from pydantic import ConfigDict, model_validator

from overlapmamba.core.configs import Config
from overlapmamba.core.sensors import SensorProfile
from overlapmamba.core.sensors.beams import row_beams
from overlapmamba.core.sensors.catalogue import CATALOGUE, Sensor
from overlapmamba.train.errors import ConfigError


class AugmentConfig(Config):
    """Off by default but for whole-column rolls of non-circular models: measured on the
    tiny towns (README, Training: choosing the recipe), these transforms lowered validation
    F1max at 120 steps. :data:`ROBUST` is the full set, for the at-scale comparison."""

    model_config = ConfigDict(frozen=True)
    config_name: ClassVar[str] = "augmentation"
    config_error: ClassVar[type[Exception]] = ConfigError

    tilt_deg: float = 0.0
    yaw_jitter: bool = False
    yaw_roll: bool | None = None  # None: only when the model is not circular
    dropout: float = 0.0
    beam_dropout: float = 0.0
    range_noise: float = 0.0
    fov_crop: float = 0.0
    fov_min_deg: float = 180.0
    sensor_like: float = 0.0
    far_loss: float = 0.0
    range_cut: float = 0.0
    range_cut_min_m: float = 40.0
    sensor_like_names: tuple[str, ...] = ()  # empty: every catalogue sensor but the model's

    @model_validator(mode="after")
    def _check(self) -> AugmentConfig:
        checks = {
            "tilt_deg": 0 <= self.tilt_deg <= 15,
            "dropout": 0 <= self.dropout < 1,
            "beam_dropout": 0 <= self.beam_dropout < 1,
            "range_noise": 0 <= self.range_noise <= 1,
            "fov_crop": 0 <= self.fov_crop <= 1,
            "fov_min_deg": 0 < self.fov_min_deg <= 360,
            "sensor_like": 0 <= self.sensor_like <= 1,
            "far_loss": 0 <= self.far_loss <= 1,
            "range_cut": 0 <= self.range_cut <= 1,
            "range_cut_min_m": self.range_cut_min_m > 0,
        }
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise ConfigError(
                f"augmentation {bad[0]}={getattr(self, bad[0])!r} is out of range; allowed: "
                "tilt_deg 0–15, dropout and beam_dropout 0–<1, range_noise 0–1 m, fov_crop 0–1, "
                "fov_min_deg 0–360, sensor_like, far_loss and range_cut 0–1, range_cut_min_m > 0 "
                "(and below the model's maximum range)"
            )
        unknown = sorted(set(self.sensor_like_names) - set(CATALOGUE))
        if unknown:
            raise ConfigError(
                f"augmentation sensor_like_names: {', '.join(unknown)} not in the catalogue; "
                f"allowed: {', '.join(sorted(CATALOGUE))}"
            )
        return self

    @classmethod
    def none(cls) -> AugmentConfig:
        """Nothing at all, not even the rolls of a non-circular model."""
        return cls(yaw_roll=False)


ROBUST = {"tilt_deg": 2.0, "yaw_jitter": True, "dropout": 0.2, "range_noise": 0.03, "fov_crop": 0.1}
"""The full set: a few degrees of tilt, sub-column turns, up to 20 % of returns lost, up to
3 cm of range noise, and one scan in ten seeing only 180–360° of its field of view."""


class Augmenter:
    """Applies an :class:`AugmentConfig` to batches of range images of one sensor profile."""

    def __init__(self, cfg: AugmentConfig, profile: SensorProfile, circular: bool) -> None:
        self.cfg = cfg
        self.empty = np.float32(profile.empty_value)
        self.H, self.W = profile.height, profile.width
        self.rows_per_deg = profile.height / profile.fov_deg
        self.max_range = np.float32(profile.max_range)
        self.roll = (not circular) if cfg.yaw_roll is None else cfg.yaw_roll
        # Azimuth of each column's centre (overlapmamba.core.projection: atan2 = π(1 − 2u/W)).
        self.azimuth = np.pi * (1 - 2 * (np.arange(self.W) + 0.5) / self.W)
        self.looks = [SensorLook(profile, s) for s in _other_sensors(cfg, profile)]
        if cfg.range_cut and cfg.range_cut_min_m >= profile.max_range:
            raise ConfigError(
                f"augmentation range_cut_min_m={cfg.range_cut_min_m} m must be below the "
                f"model's maximum range ({profile.max_range} m): the cut is drawn between them"
            )

    def __call__(
        self, images: np.ndarray, rng: np.random.Generator, native: np.ndarray | None = None
    ) -> np.ndarray:
        """(B, H, W) → float32 (B, H, W), a new array. ``native``: (B,) bool, the scans of
        the model's own sensor (None: all), the only ones ``sensor_like`` changes."""
        x = np.array(images, dtype=np.float32)
        if x.ndim != 3 or x.shape[1:] != (self.H, self.W):
            raise ValueError(f"expected range images (B, {self.H}, {self.W}), got {x.shape}")
        own = np.ones(len(x), bool) if native is None else np.asarray(native, bool)
        if own.shape != (len(x),):
            raise ValueError(f"native: one flag a scan ({len(x)}), got shape {own.shape}")
        c = self.cfg
        for img, mine in zip(x, own, strict=True):  # each transform draws for every scan
            # (so the stream never depends on data)
            if c.tilt_deg:
                self._tilt(img, rng.uniform(0, c.tilt_deg), rng.uniform(0, 2 * np.pi))
            if c.sensor_like:  # drawn only when on, as beam_dropout
                seen, pick, phase = (
                    rng.random() < c.sensor_like,
                    rng.integers(1 << 30),
                    rng.random(),
                )
                if seen and mine and self.looks:
                    self.looks[int(pick) % len(self.looks)].apply(img, phase, self.empty)
            if c.yaw_jitter:
                frac = rng.random()
                pick = rng.random(img.shape) < frac
                img[:] = np.where(pick, np.roll(img, 1, axis=-1), img)
            if self.roll:
                img[:] = np.roll(img, int(rng.integers(self.W)), axis=-1)
            valid = img != self.empty
            if c.dropout:
                lost = rng.random(img.shape) < rng.uniform(0, c.dropout)
                img[lost & valid] = self.empty
                valid &= ~lost
            if c.beam_dropout:  # drawn only when on: the streams of runs without it stay
                rows = rng.random(self.H) < rng.uniform(0, c.beam_dropout)
                img[rows] = self.empty
                valid[rows] = False
            if c.far_loss:  # drawn only when on
                share = rng.uniform(0, c.far_loss) / self.max_range
                lost = rng.random(img.shape) < share * np.maximum(img, 0)
                img[lost & valid] = self.empty
                valid &= ~lost
            if c.range_cut:  # drawn only when on
                cut, at = rng.random() < c.range_cut, rng.uniform(c.range_cut_min_m, self.max_range)
                if cut:
                    far = valid & (img >= np.float32(at))
                    img[far] = self.empty
                    valid &= ~far
            if c.range_noise:
                sigma = rng.uniform(0, c.range_noise)
                noise = rng.standard_normal(img.shape).astype(np.float32) * np.float32(sigma)
                img[valid] = np.maximum(img[valid] + noise[valid], np.float32(1e-3))
            if c.fov_crop:
                crop = rng.random() < c.fov_crop
                keep_deg, start = rng.uniform(c.fov_min_deg, 360), int(rng.integers(self.W))
                if crop:
                    kept = math.ceil(keep_deg / 360 * self.W)
                    cols = (start + np.arange(kept, self.W)) % self.W
                    img[:, cols] = self.empty
        return x

    def seen_as_other(self, images: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """(K, H, W) images of the model's own sensor → each as one other sensor (drawn
        uniformly among ``sensor_like_names``, at a random firing phase) would see it: the
        copies of the sensor term (``look_weight``), a new array, nothing else changed."""
        x = np.array(images, dtype=np.float32)
        if x.ndim != 3 or x.shape[1:] != (self.H, self.W):
            raise ValueError(f"expected range images (K, {self.H}, {self.W}), got {x.shape}")
        if not self.looks:
            raise ValueError(
                "no other sensor to see the scans as: sensor_like_names names "
                "only the model's own sensor"
            )
        for img in x:
            pick, phase = rng.integers(1 << 30), rng.random()
            self.looks[int(pick) % len(self.looks)].apply(img, phase, self.empty)
        return x

    def _tilt(self, img: np.ndarray, tilt_deg: float, axis: float) -> None:
        shift = np.rint(tilt_deg * self.rows_per_deg * np.cos(self.azimuth - axis)).astype(int)
        if not shift.any():
            return
        rows = np.arange(self.H)[:, None] - shift[None, :]  # (H, W) source row of each pixel
        inside = (rows >= 0) & (rows < self.H)
        src = img[np.clip(rows, 0, self.H - 1), np.arange(self.W)[None, :]]
        img[:] = np.where(inside, src, self.empty)


def _other_sensors(cfg: AugmentConfig, profile: SensorProfile) -> list[Sensor]:
    names = cfg.sensor_like_names or tuple(sorted(CATALOGUE))
    return [CATALOGUE[n] for n in names if CATALOGUE[n].profile() != profile]


class SensorLook:
    """How ``sensor``'s scan of a place fills the input of a model on ``profile``, in terms
    of the model's own image of that place: the source row of each row (−1: empty), the
    range limits, and which columns a turn of its firings reaches."""

    def __init__(self, profile: SensorProfile, sensor: Sensor) -> None:
        self.name = sensor.name
        H = profile.height
        pitch = (profile.fov_up_deg - profile.fov_down_deg) / H
        beams = row_beams(profile, sensor, "elevation")
        el = np.asarray(sensor.elevations_deg, np.float64)
        at = (profile.fov_up_deg - el[np.maximum(beams, 0)]) / pitch  # in rows, from the top
        src = np.floor(at).astype(np.int64)
        self.rows = np.where((beams >= 0) & (src >= 0) & (src < H), src, -1)
        # Where the model sensor's own row is empty (its beams are not one a row), the
        # neighbouring row on the beam's side of the row centre stands in.
        near = np.clip(np.where(at - src >= 0.5, src + 1, src - 1), 0, H - 1)
        self.second = np.where(self.rows >= 0, near, -1)
        self.min_range, self.max_range = np.float32(sensor.min_range), np.float32(sensor.max_range)
        self.columns, self.W = sensor.columns, profile.width

    def reached(self, phase: float) -> np.ndarray:
        """(W,) bool: the columns a turn of firings at ``phase`` (of one firing's step) hits."""
        if self.columns >= self.W:
            return np.ones(self.W, bool)
        hit = np.floor((np.arange(self.columns) + phase) * self.W / self.columns).astype(int)
        mask = np.zeros(self.W, bool)
        mask[hit % self.W] = True
        return mask

    def apply(self, img: np.ndarray, phase: float, empty: np.float32) -> None:
        """In place on one (H, W) image."""
        seen = img[np.maximum(self.rows, 0)]
        seen = np.where(seen == empty, img[np.maximum(self.second, 0)], seen)
        valid = (self.rows >= 0)[:, None] & self.reached(phase)[None, :] & (seen != empty)
        valid &= (seen > self.min_range) & (seen < self.max_range)
        img[:] = np.where(valid, seen, empty)
