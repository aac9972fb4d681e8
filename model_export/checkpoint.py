"""Self-describing checkpoints: everything needed to rebuild, resume, evaluate or export.

A checkpoint is one ``torch.save`` dict of plain values and tensors (so it loads with
``weights_only=True``: no pickled code runs on load):

    format, version        "overlapmamba-checkpoint", 1
    model_config           OverlapMambaConfig.to_dict()
    profile                the sensor profile (lidar_core), projection parameters included
    state_dict             model weights
    train                  training config, optimiser and scheduler states, completed epochs,
                           per-epoch history, best epoch, training-data fingerprints
    metrics                the latest validation metrics
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from lidar_core.sensors import SensorProfile
from model_export.errors import CheckpointError
from model_export.model import OverlapMamba, OverlapMambaConfig

FORMAT = "overlapmamba-checkpoint"
VERSION = 1


def save_checkpoint(path: Path, payload: dict[str, Any]) -> None:
    """Write atomically (temporary file, then rename): a crash never leaves a torn file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    torch.save({"format": FORMAT, "version": VERSION, **payload}, tmp)
    os.replace(tmp, path)


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


def load_model(path: str | Path) -> tuple[OverlapMamba, SensorProfile, dict[str, Any]]:
    """The model (eval mode, CPU), its sensor profile and the whole checkpoint dict."""
    ckpt = read_checkpoint(path)
    try:
        cfg = OverlapMambaConfig.from_dict(ckpt["model_config"])
        model = OverlapMamba(cfg)
        model.load_state_dict(ckpt["state_dict"])
        profile = SensorProfile.model_validate(ckpt["profile"])
    except (KeyError, ValueError, RuntimeError) as err:
        raise CheckpointError(f"{path}: the checkpoint does not rebuild its model: {err}") from None
    return model.eval(), profile, ckpt
