"""What a training run starts from: its sequences (never a test split, always the model's
sensor), their range images behind global scan indices, the copies of a batch's scans the
turn and sensor terms compare them with, the network and weights of a trained start
(``init``: a checkpoint or an exported encoder), and the real scans of the per-epoch turn
check. :func:`overlapmamba.train.train.train` runs the epochs."""

from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.datasets.base import Sequence
from overlapmamba.core.errors import DatasetError
from overlapmamba.core.sensors import SensorProfile, get_profile, get_sensor
from overlapmamba.core.sensors.beams import beams_near, on_beams
from overlapmamba.core.sensors.catalogue import CATALOGUE
from overlapmamba.core.sensors.input import BEV_MODES, Mode, SensorInput
from overlapmamba.train.augment import Augmenter
from overlapmamba.train.checkpoint import input_of_mode, read_checkpoint
from overlapmamba.train.errors import ConfigError
from overlapmamba.train.model import OverlapMambaConfig
from overlapmamba.train.rangecache import range_images
from overlapmamba.train.realscans import (
    RealTurns,
    real_turns,
    turned_image,
    turned_points,
)
from overlapmamba.train.train_config import TrainConfig


def training_input(
    profile: SensorProfile, seq: Sequence, mode: Mode = "elevation"
) -> SensorInput | None:
    """How ``seq``'s scans enter the model in training, as the exported model will take
    them (its config's ``sensor_input``): None for the model's own sensor projected plainly,
    else its sensor's input by ``mode`` (``common``: every sensor's, the model's own too;
    ``structure`` levels a drive whose sensor sat elsewhere first: :func:`input_of_mode`)."""
    inp = input_of_mode(profile, seq, mode)
    return None if inp.native else inp


class Images:
    """Range images of several sequences behind global scan indices, each sequence's scans
    projected as its sensor's (:func:`training_input`); ``aligned``: each scan's columns
    start at its mean bearing (:mod:`overlapmamba.core.views`)."""

    def __init__(
        self,
        seqs: list[Sequence],
        profile: SensorProfile,
        progress: bool,
        mode: Mode = "elevation",
        aligned: bool = False,
    ) -> None:
        self.seqs, self.profile, self.mode, self.aligned = seqs, profile, mode, aligned
        self.inputs = [training_input(profile, s, mode) for s in seqs]
        self.parts = [
            range_images(s, profile, progress=progress, sensor=inp, aligned=aligned)
            for s, inp in zip(seqs, self.inputs, strict=True)
        ]
        self.offsets = np.cumsum([0, *[len(p) for p in self.parts]])

    def _locate(self, idx: np.ndarray) -> list[tuple[int, int]]:
        k = np.searchsorted(self.offsets, idx, side="right") - 1
        return [(int(s), int(i - self.offsets[s])) for s, i in zip(k, idx, strict=True)]

    def __getitem__(self, idx: np.ndarray) -> np.ndarray:
        return np.stack([self.parts[s][i] for s, i in self._locate(idx)])

    def native(self, idx: np.ndarray) -> np.ndarray:
        """(len(idx),) bool: which scans are of the model's own sensor."""
        return np.array([self.inputs[s] is None for s, _ in self._locate(idx)], bool)

    def turned(self, idx: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """The scans ``idx`` re-projected after a turn by ``theta`` degrees (the turn term)."""
        out = []
        for (s, i), t in zip(self._locate(idx), theta, strict=True):
            xyz, inp = self.seqs[s].points(i).xyz, self.inputs[s]
            if inp is None:
                out.append(turned_image(xyz, t, self.profile))
            else:
                out.append(inp.project(turned_points(xyz, t))[0])
        return np.stack(out)

    def sparser(
        self, idx: np.ndarray, rng: np.random.Generator, count: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """The ``bev`` input's look at another sensor → (at, images): of the scans ``idx``,
        the first ``count`` whose sensor has a catalogue sensor of fewer beams to be seen as
        (``at``: their places in ``idx``), each projected again from only its beams nearest
        that sensor's elevations (drawn uniformly among them): the same place as a sparser
        sensor sees it, where the range-image inputs' look (``augment.SensorLook``) moves
        rows a bird's-eye image does not have."""
        at: list[int] = []
        out: list[np.ndarray] = []
        for k, (s, i) in enumerate(self._locate(idx)):
            if len(at) == count:
                break
            inp = self.inputs[s]
            options = _sparser_beams(inp.sensor.name) if inp is not None else []
            if inp is None or not options:
                continue
            beams = options[int(rng.integers(len(options)))]
            xyz = on_beams(self.seqs[s].points(i).xyz, inp.sensor, beams)
            out.append(inp.project(xyz, aligned=self.aligned)[0])
            at.append(k)
        shape = (0, *self.parts[0].shape[1:])
        return np.array(at, np.int64), np.stack(out) if out else np.zeros(shape, np.float32)


@functools.cache
def _sparser_beams(name: str) -> list[np.ndarray]:
    """For catalogue sensor ``name``: its beams nearest each catalogue sensor's with fewer
    beams (two at least), one array a sensor, duplicates dropped."""
    sensor = CATALOGUE[name]
    found: dict[tuple[int, ...], np.ndarray] = {}
    for other in CATALOGUE.values():
        beams = beams_near(sensor, other)
        if other.beams < sensor.beams and len(beams) >= 2:
            found.setdefault(tuple(beams.tolist()), beams)
    return list(found.values())


def refuse_test_split(path: Path, meta: dict, role: str) -> None:
    """A test town is never trained on, nor validated on: the validation scores choose the
    checkpoint (best.pt), and a checkpoint chosen on a test town would report its own
    selection data. ``meta``: the folder's manifest's ``config``."""
    if meta.get("split") == "test":
        use = "trained on" if role == "training" else f"used for {role} (it selects best.pt)"
        raise DatasetError(
            f"{path} is a test split: it is never {use}; allowed: a train or val split"
        )


def open_split(
    path: Path, cfg: OverlapMambaConfig, role: str, any_sensor: bool = False
) -> Sequence:
    """A training or validation sequence: never a test split; of the model's own sensor
    unless ``any_sensor`` (training: each sensor's scans enter by :func:`training_input`)."""
    seq = open_sequence(path)
    manifest = path / "manifest.json"
    if manifest.is_file():
        meta = json.loads(manifest.read_text()).get("config", {})
        refuse_test_split(path, meta, role)
        sensor = meta.get("sensor", cfg.sensor)
        if sensor != cfg.sensor and not (any_sensor and role == "training"):
            hint = "" if role != "training" else " (train.any_sensor = true trains on any)"
            raise DatasetError(
                f"{path} was recorded with {sensor}, the model expects {cfg.sensor}{hint}"
            )
        if sensor != cfg.sensor:
            get_sensor(sensor)  # an unknown sensor is refused here, by name
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
    (the runtime-only scan settings aside). A network that averages views itself
    (``token_views``) trains on one image a scan: the same weights, its views met again at
    export (``overlapmamba export --meet tokens``). The input a continuation takes
    (``sensor_input``) is the file's (an exported file's metadata) unless a config given
    alongside names another: a network can be continued on another input. So is where its
    columns start (``column_phase``), unless the config given alongside sets it."""
    path = train_cfg.init_path()
    assert path is not None
    if not path.is_file():
        # looked for from here, then from the repository's root: both named
        looked = list(dict.fromkeys(str(p) for p in (Path(train_cfg.init).absolute(), path)))
        where = f"neither {' nor '.join(looked)} is" if len(looked) > 1 else f"{looked[0]} is not"
        raise ConfigError(f"init {train_cfg.init!r}: {where} a file")
    if path.suffix == ".onnx":
        from overlapmamba.train.modelfile import read_metadata

        try:
            meta = read_metadata(path)
            cfg = OverlapMambaConfig.from_dict(meta.network)
            cfg = cfg.model_copy(
                update={"sensor_input": meta.sensor_input, "column_phase": meta.column_phase}
            )
        except ValueError as err:
            raise ConfigError(f"init {train_cfg.init!r}: {err}") from None
    else:
        cfg = OverlapMambaConfig.from_dict(read_checkpoint(path)["model_config"])
    cfg = cfg.model_copy(update={"token_views": 1})
    if model_cfg is not None:
        runtime = ("scan_backend", "scan_chunk", "token_views", "sensor_input", "column_phase")
        update: dict[str, str] = {"sensor_input": model_cfg.sensor_input}
        if "column_phase" in model_cfg.model_fields_set:  # else the file's
            update["column_phase"] = model_cfg.column_phase
        cfg = cfg.model_copy(update=update)
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


def batch_copies(
    images: Images,
    idx: np.ndarray,
    rng: np.random.Generator,
    augment: Augmenter,
    turn_scans: int,
    look_scans: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The copies a batch ``idx`` is compared with → (turned, looked_at, looked):

    - ``turned``: its first ``turn_scans`` scans re-projected after a random continuous
      turn, then augmented like the batch (0: none, and nothing drawn);
    - ``looked``: its first ``look_scans`` scans of the model's own sensor (their places in
      the batch: ``looked_at``) as another catalogue sensor sees them, then augmented like
      the batch but for ``sensor_like`` (0: none, and nothing drawn). How many draws these
      take depends on how many of the batch's scans are the model sensor's, which the batch
      (and so the epoch's generator) fixes: ``--resume`` stays exact. On the ``bev`` input
      (no scan is the model sensor's there): its first ``look_scans`` scans that a sparser
      catalogue sensor could have made, as that sensor sees them (:meth:`Images.sparser`).
    """
    shape = (0, *images.parts[0].shape[1:])
    turned = looked = np.zeros(shape, np.float32)
    if turn_scans:
        theta = rng.uniform(-180.0, 180.0, turn_scans)
        turned = augment(
            images.turned(idx[:turn_scans], theta), rng, images.native(idx[:turn_scans])
        )
    looked_at = np.zeros(0, np.int64)
    if look_scans and images.mode in BEV_MODES:
        looked_at, seen = images.sparser(idx, rng, look_scans)
        if len(looked_at):
            looked = augment(seen, rng, np.zeros(len(looked_at), bool))
    elif look_scans:
        looked_at = np.flatnonzero(images.native(idx))[:look_scans]
        if len(looked_at):
            seen = augment.seen_as_other(images[idx[looked_at]], rng)
            looked = augment(seen, rng, np.zeros(len(looked_at), bool))
    return turned, looked_at, looked


def real_turn_scans(
    path: Path | None,
    profile: SensorProfile,
    progress: bool,
    mode: Mode = "elevation",
    aligned: bool = False,
) -> RealTurns | None:
    """The real scans of the per-epoch turn check, projected once (``aligned``: each at its
    mean bearing, as the model takes them); None (with a note) when the check is off or the
    folder is missing."""
    if path is None:
        return None
    if not (path / "velodyne").is_dir():
        if progress:
            tqdm.write(f"note: no real scans at {path}: the per-epoch turn check is skipped")
        return None
    return real_turns(open_sequence(path), SensorInput.own(profile, mode), aligned=aligned)
