"""Sequence readers behind one registry. Readers are imported only when used.

open_sequence("path/to/00")                    auto-detects the layout
open_sequence("path/to/scene", kind="pcd-folder", sensor="hdl32")

ROS recordings (a ROS 1 bag, a rosbag2 folder, a bare MCAP file) are drives for the client
and the CLI rather than sequences: they carry no loop ground truth, and poses only when an
odometry topic is named. ``lidar_core.datasets.bags.open_bag`` reads them.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

from lidar_core.datasets.base import Sequence
from lidar_core.errors import DatasetError

# kind -> (module, opener function). Order matters for auto-detection.
REGISTRY: dict[str, tuple[str, str]] = {
    "kitti": ("lidar_core.datasets.kitti", "open_kitti"),
    "pcd-folder": ("lidar_core.datasets.pcd_folder", "open_pcd_folder"),
}

__all__ = ["REGISTRY", "Sequence", "detect_kind", "open_sequence"]


def detect_kind(root: str | Path) -> str:
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"sequence folder {root} does not exist")
    for kind, (module, _) in REGISTRY.items():
        if importlib.import_module(module).looks_like(root):
            return kind
    raise DatasetError(
        f"{root} matches no known sequence layout; allowed: KITTI (velodyne/*.bin + "
        "poses.txt [+ calib.txt]) or a PCD folder (clouds/*.pcd or *.pcd + poses.txt)",
        allowed=list(REGISTRY),
    )


def open_sequence(root: str | Path, kind: str = "auto", **options: Any) -> Sequence:
    if kind == "auto":
        kind = detect_kind(root)
    if kind not in REGISTRY:
        raise DatasetError(
            f"unknown sequence kind {kind!r}; allowed: auto, {', '.join(REGISTRY)}",
            allowed=["auto", *REGISTRY],
        )
    module, func = REGISTRY[kind]
    seq: Sequence = getattr(importlib.import_module(module), func)(root, **options)
    return seq
