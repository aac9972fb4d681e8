"""What a training run starts from: its sequences (never a test split, always the model's
sensor), their range images behind global scan indices, the network and weights of a trained
start (``init``: a checkpoint or an exported encoder), and the real scans of the per-epoch
turn check. :func:`overlapmamba.train.train.train` runs the epochs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.datasets.base import Sequence
from overlapmamba.core.errors import DatasetError
from overlapmamba.core.sensors import SensorProfile, get_profile
from overlapmamba.train.checkpoint import read_checkpoint
from overlapmamba.train.errors import ConfigError
from overlapmamba.train.model import OverlapMambaConfig
from overlapmamba.train.rangecache import range_images
from overlapmamba.train.realscans import RealTurns, native_input, real_turns, turned_image
from overlapmamba.train.train_config import TrainConfig


class Images:
    """Range images of several sequences behind global scan indices."""

    def __init__(self, seqs: list[Sequence], profile: SensorProfile, progress: bool) -> None:
        self.seqs, self.profile = seqs, profile
        self.parts = [range_images(s, profile, progress=progress) for s in seqs]
        self.offsets = np.cumsum([0, *[len(p) for p in self.parts]])

    def _locate(self, idx: np.ndarray) -> list[tuple[int, int]]:
        k = np.searchsorted(self.offsets, idx, side="right") - 1
        return [(int(s), int(i - self.offsets[s])) for s, i in zip(k, idx, strict=True)]

    def __getitem__(self, idx: np.ndarray) -> np.ndarray:
        return np.stack([self.parts[s][i] for s, i in self._locate(idx)])

    def turned(self, idx: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """The scans ``idx`` re-projected after a turn by ``theta`` degrees (the turn term)."""
        return np.stack(
            [
                turned_image(self.seqs[s].points(i).xyz, t, self.profile)
                for (s, i), t in zip(self._locate(idx), theta, strict=True)
            ]
        )


def open_split(path: Path, cfg: OverlapMambaConfig, role: str) -> Sequence:
    seq = open_sequence(path)
    manifest = path / "manifest.json"
    if manifest.is_file():
        meta = json.loads(manifest.read_text()).get("config", {})
        if role == "training" and meta.get("split") == "test":
            raise DatasetError(f"{path} is a test split: it is never trained on")
        if meta.get("sensor", cfg.sensor) != cfg.sensor:
            raise DatasetError(
                f"{path} was recorded with {meta['sensor']}, the model expects {cfg.sensor}"
            )
    return seq


def model_profile(cfg: OverlapMambaConfig) -> SensorProfile:
    profile = get_profile(cfg.sensor)
    if (profile.height, profile.width) != (cfg.height, cfg.width):
        raise ConfigError(
            f"model input {cfg.height}×{cfg.width} does not match sensor {cfg.sensor}'s "
            f"range images ({profile.height}×{profile.width})"
        )
    return profile


def start_config(
    train_cfg: TrainConfig, model_cfg: OverlapMambaConfig | None
) -> OverlapMambaConfig:
    """The network config of ``init``'s file; a different one given alongside is refused
    (the runtime-only scan settings aside)."""
    path = train_cfg.init_path()
    assert path is not None
    if not path.is_file():
        raise ConfigError(f"init {train_cfg.init!r}: {path} does not exist")
    if path.suffix == ".onnx":
        from overlapmamba.train.modelfile import read_metadata

        try:
            cfg = OverlapMambaConfig.from_dict(read_metadata(path).network)
        except ValueError as err:
            raise ConfigError(f"init {train_cfg.init!r}: {err}") from None
    else:
        cfg = OverlapMambaConfig.from_dict(read_checkpoint(path)["model_config"])
    if model_cfg is not None:
        runtime = ("scan_backend", "scan_chunk")
        a, b = cfg.to_dict(), model_cfg.to_dict()
        differ = sorted(k for k in a if k not in runtime and a[k] != b.get(k))
        if differ:
            raise ConfigError(
                f"init {train_cfg.init!r} is a network with other "
                + ", ".join(f"{k} ({a[k]!r}, not {b.get(k)!r})" for k in differ)
                + ": drop the model settings or start from a matching network"
            )
    return cfg


def start_weights(train_cfg: TrainConfig, progress: bool) -> dict[str, torch.Tensor]:
    """``init``'s weights: a checkpoint's state dict, or an exported encoder's recovered
    (and checked against onnxruntime: :func:`overlapmamba.train.recover.recover`)."""
    path = train_cfg.init_path()
    assert path is not None
    if path.suffix == ".onnx":
        from overlapmamba.train.recover import recover

        model, _, check = recover(path)
        if progress:
            tqdm.write(
                f"start: {path}'s weights recovered (descriptors within "
                f"{check['descriptor_max_abs']:.1e} of onnxruntime's)"
            )
        return model.state_dict()
    return read_checkpoint(path)["state_dict"]


def real_turn_scans(path: Path | None, profile: SensorProfile, progress: bool) -> RealTurns | None:
    """The real scans of the per-epoch turn check, projected once; None (with a note) when
    the check is off or the folder is missing."""
    if path is None:
        return None
    if not (path / "velodyne").is_dir():
        if progress:
            tqdm.write(f"note: no real scans at {path}: the per-epoch turn check is skipped")
        return None
    return real_turns(open_sequence(path), native_input(profile))
