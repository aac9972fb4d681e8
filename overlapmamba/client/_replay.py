"""Recorded drives for the CLI and the fleet simulator: scans, times, poses, ground truth.

A drive is a sequence folder (KITTI layout or PCD folder, ``overlapmamba.core.datasets``) or a ROS
recording (a ROS 1 bag, a rosbag2 folder, a bare MCAP file: ``overlapmamba.core.datasets.bags``,
its PointCloud2 ``topic``, poses from an ``odometry`` topic when named). A folder's times
come from ``times.txt`` when present (else 10 Hz), a bag's from the bag; poses become
x,y,z,qx,qy,qz,qw (none for a bag without odometry); the loop radius comes from the
sequence's own ``ground_truth/loops.npz`` when it ships one (the synthetic generator does).
A drive's sensor is the one its user names, else the one its ``manifest.json`` records (a
synthetic drive's); otherwise none is sent, and the server takes the map's or the model's.
Where the sensor sits (its mount) likewise: the user's, else the manifest's mounting (the
one ``overlapmamba eval`` reads; sent even where it is the model's own, so that a map's
declared mount does not stand in for it), else none is sent.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from overlapmamba.client._base import NAME_CHARS
from overlapmamba.core.datasets import open_recording
from overlapmamba.core.datasets.bags import Bag
from overlapmamba.core.datasets.base import Sequence
from overlapmamba.core.datasets.kitti import manifest_mount, manifest_sensor, read_manifest
from overlapmamba.core.errors import LidarCoreError
from overlapmamba.core.overlap import LoopGroundTruth
from overlapmamba.core.poses import quaternion

_NOT_IN_IDS = re.compile(f"[^{NAME_CHARS}]+")  # what the service's ids may not hold


@dataclass
class Drive:
    seq: Sequence | Bag  # points(i), name, poses ((N, 4, 4) world poses, or None on a bag)
    times: np.ndarray  # (N,) seconds
    poses: np.ndarray | None  # (N, 7) x, y, z, qx, qy, qz, qw; None: the drive has none
    loop_radius: float | None  # metres, from the shipped ground truth; None: no ground truth
    sensor: str | None = None  # what the scans' requests name; None: the map's, or the model's
    mount: str | None = None  # HEIGHT,PITCH,ROLL the scans' requests name; None: the map's

    @property
    def name(self) -> str:
        return self.seq.name

    @property
    def session(self) -> str:
        """The session id its keyframes go under unless one is given: the folder's or
        file's name (``.`` is the folder's own), with the topic where the recording holds
        more than one PointCloud2 topic (each its own keyframes); a character an id may not
        hold becomes ``-``. Names that are valid ids are kept as they are."""
        root = Path(os.path.abspath(self.seq.root))
        name = root.stem if root.is_file() else root.name
        if isinstance(self.seq, Bag) and len(self.seq.clouds) > 1:
            name = f"{name}-{self.seq.topic.strip('/')}"
        clean = _NOT_IN_IDS.sub("-", name).lstrip("-_.@")[:100]
        return clean or "drive"

    def __len__(self) -> int:
        return len(self.seq)

    def scan(self, i: int) -> np.ndarray:
        return self.seq.xyzi(i)

    def scans(self, frames: Iterable[int], skipped: list[str]) -> Iterator[tuple[int, np.ndarray]]:
        """(i, scan) of each of ``frames`` that can be read. One that cannot (an empty cloud
        a driver sent while it started, a NaN in a cloud marked dense, a damaged message) is
        left out, and why appended to ``skipped``: one bad message does not end a drive."""
        for i in frames:
            try:
                points = self.scan(i)
            except LidarCoreError as err:
                skipped.append(str(err))
                continue
            yield i, points

    def pose(self, i: int) -> np.ndarray | None:
        """Scan i's pose; None where the drive has none, or none near scan i's stamp."""
        if self.poses is None or np.isnan(self.poses[i]).any():
            return None
        return self.poses[i]

    @property
    def unposed(self) -> int:
        """Scans with no pose though the drive has poses (none near their stamps)."""
        return 0 if self.poses is None else int(np.isnan(self.poses).any(axis=1).sum())


def _pose7(world: np.ndarray) -> np.ndarray:
    return np.array([[*T[:3, 3], *quaternion(T[:3, :3])] for T in world])


def open_drive(
    root: str | Path,
    *,
    topic: str | None = None,
    odometry: str | None = None,
    tf: str | None = None,
    sensor: str | None = None,
    mount: str | None = None,
) -> Drive:
    """``topic``, ``odometry`` and ``tf``: for a ROS recording, which PointCloud2 topic
    (needed when it holds several), and which nav_msgs/Odometry topic or /tf fixed frame
    ("map", or "map:velodyne" for another child frame than the scans') gives the poses.
    ``sensor``: the sensor that recorded it, ``mount`` (HEIGHT[,PITCH[,ROLL]]) where it sat
    (default for both: its manifest's, if any)."""
    root = Path(root)
    # a scan with no pose near its stamp (odometry started late) goes without one
    seq = open_recording(root, topic=topic, odometry=odometry, tf=tf, pose_gaps="nan")
    if isinstance(seq, Bag):
        poses = None if seq.poses is None else _pose7(seq.poses)
        return Drive(
            seq=seq, times=seq.times, poses=poses, loop_radius=None, sensor=sensor, mount=mount
        )
    n = len(seq)
    times_file = root / "times.txt"
    times = read_times(times_file, n) if times_file.is_file() else np.arange(n) * 0.1
    radius = None
    gt = root / "ground_truth" / "loops.npz"
    if gt.is_file():
        radius = float(LoopGroundTruth.load(gt).params.get("radius", 30.0))
    manifest = {} if sensor and mount else read_manifest(root)
    return Drive(
        seq=seq,
        times=np.asarray(times, dtype=np.float64),
        poses=None if np.isnan(seq.poses).all() else _pose7(seq.poses),  # no poses.txt: none
        loop_radius=radius,
        sensor=sensor or manifest_sensor(manifest),
        mount=mount or _manifest_mount(root, manifest),
    )


def read_times(path: Path, n: int) -> np.ndarray:
    """A KITTI ``times.txt``: one finite time (seconds) a line, one line a scan."""
    allowed = f"allowed: one time in seconds a line, {n} lines (one a scan), no header"
    try:
        times = np.loadtxt(path, ndmin=1, dtype=np.float64)
    except ValueError as err:
        raise ValueError(f"{path} cannot be read as times: {err}; {allowed}") from None
    if times.ndim != 1:
        raise ValueError(f"{path} has {times.shape[1]} columns; {allowed}")
    if not np.all(np.isfinite(times)):
        line = int(np.flatnonzero(~np.isfinite(times))[0]) + 1
        raise ValueError(f"{path}: line {line} is not a finite time; {allowed}")
    if len(times) != n:
        raise ValueError(f"{path}: {len(times)} times for {n} scans; {allowed}")
    return times


def _manifest_mount(root: Path, manifest: dict) -> str | None:
    """The manifest's mounting as a scan call names it (HEIGHT,PITCH,ROLL), the model's own
    included: a map that declares another must not take its place."""
    mount = manifest_mount(root, manifest, reference=True)
    return None if mount is None else mount.text()
