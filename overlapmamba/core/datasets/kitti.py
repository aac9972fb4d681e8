"""KITTI odometry layout: ``velodyne/NNNNNN.bin``, ``poses.txt``, ``calib.txt``.

``poses.txt`` holds left-camera poses; with a ``calib.txt`` carrying ``Tr`` (velodyne→camera)
they are converted to the LiDAR frame. Without ``calib.txt`` the poses are taken as
LiDAR-frame already (our synthetic generator writes an identity ``Tr`` for clarity anyway).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from overlapmamba.core.datasets.base import Sequence
from overlapmamba.core.errors import DatasetError
from overlapmamba.core.poses import camera_to_lidar, read_calib, read_poses


def looks_like(root: Path) -> bool:
    return (root / "velodyne").is_dir()


def _manifest_sensor(root: Path) -> str | None:
    path = root / "manifest.json"
    if not path.is_file():
        return None
    try:
        sensor = json.loads(path.read_text()).get("config", {}).get("sensor")
    except (json.JSONDecodeError, AttributeError, OSError):
        raise DatasetError(f"{path} is not a readable manifest") from None
    return sensor if isinstance(sensor, str) else None


def open_kitti(root: str | Path, *, sensor: str | None = None) -> Sequence:
    """``sensor``: the catalogue sensor the scans come from; None: what the folder's
    ``manifest.json`` says (a synthetic drive records its sensor), else KITTI's HDL-64E."""
    root = Path(root)
    if sensor is None:
        sensor = _manifest_sensor(root) or "kitti-hdl64"
    velodyne = root / "velodyne"
    if not velodyne.is_dir():
        raise DatasetError(f"{root} is not a KITTI sequence: no velodyne/ folder")
    scans = tuple(sorted(velodyne.glob("*.bin")))
    pose_file = root / "poses.txt"
    if not pose_file.is_file():
        raise DatasetError(f"{root}: poses.txt is missing (one 3×4 pose per scan)")
    poses = read_poses(pose_file)
    calib_file = root / "calib.txt"
    if calib_file.is_file():
        calib = read_calib(calib_file)
        if "Tr" not in calib or np.shape(calib["Tr"]) != (4, 4):
            raise DatasetError(f"{calib_file}: no 12-number 'Tr:' (velodyne→camera) entry")
        if len(poses):
            poses = camera_to_lidar(poses, calib["Tr"])
    return Sequence(root=root, scan_paths=scans, poses=poses, sensor=sensor)
