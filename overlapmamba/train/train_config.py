"""The training recipe: every setting of ``overlapmamba train`` as one config that travels
in checkpoints (``TrainConfig``), and ``.json``/``.toml`` config files.

A config file has a ``[model]`` table (``OverlapMambaConfig`` fields), a ``[train]`` table
(these fields) and, inside it, ``[train.augment]`` (``AugmentConfig`` fields).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import ClassVar

from pydantic import Field, model_validator
from torch import Tensor

from overlapmamba.core.configs import Config
from overlapmamba.train.augment import AugmentConfig
from overlapmamba.train.errors import ConfigError
from overlapmamba.train.losses import BATCH_LOSSES, SCALES, BandRanking, BatchLoss, ImTrihardParams

ROOT = Path(__file__).resolve().parents[2]


def _located(text: str) -> Path | None:
    """A path setting: as given when it exists from here, else relative to the repository
    root; None when empty (off)."""
    if not text:
        return None
    path = Path(text)
    return path if path.is_absolute() or path.exists() else ROOT / path


REAL_SCANS = "../shared/data/kitti00_0000-0100"  # relative to the repository root
SCHEDULE = "warmup-step/1"  # the learning-rate schedule's name in checkpoints (resume checks it)


class TrainConfig(Config):
    config_name: ClassVar[str] = "training"
    config_error: ClassVar[type[Exception]] = ConfigError

    epochs: int = 10
    epoch_scans: int = 2000  # scans drawn per epoch
    batch_size: int = 16  # groups of 1 + group_positives + group_negatives (default 4)
    lr: float = 1e-4  # Adam; the reference's 5e-6 barely moves a freshly initialised head
    warmup_steps: int = 50  # linear learning-rate warm-up over the first steps of the run
    step_size: int = 5  # × gamma every step_size epochs (reference: 5, 0.9)
    gamma: float = 0.9
    loss: str = "imtrihard"  # imtrihard (paper eq. 13) or triplet (OverlapTransformer)
    # ImTrihard margin α, in units of the batch's spread with the normalised scale (measured
    # on the tiny towns, README "Training: measured"); the paper-era constants 0.5 / 0.1 on
    # absolute distances are the ablation row abl-oldloss
    alpha: float = 0.5
    lam: float = 0.0  # ImTrihard compression weight λ
    k_p: float = 1.0
    k_n: float = 1.0
    hinge: bool = True
    margin: float = 0.5  # triplet margin m
    margin_scale: str = "normalised"  # absolute, relative or normalised (losses.SCALES)
    positive_threshold: float = 0.3  # overlap above this: positive
    negative_threshold: float = 0.1  # overlap at most this: negative; in between: neither
    revisit_fraction: float = 0.5  # anchors whose first positive is an old pass
    group_positives: int = 2  # a batch is groups of anchor + positives + near misses
    group_negatives: int = 1
    # Hard negatives mined by the current model (overlapmamba.train.mining): the share of groups
    # whose negative is a distant look-alike instead of the near miss (0: off), from a pool
    # of mine_pool training scans described at each epoch's start, mine_top per anchor.
    hard_negatives: float = 0.0
    mine_pool: int = 2000
    mine_top: int = 10
    # The ambiguous band ranked below the positives (losses.BandRanking), from epoch
    # band_from_epoch on: band_weight (0: off) and band_alpha (in the margin's units) set the
    # term, band_share the share of the non-mined groups whose near miss is a band scan.
    # Epochs before band_from_epoch draw and train exactly as without it.
    band_weight: float = 0.0
    band_alpha: float = 0.2
    band_share: float = 0.0
    band_from_epoch: int = 1
    # Train on towns of any catalogue sensor (gen-data --sensor), each sensor's beams put
    # into the model's input by elevation as the exported model takes them; renderings of
    # one drive share its pair table (overlapmamba.train.drives). Validation stays the
    # model's own sensor.
    any_sensor: bool = False
    # Renderings of the validation drive by other sensors, scored every epoch on their own
    # and against the validation scans (overlapmamba.train.valsensors); select_on "sensors"
    # keeps the epoch with the best mean F1max over them all as best.pt ("val": val's alone).
    val_sensors: list[str] = Field(default_factory=list)
    select_on: str = "val"
    augment: dict = Field(default_factory=dict)  # AugmentConfig overrides
    # Turn consistency (losses.consistency): the first turn_scans scans of each batch are
    # also fed turned about z by a random continuous angle (re-projected from their points,
    # then augmented like the batch),
    # and turn_weight × their squared distance to the unturned scan, in units of the batch's
    # spread, joins the loss (0: off, and nothing is drawn for it); a turned copy nearer
    # than turn_allowance (in units of the spread too) costs nothing.
    turn_weight: float = 0.0
    turn_scans: int = 4
    turn_allowance: float = 0.0
    # Sensor consistency (losses.consistency, the same measure): up to look_scans scans of
    # the model's own sensor in each batch are also fed as another catalogue sensor sees
    # them (augment.Augmenter.seen_as_other, then augmented like the batch), and
    # look_weight × their squared distance to the scan as the batch has it, in units of the
    # batch's spread, joins the loss (0: off, and nothing is drawn for it). On the bev
    # input, up to look_scans scans of any sensor with a sparser one in the catalogue, seen
    # through that sensor's beams (train_inputs.Images.sparser).
    look_weight: float = 0.0
    look_scans: int = 4
    # Start from a trained network instead of the seed's weights: a checkpoint (.pt) or an
    # exported encoder (.onnx, weights recovered exactly: overlapmamba.train.recover), relative to
    # the repository root unless it exists from here. freeze_bn keeps every batch norm in
    # eval mode (statistics and all), which a recovered network needs: its norms were folded
    # into the convolutions and have no statistics to continue.
    init: str = ""
    freeze_bn: bool = False
    recalibrate_batches: int = 20  # epoch 0: batch-norm statistics from this many batches
    log_every: int = 10  # steps per health record
    real: str = REAL_SCANS  # real scans whose turned copies are checked every epoch ("": off)
    seed: int = 0
    device: str = "cpu"  # cpu or cuda

    @model_validator(mode="after")
    def _check(self) -> TrainConfig:
        odd = [k for k, v in self.__dict__.items() if isinstance(v, float) and not math.isfinite(v)]
        if odd:  # NaN passes every `x < 0` test below, and trains on NaN losses in silence
            raise ConfigError(f"{', '.join(odd)} must be finite numbers, got NaN or infinity")
        for name in ("alpha", "lam", "k_p", "k_n", "margin"):
            value = getattr(self, name, None)
            if isinstance(value, int | float) and value < 0:
                raise ConfigError(f"{name} must be ≥ 0, got {value}")
        fraction = getattr(self, "revisit_fraction", None)
        if isinstance(fraction, int | float) and not 0 <= fraction <= 1:
            raise ConfigError(f"revisit_fraction must be within 0 … 1, got {fraction}")
        if not 0 <= self.seed < 2**63:  # numpy's seed sequence and torch's manual_seed
            raise ConfigError(f"seed must be within 0 … 2**63 − 1, got {self.seed}")
        if self.loss not in BATCH_LOSSES:
            raise ConfigError(f"unknown loss {self.loss!r}; allowed: {', '.join(BATCH_LOSSES)}")
        names = ("epochs", "epoch_scans", "batch_size", "step_size", "log_every")
        for name in (*names, "group_positives", "mine_top"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be ≥ 1, got {getattr(self, name)}")
        for name in ("warmup_steps", "recalibrate_batches", "group_negatives"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name} must be ≥ 0, got {getattr(self, name)}")
        if not (self.lr > 0 and 0 < self.gamma <= 1 and 0 <= self.positive_threshold < 1):
            raise ConfigError("need lr > 0, 0 < gamma ≤ 1 and 0 ≤ positive_threshold < 1")
        if not 0 <= self.negative_threshold <= self.positive_threshold:
            raise ConfigError(
                f"negative_threshold {self.negative_threshold} is not allowed: use 0 ≤ "
                f"negative_threshold ≤ positive_threshold ({self.positive_threshold})"
            )
        group = 1 + self.group_positives + self.group_negatives
        if self.batch_size % group:
            raise ConfigError(
                f"batch_size {self.batch_size} is not allowed: use a multiple of {group} (an "
                f"anchor, {self.group_positives} positives and {self.group_negatives} near "
                "misses per group)"
            )
        if not 0 <= self.hard_negatives <= 1 or self.mine_pool < 2:
            raise ConfigError(
                f"hard_negatives {self.hard_negatives} / mine_pool {self.mine_pool} are not "
                "allowed: use 0 ≤ hard_negatives ≤ 1 and mine_pool ≥ 2"
            )
        if not (self.band_weight >= 0 and self.band_alpha >= 0 and 0 <= self.band_share <= 1):
            raise ConfigError(
                f"band_weight {self.band_weight}, band_alpha {self.band_alpha} and band_share "
                f"{self.band_share} are not allowed: use band_weight ≥ 0, band_alpha ≥ 0 and "
                "0 ≤ band_share ≤ 1"
            )
        if self.band_from_epoch < 1:
            raise ConfigError(f"band_from_epoch must be ≥ 1, got {self.band_from_epoch}")
        if self.band_weight > 0 and self.loss != "imtrihard":
            raise ConfigError(
                f"band_weight > 0 needs loss 'imtrihard' (the band term is ImTrihard's); got "
                f"{self.loss!r}"
            )
        if self.turn_weight < 0 or self.turn_scans < 1 or not 0 <= self.turn_allowance < 1:
            raise ConfigError(
                f"turn_weight {self.turn_weight} / turn_scans {self.turn_scans} / "
                f"turn_allowance {self.turn_allowance} are not allowed: use turn_weight ≥ 0, "
                "turn_scans ≥ 1 and 0 ≤ turn_allowance < 1 (a turned copy one spread away is "
                "as far as any other scan)"
            )
        if self.turn_scans > self.batch_size:
            raise ConfigError(
                f"turn_scans {self.turn_scans} is more than the batch ({self.batch_size}): "
                "turned copies are taken from the batch's own scans"
            )
        if self.look_weight < 0 or not 1 <= self.look_scans <= self.batch_size:
            raise ConfigError(
                f"look_weight {self.look_weight} / look_scans {self.look_scans} are not "
                f"allowed: use look_weight ≥ 0 and 1 ≤ look_scans ≤ batch_size "
                f"({self.batch_size}): the copies are of the batch's own scans"
            )
        if self.init.endswith(".onnx") and not self.freeze_bn:
            raise ConfigError(
                f"init {self.init!r} is an exported encoder: its batch norms were folded and "
                "have no statistics to train with; set freeze_bn = true"
            )
        if self.init and not self.init.endswith((".onnx", ".pt")):
            raise ConfigError(
                f"init {self.init!r}: allowed are a checkpoint (.pt) or an exported encoder (.onnx)"
            )
        if self.device not in ("cpu", "cuda"):
            raise ConfigError(f"device {self.device!r} is not allowed; allowed: cpu, cuda")
        if self.margin_scale not in SCALES:
            raise ConfigError(
                f"margin_scale {self.margin_scale!r} is unknown; allowed: {', '.join(SCALES)}"
            )
        if self.select_on not in ("val", "sensors"):
            raise ConfigError(f"select_on {self.select_on!r} is not allowed; allowed: val, sensors")
        if self.select_on == "sensors" and not self.val_sensors:
            raise ConfigError(
                "select_on 'sensors' needs val_sensors: renderings of the validation drive by "
                "other sensors (e.g. data/synth/val-vlp16 beside data/synth/val-kitti-hdl64)"
            )
        self.augment_config()  # refuses unknown or out-of-range augmentation settings
        return self

    def real_path(self) -> Path | None:
        """The real scans of the per-epoch turn check: as given when it exists from here,
        else relative to the repository root; None when the check is off."""
        return _located(self.real)

    def init_path(self) -> Path | None:
        """The network the run starts from (as given when it exists from here, else relative
        to the repository root); None: the seed's fresh weights."""
        return _located(self.init)

    def augment_config(self) -> AugmentConfig:
        return AugmentConfig.from_dict(self.augment)

    def band_on(self, epoch: int) -> bool:
        """Whether epoch ``epoch`` trains with the band term and draws band scans."""
        return epoch >= self.band_from_epoch and (self.band_weight > 0 or self.band_share > 0)

    def loss_fn(self, epoch: int = 1) -> Callable[[Tensor, Tensor], BatchLoss]:
        """The batch loss of epoch ``epoch`` (the band term from ``band_from_epoch`` on)."""
        fn = BATCH_LOSSES[self.loss]
        kw: dict = {"negative": self.negative_threshold, "scale": self.margin_scale}
        if self.loss == "imtrihard":
            p = ImTrihardParams(self.alpha, self.lam, self.k_p, self.k_n, self.hinge)
            if self.band_on(epoch) and self.band_weight > 0:
                kw["band"] = BandRanking(self.band_weight, self.band_alpha)
            return lambda d, ov: fn(d, ov, self.positive_threshold, p, **kw)
        return lambda d, ov: fn(d, ov, self.positive_threshold, self.margin, **kw)

    def lr_factor(self, step: int, steps_per_epoch: int) -> float:
        """Learning-rate multiplier at a global step: linear warm-up, then × gamma every
        ``step_size`` epochs."""
        warm = min(1.0, (step + 1) / self.warmup_steps) if self.warmup_steps else 1.0
        return warm * self.gamma ** ((step // steps_per_epoch) // self.step_size)


def load_config_file(path: Path) -> tuple[dict, dict]:
    """``{"model": {...}, "train": {...}}`` from .json or .toml → (model dict, train dict)."""
    if not path.is_file():
        raise ConfigError(f"config file {path} does not exist")
    import tomllib

    if path.suffix not in (".json", ".toml"):
        raise ConfigError(f"{path.name}: allowed config suffixes are .json and .toml")
    try:
        text = path.read_text(encoding="utf-8")
        raw = json.loads(text) if path.suffix == ".json" else tomllib.loads(text)
    except (UnicodeDecodeError, json.JSONDecodeError, tomllib.TOMLDecodeError) as err:
        raise ConfigError(
            f"config file {path} is not valid {path.suffix[1:].upper()}: {err}"
        ) from None
    if not isinstance(raw, dict):
        raise ConfigError(f"config file {path} holds {type(raw).__name__}; allowed: a table")
    extra = sorted(set(raw) - {"model", "train"})
    if extra:
        raise ConfigError(f"{path}: unknown sections {extra}; allowed: model, train")
    sections = {k: raw.get(k, {}) for k in ("model", "train")}
    for key, value in sections.items():
        if not isinstance(value, dict):
            raise ConfigError(
                f"{path}: section {key!r} is {type(value).__name__} {value!r}; allowed: a table"
            )
    return dict(sections["model"]), dict(sections["train"])
