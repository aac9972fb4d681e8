"""Validation across sensors: the validation drive rendered by other sensors.

``[train] val_sensors`` names renderings of the validation sequence's drive by other
catalogue sensors (``make data-sensors`` writes ``val-kitti-hdl64`` and its renderings
``val-vlp16``, ``val-os0-128``, …: the same drive, scan for scan). Every epoch each is
described as the service takes that sensor's scans (by elevation,
:func:`~overlapmamba.train.train_inputs.training_input`) and scored twice under the
loop-closure protocol, with the validation drive's own loop table (frame i is the same
place in every rendering, :mod:`overlapmamba.train.drives`):

    own     its queries against its own earlier scans (a fleet of that sensor alone)
    cross   its queries against the model sensor's earlier scans (a map made by the model's
            sensor, queried by this one)

``select_on = "sensors"`` keeps as ``best.pt`` the epoch with the best mean F1max over the
validation sequence and every rendering's own and cross scores, instead of the validation
sequence's alone.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from overlapmamba.core.datasets.base import Sequence
from overlapmamba.core.errors import DatasetError
from overlapmamba.core.overlap import LoopGroundTruth
from overlapmamba.core.sensors import SensorProfile
from overlapmamba.core.sensors.input import Mode
from overlapmamba.train.checkpoint import Network
from overlapmamba.train.drives import drive_key, group_drives
from overlapmamba.train.evaluate import cross_loop_closure, describe, loop_closure, summary
from overlapmamba.train.rangecache import cache_key, range_images
from overlapmamba.train.train_inputs import refuse_test_split, training_input


@dataclass(frozen=True)
class Rendering:
    """One rendering of the validation drive by another sensor, ready to describe."""

    name: str  # its sensor, as the catalogue names it
    path: str
    key: str  # its range cache key (the run's data fingerprint)
    images: np.ndarray  # (N, H, W) in the model's input


def open_renderings(
    paths: list[str],
    val_seq: Sequence,
    profile: SensorProfile,
    progress: bool,
    mode: Mode = "elevation",
    aligned: bool = False,
) -> list[Rendering]:
    """The renderings, checked to be the validation drive's (same drive keys, every scan
    within 5 cm of the validation scan of its frame) and of distinct sensors."""
    from overlapmamba.core.datasets import open_sequence

    out: list[Rendering] = []
    for p in paths:
        seq = open_sequence(Path(p))
        manifest = Path(p) / "manifest.json"
        if manifest.is_file():
            meta = json.loads(manifest.read_text()).get("config", {})
            refuse_test_split(Path(p), meta, "validation across sensors")
        if seq.sensor is None:
            raise DatasetError(f"val_sensors: {p} names no sensor in its manifest")
        if drive_key(seq) != drive_key(val_seq):
            raise DatasetError(
                f"val_sensors: {p} is not a rendering of the validation drive {val_seq.root} "
                "(another seed, session, length, town or drive): validate across sensors on "
                "renderings of one drive, e.g. val-kitti-hdl64 with val-vlp16, val-os0-128, …"
            )
        group_drives([val_seq, seq], lambda s: s is val_seq)  # frames in the same places
        if seq.sensor == val_seq.sensor or seq.sensor in {r.name for r in out}:
            raise DatasetError(f"val_sensors: a second rendering by {seq.sensor} ({p})")
        sensor = training_input(profile, seq, mode)
        images = range_images(seq, profile, sensor=sensor, progress=progress, aligned=aligned)
        key = cache_key(seq, profile, sensor=sensor, aligned=aligned)
        out.append(Rendering(seq.sensor, str(seq.root), key, images))
    return out


def validation_fields(
    model: Network,
    val_images: np.ndarray,
    gt: LoopGroundTruth,
    renderings: list[Rendering],
    device: str,
) -> dict[str, Any]:
    """An epoch's validation fields: ``val`` (the validation sequence's loop-closure
    summary), ``val_sensors`` (with renderings) and ``val_s`` (the seconds it took)."""
    t = time.perf_counter()
    desc_val, _ = describe(model, val_images, device=device)
    out: dict[str, Any] = {"val": summary(loop_closure(desc_val, gt))}
    if renderings:
        out["val_sensors"] = validate_renderings(model, renderings, desc_val, gt, device)
    out["val_s"] = time.perf_counter() - t
    return out


def validate_renderings(
    model: Network,
    renderings: list[Rendering],
    val_desc: np.ndarray,
    gt: LoopGroundTruth,
    device: str,
) -> dict[str, dict[str, Any]]:
    """{sensor: {"own": summary, "cross": summary}} for every rendering."""
    out = {}
    for r in renderings:
        desc, _ = describe(model, r.images, device=device)
        out[r.name] = {
            "own": summary(loop_closure(desc, gt)),
            "cross": cross_loop_closure(desc, val_desc, gt),
        }
    return out


def selection_score(val: dict[str, Any], sensors: dict[str, dict[str, Any]] | None) -> float:
    """The mean F1max over the validation sequence and every rendering's own and cross
    scores (the validation sequence's alone without renderings)."""
    scores = [val["all"]["f1max"]]
    for s in (sensors or {}).values():
        scores += [s["own"]["all"]["f1max"], s["cross"]["all"]["f1max"]]
    return float(np.mean(scores))
