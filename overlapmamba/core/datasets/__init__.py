"""Sequence readers behind one registry. Readers are imported only when used.

open_sequence("path/to/00")                    auto-detects the layout
open_sequence("path/to/scene", kind="pcd-folder", sensor="hdl32")

open_recording("drive.mcap", topic="/points", odometry="/odom")
open_recording("drive.bag", tf="map")          a sequence folder or a ROS recording

ROS recordings (a ROS 1 bag, a rosbag2 folder, a bare MCAP file; ``overlapmamba.core.datasets.
bags``) carry no loop ground truth, and poses only when an odometry topic or a /tf frame
is named; they
offer what the client's drives and ``overlapmamba eval`` read of a sequence.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

from overlapmamba.core.datasets.base import Sequence
from overlapmamba.core.errors import DatasetError

# kind -> (module, opener function). Order matters for auto-detection.
REGISTRY: dict[str, tuple[str, str]] = {
    "kitti": ("overlapmamba.core.datasets.kitti", "open_kitti"),
    "pcd-folder": ("overlapmamba.core.datasets.pcd_folder", "open_pcd_folder"),
}

__all__ = ["REGISTRY", "Sequence", "detect_kind", "open_recording", "open_sequence"]


_LAYOUTS = (
    "allowed: KITTI (velodyne/*.bin + poses.txt [+ calib.txt]), a PCD folder "
    "(clouds/*.pcd or *.pcd + poses.txt), or a ROS recording (a .bag or .mcap file, or a "
    "rosbag2 folder with its metadata.yaml)"
)


def detect_kind(root: str | Path) -> str:
    root = Path(root)
    if not root.exists():
        raise DatasetError(f"{root} does not exist; {_LAYOUTS}")
    if root.is_file():
        hint = (
            " (a rosbag2's storage file: give its folder, which holds metadata.yaml)"
            if root.suffix == ".db3"
            else " (a recording still being written, or cut short: `ros2 bag reindex` or "
            "`rosbag reindex` mends one)"
            if root.suffix == ".active"
            else ""
        )
        raise DatasetError(f"{root} is a file of no known kind{hint}; {_LAYOUTS}")
    for kind, (module, _) in REGISTRY.items():
        if importlib.import_module(module).looks_like(root):
            return kind
    hint = ""
    if any(root.glob("*.db3")) or any(root.glob("*.mcap")):
        hint = (
            " (it holds rosbag2 storage files but no metadata.yaml: a recording cut short; "
            "`ros2 bag reindex` writes it)"
        )
    raise DatasetError(f"{root} matches no known layout{hint}; {_LAYOUTS}", allowed=list(REGISTRY))


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


def open_recording(
    path: str | Path,
    *,
    topic: str | None = None,
    odometry: str | None = None,
    tf: str | None = None,
    need_poses: bool = False,
    sensor: str | None = None,
    pose_gaps: str = "raise",
) -> Any:
    """A sequence folder (``open_sequence``) or a ROS recording (``bags.open_bag``: its
    PointCloud2 ``topic``, poses from its ``odometry`` topic or from /tf in the ``tf`` frame):
    a ``Sequence`` or a ``Bag``. ``need_poses``: a recording must then say where its poses
    are. ``pose_gaps``: as ``open_bag``'s; ``"nan"`` also opens a folder without a poses.txt
    (NaN poses). Raises DatasetError."""
    from overlapmamba.core.datasets.bags import is_bag, open_bag

    if not is_bag(path):
        if topic is not None or odometry is not None or tf is not None:
            raise DatasetError(
                f"{path} is a sequence folder: --topic, --odometry and --tf are for ROS recordings"
            )
        # ``pose_gaps="nan"``: a folder without poses.txt has NaN poses (sent as none)
        options: dict[str, Any] = {"missing_poses": pose_gaps} if pose_gaps == "nan" else {}
        if sensor is not None:
            from overlapmamba.core.sensors.catalogue import catalogue_name

            options["sensor"] = catalogue_name(sensor)
        return open_sequence(path, **options)
    if need_poses and odometry is None and tf is None:
        raise DatasetError(
            f"{path} is a ROS recording without poses: name its nav_msgs/Odometry topic "
            "(--odometry) or the fixed frame of its /tf (--tf map)"
        )
    return open_bag(path, topic=topic, odometry=odometry, tf=tf, sensor=sensor, pose_gaps=pose_gaps)
