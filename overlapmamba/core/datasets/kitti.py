"""KITTI odometry layout: ``velodyne/NNNNNN.bin``, ``poses.txt``, ``calib.txt``.

``poses.txt`` holds left-camera poses; with a ``calib.txt`` carrying ``Tr`` (velodyne→camera)
they are converted to the LiDAR frame. Without ``calib.txt`` the poses are taken as
LiDAR-frame already (our synthetic generator writes an identity ``Tr`` for clarity anyway).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from overlapmamba.core.datasets.base import Sequence, scan_order
from overlapmamba.core.errors import DatasetError
from overlapmamba.core.poses import camera_to_lidar, read_calib, read_poses
from overlapmamba.core.sensors.mount import Mount


def looks_like(root: Path) -> bool:
    return (root / "velodyne").is_dir()


def read_manifest(root: Path) -> dict:
    """A drive's ``manifest.json`` ({} where it has none; a DatasetError where unreadable)."""
    path = root / "manifest.json"
    if not path.is_file():
        return {}
    try:
        manifest = json.loads(path.read_text())
    except (json.JSONDecodeError, OSError):
        manifest = None
    if not isinstance(manifest, dict):
        raise DatasetError(f"{path} is not a readable manifest")
    return manifest


def manifest_sensor(manifest: dict) -> str | None:
    sensor = (manifest.get("config") or {}).get("sensor")
    return sensor if isinstance(sensor, str) else None


def manifest_mount(root: Path, manifest: dict, *, reference: bool = False) -> Mount | None:
    """Where a synthetic drive's sensor sat (its manifest's resolved mounting); None where
    the manifest says nothing, and at the reference mount (level, 1.73 m up) unless
    ``reference`` (a client names it, so that a map's declared mount does not stand in)."""
    mounting = (manifest.get("resolved") or {}).get("mounting")
    if not mounting:
        return None
    try:
        mount = Mount(
            height=mounting["height"],
            pitch_deg=mounting.get("pitch_deg", 0.0),
            roll_deg=mounting.get("roll_deg", 0.0),
        )
    except (KeyError, TypeError, ValueError) as e:
        raise DatasetError(f"{root}/manifest.json: unreadable mounting {mounting!r}: {e}") from None
    return None if mount.at_reference and not reference else mount


def open_kitti(
    root: str | Path,
    *,
    sensor: str | None = None,
    unfinished: bool = False,
    missing_poses: str = "raise",
) -> Sequence:
    """``sensor``: the catalogue sensor the scans come from; None: what the folder's
    ``manifest.json`` says (a synthetic drive records its sensor), else KITTI's HDL-64E. The
    sequence's ``mount`` is the manifest's mounting where it is not the reference. Without
    a ``poses.txt`` (KITTI's test sequences, a raw drive): an error, or with
    ``missing_poses="nan"`` NaN poses (what the client's drives send as no pose)."""
    root = Path(root)
    # overlapmamba.synth.generate.INCOMPLETE; ``unfinished``: the generator's own reads
    if not unfinished and (root / ".incomplete").exists():
        raise DatasetError(
            f"{root} is a gen-data output that never finished (its .incomplete marker is "
            "there: the run was killed, or is still going): delete it and generate again"
        )
    manifest = read_manifest(root)
    if sensor is None:
        sensor = manifest_sensor(manifest) or "kitti-hdl64"
    velodyne = root / "velodyne"
    if not velodyne.is_dir():
        raise DatasetError(f"{root} is not a KITTI sequence: no velodyne/ folder")
    scans = tuple(sorted(velodyne.glob("*.bin"), key=scan_order))  # 2.bin before 10.bin
    pose_file = root / "poses.txt"
    if not pose_file.is_file():
        if missing_poses == "nan" and scans:
            return Sequence(
                root=root,
                scan_paths=scans,
                poses=np.full((len(scans), 4, 4), np.nan),
                sensor=sensor,
                mount=manifest_mount(root, manifest),
            )
        raise DatasetError(f"{root}: poses.txt is missing (one 3×4 pose per scan)")
    poses = read_poses(pose_file)
    calib_file = root / "calib.txt"
    if calib_file.is_file():
        calib = read_calib(calib_file)
        if "Tr" not in calib or np.shape(calib["Tr"]) != (4, 4):
            raise DatasetError(f"{calib_file}: no 12-number 'Tr:' (velodyne→camera) entry")
        if len(poses):
            try:
                poses = camera_to_lidar(poses, calib["Tr"])
            except DatasetError as err:
                raise DatasetError(f"{root} ({calib_file.name}, {pose_file.name}): {err}") from None
    mount = manifest_mount(root, manifest)
    return Sequence(root=root, scan_paths=scans, poses=poses, sensor=sensor, mount=mount)
