"""Recorded robot drives in ROS formats, read with rosbags (one library for all of them):

    drive.bag                    ROS 1 bag
    drive/ (metadata.yaml)       rosbag2, SQLite (.db3) or MCAP storage
    drive.mcap                   a bare MCAP file of ROS 2 messages

A topic of ``sensor_msgs/msg/PointCloud2`` becomes a drive's scans, in the order recorded,
each decoded by :func:`lidar_core.io.pointcloud2.decode_message` (so every field layout a
driver sends works, and a malformed message names what is wrong). Times are the bag's
receive times. Poses come from a ``nav_msgs/msg/Odometry`` topic when one is named: the
odometry message nearest in time to each scan (within ``max_pose_gap_s``), its pose taken
as the scan's (the odometry's child frame taken as the LiDAR's).

Not read here: ``/tf`` frame pairs (a transform tree needs buffering and interpolation;
record odometry in the LiDAR's frame, or convert it first).
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lidar_core.errors import DatasetError
from lidar_core.io.pointcloud2 import decode_message
from lidar_core.points import PointCloud
from lidar_core.poses import from_quaternion

PREFETCH = 8  # scans decoded per seek
CACHED = 32  # scans kept (≈ 2 MB each for a 120k-point scan)
POINTCLOUD2 = ("sensor_msgs/msg/PointCloud2", "sensor_msgs/PointCloud2")
ODOMETRY = ("nav_msgs/msg/Odometry", "nav_msgs/Odometry")


def is_bag(path: str | Path) -> bool:
    """A ROS 1 bag, a rosbag2 folder or a bare MCAP file."""
    p = Path(path)
    return (p.is_file() and p.suffix in (".bag", ".mcap")) or (
        p.is_dir() and (p / "metadata.yaml").is_file()
    )


def _reader(path: Path) -> Any:
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError as err:  # pragma: no cover - the client and serve extras install it
        raise DatasetError(
            f"{path}: reading ROS bags needs the rosbags package (pip install rosbags)"
        ) from err
    return AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))


@dataclass
class Bag:
    """One PointCloud2 topic of a recording: ``len``, ``points(i)``, ``times``, ``poses``."""

    path: Path
    topic: str
    stamps_ns: np.ndarray  # (N,) int64: the bag's receive times, as it indexes them
    poses: np.ndarray | None  # (N, 4, 4) from the odometry topic, or None
    _cache: dict[int, PointCloud] = field(default_factory=dict, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    sensor: str | None = None  # the sensor profile, as a Sequence has it (unknown here)

    @property
    def name(self) -> str:
        return self.path.stem if self.path.is_file() else self.path.name

    @property
    def times(self) -> np.ndarray:
        """(N,) seconds."""
        return self.stamps_ns / 1e9

    @property
    def root(self) -> Path:
        return self.path

    def __iter__(self) -> Iterator[PointCloud]:
        for i in range(len(self)):
            yield self.points(i)

    def positions(self) -> np.ndarray:
        """(N, 3) scan positions in the world frame (from the odometry)."""
        if self.poses is None:
            raise DatasetError(f"{self.path}: no poses; name an odometry topic")
        return self.poses[:, :3, 3]

    def update_digest(self, h: Any) -> None:
        """What identifies the recording, cheaply (as ``Sequence.update_digest``): its
        files' names and sizes, the topic, the message times and the poses."""
        files = sorted(self.path.rglob("*")) if self.path.is_dir() else [self.path]
        for f in files:
            if f.is_file():
                h.update(f"{f.name}:{f.stat().st_size}".encode())
        h.update(self.topic.encode())
        h.update(np.ascontiguousarray(self.stamps_ns).tobytes())
        if self.poses is not None:
            h.update(np.ascontiguousarray(self.poses).tobytes())

    def __len__(self) -> int:
        return len(self.stamps_ns)

    def points(self, i: int) -> PointCloud:
        """Scan ``i``. Random access: the reader seeks to its time and decodes it and the
        next ``PREFETCH`` - 1 (a replay reads on in order); the latest ``CACHED`` are kept.
        Safe from several threads (the fleet simulator's robots share a drive)."""
        with self._lock:
            if i in self._cache:
                return self._cache[i]
        if not 0 <= i < len(self):
            raise IndexError(f"scan {i} of {len(self)}")
        t = int(self.stamps_ns[i])
        j = i - self._nth(i)  # the index of the first message at scan i's time
        found: dict[int, PointCloud] = {}
        with _reader(self.path) as r:
            cons = [c for c in r.connections if c.topic == self.topic]
            for con, _, raw in r.messages(connections=cons, start=t):
                if j >= i:
                    msg = r.deserialize(raw, con.msgtype)
                    found[j] = decode_message(msg, source=f"{self.topic} message {j}")
                j += 1
                if j >= min(i + PREFETCH, len(self)):
                    break
        if i not in found:
            raise DatasetError(f"{self.path}: message {i} of {self.topic} is gone")
        with self._lock:
            self._cache.update(found)
            while len(self._cache) > CACHED:
                self._cache.pop(next(iter(self._cache)))
        return found[i]

    def _nth(self, i: int) -> int:
        """Which of the messages sharing scan i's time stamp it is."""
        return int(i - np.searchsorted(self.stamps_ns, self.stamps_ns[i]))


def open_bag(
    path: str | Path,
    *,
    topic: str | None = None,
    odometry: str | None = None,
    max_pose_gap_s: float = 0.1,
) -> Bag:
    """Index a recording's PointCloud2 topic (``topic``: which, when it holds several) and,
    when ``odometry`` names a topic, each scan's pose. Raises DatasetError naming what is
    wrong and what the recording holds."""
    path = Path(path)
    if not is_bag(path):
        raise DatasetError(
            f"{path} is not a ROS recording; allowed: a .bag file, a rosbag2 folder "
            "(metadata.yaml) or a .mcap file"
        )
    try:
        with _reader(path) as r:
            clouds = sorted({c.topic for c in r.connections if c.msgtype in POINTCLOUD2})
            if topic is None:
                if len(clouds) != 1:
                    raise DatasetError(
                        f"{path}: {len(clouds)} PointCloud2 topics "
                        f"({', '.join(clouds) or 'none'}); name one with --topic",
                        topics=clouds,
                    )
                topic = clouds[0]
            elif topic not in clouds:
                raise DatasetError(
                    f"{path}: no PointCloud2 topic {topic!r}; it has {', '.join(clouds) or 'none'}",
                    topics=clouds,
                )
            cons = [c for c in r.connections if c.topic == topic]
            stamps = np.array([t for _, t, _ in r.messages(connections=cons)], dtype=np.int64)
            poses = None
            if odometry is not None:
                poses = _odometry_poses(r, path, odometry, stamps, max_pose_gap_s)
    except DatasetError:
        raise
    except Exception as err:  # rosbags raises its own types for damaged files
        raise DatasetError(f"{path}: the recording cannot be read: {err}") from err
    if not len(stamps):
        raise DatasetError(f"{path}: topic {topic} holds no messages")
    order = np.argsort(stamps, kind="stable")
    if not np.array_equal(order, np.arange(len(stamps))):
        raise DatasetError(f"{path}: {topic} is not in time order")
    return Bag(path, topic, stamps, poses)


def _odometry_poses(
    r: Any, path: Path, topic: str, stamps: np.ndarray, max_gap_s: float
) -> np.ndarray:
    cons = [c for c in r.connections if c.topic == topic]
    if not cons or cons[0].msgtype not in ODOMETRY:
        have = sorted({c.topic for c in r.connections if c.msgtype in ODOMETRY})
        raise DatasetError(
            f"{path}: no nav_msgs/Odometry topic {topic!r}; it has {', '.join(have) or 'none'}",
            topics=have,
        )
    times, poses = [], []
    for con, t, raw in r.messages(connections=cons):
        p = r.deserialize(raw, con.msgtype).pose.pose
        times.append(t)
        o = p.orientation
        poses.append(
            from_quaternion([p.position.x, p.position.y, p.position.z], [o.x, o.y, o.z, o.w])
        )
    if not times:
        raise DatasetError(f"{path}: odometry topic {topic} holds no messages")
    t = np.asarray(times, dtype=np.int64)
    nearest = (
        np.clip(np.searchsorted(t, stamps), 1, len(t) - 1)
        if len(t) > 1
        else np.zeros(len(stamps), dtype=np.int64)
    )
    if len(t) > 1:
        left = nearest - 1
        nearest = np.where(np.abs(t[left] - stamps) <= np.abs(t[nearest] - stamps), left, nearest)
    gap = np.abs(t[nearest] - stamps) / 1e9
    if gap.max() > max_gap_s:
        i = int(gap.argmax())
        raise DatasetError(
            f"{path}: scan {i} is {gap[i]:.3f} s from the nearest odometry message; allowed: "
            f"at most {max_gap_s} s"
        )
    return np.stack([poses[j] for j in nearest])
