"""Self-describing checkpoints: everything needed to rebuild, resume, evaluate or export.

A checkpoint is one ``torch.save`` dict of plain values and tensors (so it loads with
``weights_only=True``: no pickled code runs on load):

    format, version        "overlapmamba-checkpoint", 1
    model_config           OverlapMambaConfig.to_dict()
    profile                the sensor profile (overlapmamba.core), projection parameters included
    state_dict             model weights
    train                  training config, optimiser and scheduler states, completed epochs,
                           per-epoch history, best epoch, training-data fingerprints
    metrics                the latest validation metrics

:func:`load_model` also opens an exported encoder (``.onnx``, as ``overlapmamba export``
writes it and the service loads it) as an :class:`ExportedNetwork`, so the shipped model
can be evaluated without the checkpoint it came from.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from overlapmamba.core.datasets.base import Sequence
from overlapmamba.core.modelmeta import INPUT, OUTPUTS, EncoderMetadata
from overlapmamba.core.sensors import SensorProfile, get_sensor, sensor_of_profile
from overlapmamba.core.sensors.input import LEVELLED_MODES, Mode, SensorInput, check_mode
from overlapmamba.train.errors import CheckpointError
from overlapmamba.train.model import OverlapMamba, OverlapMambaConfig, channels_last

FORMAT = "overlapmamba-checkpoint"
VERSION = 1


def save_checkpoint(path: Path, payload: dict[str, Any]) -> None:
    """Write atomically (temporary file, flushed to disk, then renamed, the rename flushed
    too): a crash or a power loss leaves the previous file whole, never a torn or empty one.
    A write that fails (a full disk) removes its temporary file, keeps the previous
    checkpoint, and is a :class:`CheckpointError` naming the file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            torch.save({"format": FORMAT, "version": VERSION, **payload}, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as err:
        tmp.unlink(missing_ok=True)
        if not isinstance(err, Exception):
            raise  # KeyboardInterrupt: the previous checkpoint stands
        raise CheckpointError(
            f"could not write {path} ({type(err).__name__}: {err}); the previous one, if "
            "any, is kept",
            path=str(path),
        ) from None
    try:  # the rename itself to disk; some mounts (CIFS, FUSE) cannot fsync a folder
        folder = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(folder)
        finally:
            os.close(folder)
    except OSError:
        pass  # the checkpoint is written and renamed: only its durability is the mount's


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist", path=str(path))
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises many kinds for a foreign or torn file
        raise CheckpointError(
            f"{path} is not a readable checkpoint ({type(err).__name__}); expected a file "
            "written by `overlapmamba train`",
            path=str(path),
        ) from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise CheckpointError(
            f"{path} is not an OverlapMamba checkpoint (no '{FORMAT}' format tag)", path=str(path)
        )
    if ckpt.get("version") != VERSION:
        raise CheckpointError(
            f"{path} has checkpoint version {ckpt.get('version')!r}; this code reads {VERSION}",
            version=ckpt.get("version"),
            allowed=[VERSION],
        )
    return ckpt


class ExportedNetwork(torch.nn.Module):
    """An exported encoder behind the network's interface, for evaluation: ``forward(x)``
    gives (descriptors, yaw features) from onnxruntime on the CPU, through the graph's own
    scan. ``cfg`` is the exported network's config, ``digest`` the file's model id, ``meta``
    its whole metadata. It has no weights to train."""

    def __init__(self, path: str | Path, threads: int = 0) -> None:
        super().__init__()
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        try:
            self.session = ort.InferenceSession(
                str(path), sess_options=opts, providers=["CPUExecutionProvider"]
            )
        except Exception as err:  # onnxruntime raises its own unrelated classes
            message = f"onnxruntime cannot load {path}: {err}"
            raise CheckpointError(message, path=str(path)) from None
        try:
            self.meta = EncoderMetadata.from_props(self.session.get_modelmeta().custom_metadata_map)
            self.cfg = OverlapMambaConfig.from_dict(self.meta.network)
        except ValueError as err:
            raise CheckpointError(f"{path}: {err}", path=str(path)) from None
        self.digest = self.meta.model_id

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        images = x.detach().cpu().numpy().astype(np.float32, copy=False)
        desc, yaw = self.session.run(list(OUTPUTS), {INPUT: images})
        return torch.from_numpy(desc), torch.from_numpy(yaw)


# What evaluation runs: a trained network, or an exported encoder behind the same interface.
Network = OverlapMamba | ExportedNetwork


def views_of(model: Network) -> int:
    """How many sub-column views describe a scan (:mod:`overlapmamba.core.views`): an exported
    encoder's metadata says; a network in training by one, or by the views it averages
    itself (``token_views``)."""
    return model.meta.views if isinstance(model, ExportedNetwork) else model.cfg.token_views


def aligned_of(model: Network) -> bool:
    """Whether each scan's columns start at its own mean bearing (:mod:`overlapmamba.core.views`):
    an exported encoder's metadata says; a network in training, its config (which its export
    writes)."""
    if isinstance(model, ExportedNetwork):
        return model.meta.aligned
    return model.cfg.column_phase == "aligned"


def sensor_input_of(model: Network) -> Mode:
    """How scans enter the model (:mod:`overlapmamba.core.sensors.input`): an exported
    encoder's metadata says; a network in training, its config (which its export writes)."""
    if isinstance(model, ExportedNetwork):
        return model.meta.sensor_input
    return check_mode(model.cfg.sensor_input)


def input_of(model: Network, profile: SensorProfile, seq: Sequence) -> SensorInput:
    """How ``seq``'s scans become ``model``'s input: its sensor (a sequence that names none
    is the model's own) into the model's profile, as the model takes other sensors."""
    return input_of_mode(profile, seq, sensor_input_of(model))


def input_of_mode(profile: SensorProfile, seq: Sequence, mode: Mode) -> SensorInput:
    """:func:`input_of` for an input ``mode``. The ``structure`` and ``bev`` inputs keep what
    stands above the reference ground, so a drive whose sensor sat elsewhere (``seq.mount``: a drawn
    town's robot or backpack) is levelled and moved to the reference height first, as the
    service does with a mount a robot declares; the other modes take scans as recorded (how
    their models were trained and measured)."""
    sensor = get_sensor(seq.sensor) if seq.sensor else sensor_of_profile(profile)
    mount = seq.mount if mode in LEVELLED_MODES else None
    return SensorInput(profile, sensor, mode, mount)


def load_model(path: str | Path) -> tuple[Network, SensorProfile, dict[str, Any]]:
    """The model (eval mode, CPU), its sensor profile and the whole checkpoint dict; for an
    exported ``.onnx``, an :class:`ExportedNetwork` and ``{"model_config", "metrics",
    "encoder"}`` from its metadata."""
    if Path(path).suffix == ".onnx":
        if not Path(path).is_file():
            raise CheckpointError(f"model {path} does not exist", path=str(path))
        net = ExportedNetwork(path)
        info = {"model_config": net.meta.network, "metrics": net.meta.metrics}
        return net.eval(), net.meta.profile, {**info, "encoder": net.meta.model_dump(mode="json")}
    ckpt = read_checkpoint(path)
    try:
        cfg = OverlapMambaConfig.from_dict(ckpt["model_config"])
        model = channels_last(OverlapMamba(cfg))
        model.load_state_dict(ckpt["state_dict"])
        profile = SensorProfile.model_validate(ckpt["profile"])
    except (KeyError, ValueError, RuntimeError) as err:
        raise CheckpointError(f"{path}: the checkpoint does not rebuild its model: {err}") from None
    return model.eval(), profile, ckpt
