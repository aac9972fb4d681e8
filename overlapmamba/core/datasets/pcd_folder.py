"""A folder of PCD scans plus ``poses.txt`` (LiDAR-frame, 3×4 per line), such as
``clouds/0.pcd … clouds/38.pcd``. Files are ordered by the number in their name."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from overlapmamba.core.datasets.base import Sequence, scan_order
from overlapmamba.core.errors import DatasetError
from overlapmamba.core.poses import read_poses


def _scan_dir(root: Path) -> Path:
    return root / "clouds" if (root / "clouds").is_dir() else root


def looks_like(root: Path) -> bool:
    return any(_scan_dir(root).glob("*.pcd"))  # poses.txt: checked on opening


def open_pcd_folder(
    root: str | Path, *, sensor: str | None = None, missing_poses: str = "raise"
) -> Sequence:
    """``missing_poses``: as ``open_kitti``'s."""
    root = Path(root)
    scans = tuple(sorted(_scan_dir(root).glob("*.pcd"), key=scan_order))
    if not scans:
        raise DatasetError(f"{root}: no .pcd files in {_scan_dir(root)}")
    pose_file = root / "poses.txt"
    if not pose_file.is_file():
        if missing_poses == "nan":
            nan = np.full((len(scans), 4, 4), np.nan)
            return Sequence(root=root, scan_paths=scans, poses=nan, sensor=sensor)
        raise DatasetError(f"{root}: poses.txt is missing (one 3×4 pose per scan)")
    return Sequence(root=root, scan_paths=scans, poses=read_poses(pose_file), sensor=sensor)
