"""Recorded robot drives in ROS formats, read with rosbags (one library for all of them):

    drive.bag                    ROS 1 bag
    drive/ (metadata.yaml)       rosbag2, SQLite (.db3) or MCAP storage
    drive.mcap                   a bare MCAP file of ROS 2 messages

A topic of ``sensor_msgs/msg/PointCloud2`` becomes a drive's scans, in the order recorded,
each decoded by :func:`overlapmamba.core.io.pointcloud2.decode_message` (so every field layout a
driver sends works, and a malformed message names what is wrong). Times are the bag's
receive times. Poses, when asked for, are each scan's at its header stamp, from one of:

    odometry="/odom"           a nav_msgs/msg/Odometry topic: its pose (the child frame
                               taken as the LiDAR's), interpolated between messages
    tf="map"                   /tf and /tf_static: the scans' frame (their header frame_id)
    tf="map:base_link"         or the named one, in the named fixed frame, through the chain
                               of transforms between them (``overlapmamba.core.tf_tree``)

A scan whose nearest pose sample is more than ``max_pose_gap_s`` away is refused.
"""

from __future__ import annotations

import contextlib
import threading
import weakref
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from overlapmamba.core.datasets.base import scan_order
from overlapmamba.core.errors import DatasetError, LidarCoreError
from overlapmamba.core.io.pointcloud2 import decode_message
from overlapmamba.core.points import PointCloud
from overlapmamba.core.poses import from_quaternion
from overlapmamba.core.tf_tree import TransformTree

PREFETCH = 8  # scans decoded per seek
CACHED = 32  # scans kept (≈ 2 MB each for a 120k-point scan)
POINTCLOUD2 = ("sensor_msgs/msg/PointCloud2", "sensor_msgs/PointCloud2")
ODOMETRY = ("nav_msgs/msg/Odometry", "nav_msgs/Odometry")
TF = ("tf2_msgs/msg/TFMessage", "tf2_msgs/TFMessage", "tf/msg/tfMessage", "tf/tfMessage")
TF_TOPICS = {"/tf": False, "/tf_static": True}  # topic -> static


def is_bag(path: str | Path) -> bool:
    """A ROS 1 bag, a rosbag2 folder, a bare MCAP file, or a folder of ROS 1 bags (a
    recording split by ``rosbag record --split``)."""
    p = Path(path)
    if p.is_file():
        return p.suffix in (".bag", ".mcap")
    if not p.is_dir():
        return False
    if (p / "metadata.yaml").is_file():
        return True
    # a folder of .bag parts; not a sequence folder that holds a stray bag
    sequence = (p / "velodyne").is_dir() or (p / "poses.txt").is_file() or any(p.glob("*.pcd"))
    return not sequence and any(p.glob("*.bag"))


def _parts(path: Path) -> list[Path]:
    """The files of the recording: a folder of ROS 1 bags is read as one, its parts in the
    order of the numbers in their names (``drive_2.bag`` before ``drive_10.bag``)."""
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        return sorted(path.glob("*.bag"), key=scan_order)
    return [path]


def _reader(path: Path) -> Any:
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError as err:  # pragma: no cover - the client and serve extras install it
        raise DatasetError(
            f"{path}: reading ROS bags needs the rosbags package (pip install rosbags)"
        ) from err
    return AnyReader(_parts(path), default_typestore=get_typestore(Stores.ROS2_HUMBLE))


def _close_quietly(reader: Any) -> None:
    with contextlib.suppress(Exception):  # closing one that failed halfway
        reader.close()


@dataclass
class Bag:
    """One PointCloud2 topic of a recording: ``len``, ``points(i)``, ``times``, ``poses``."""

    path: Path
    topic: str
    stamps_ns: np.ndarray  # (N,) int64: the bag's receive times, as it indexes them
    poses: np.ndarray | None  # (N, 4, 4) from the odometry topic, or None
    _cache: dict[int, PointCloud] = field(default_factory=dict, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    # one reader, opened at the first read and kept: opening a recording costs its index (a
    # ROS 1 bag's), or all of it (a file-compressed rosbag2 is inflated into a temporary
    # folder); reads through it take turns
    _reader: Any = field(default=None, repr=False)
    _reading: threading.Lock = field(default_factory=threading.Lock, repr=False)
    _finalizer: Any = field(default=None, repr=False)

    sensor: str | None = None  # the catalogue sensor, as a Sequence has it (None: not said)
    clouds: tuple[str, ...] = ()  # every PointCloud2 topic the recording holds
    # odometry or /tf samples left out as unusable (a zero or non-finite quaternion, a
    # non-finite position, an unnamed frame): gaps, as a publisher still starting leaves them
    bad_pose_samples: int = 0

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

    def xyzi(self, i: int) -> np.ndarray:
        """Scan ``i`` as (N, 4) float32 ``xyzi``, as a service takes it."""
        return self.points(i).as_xyzi()

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
        failure: Exception | None = None
        with self._reading:
            try:  # changed or gone since it was indexed, the recording says so
                r = self._opened()
                cons = [c for c in r.connections if c.topic == self.topic]
                for con, _, raw in r.messages(connections=cons, start=t):
                    if j >= i:
                        msg = r.deserialize(raw, con.msgtype)
                        found[j] = decode_message(msg, source=f"{self.topic} message {j}")
                    j += 1
                    if j >= min(i + PREFETCH, len(self)):
                        break
            except LidarCoreError as err:  # a message that does not decode: the reader is fine
                failure = err
            except Exception as err:  # a damaged file, cut short: those read serve
                failure = err
                self.close()  # the next read opens it afresh
        if i not in found:
            why = "is gone" if failure is None else f"cannot be read: {failure}"
            raise DatasetError(
                f"{self.path}: message {i} of {self.topic} (t = {t * 1e-9:.3f} s) {why}"
            ) from failure
        with self._lock:
            self._cache.update(found)
            while len(self._cache) > CACHED:
                self._cache.pop(next(iter(self._cache)))
        return found[i]

    def _opened(self) -> Any:
        if self._reader is None:
            r = _reader(self.path)
            r.open()
            self._reader = r
            self._finalizer = weakref.finalize(self, _close_quietly, r)  # when it is dropped
        return self._reader

    def close(self) -> None:
        """Close the recording's reader (the next read opens it again)."""
        r, self._reader = self._reader, None
        if self._finalizer is not None:
            self._finalizer.detach()
            self._finalizer = None
        if r is not None:
            _close_quietly(r)

    def _nth(self, i: int) -> int:
        """Which of the messages sharing scan i's time stamp it is."""
        return int(i - np.searchsorted(self.stamps_ns, self.stamps_ns[i]))


def open_bag(
    path: str | Path,
    *,
    topic: str | None = None,
    odometry: str | None = None,
    tf: str | None = None,
    max_pose_gap_s: float = 0.1,
    pose_gaps: str = "raise",
    sensor: str | None = None,
) -> Bag:
    """Index a recording's PointCloud2 topic (``topic``: which, when it holds several) and,
    when ``odometry`` names a topic or ``tf`` a frame ("FIXED" or "FIXED:CHILD"), each
    scan's pose. A scan with no pose sample within ``max_pose_gap_s`` is an error, or with
    ``pose_gaps="nan"`` a NaN pose (the odometry started late, or paused; an error still
    when no scan has one). ``sensor``: the catalogue sensor that recorded it (a recording
    does not say; nothing is guessed). Raises DatasetError naming what is wrong and what
    the recording holds, ProfileError for an unknown sensor."""
    if sensor is not None:
        from overlapmamba.core.sensors.catalogue import catalogue_name

        sensor = catalogue_name(sensor)
    path = Path(path)
    if not is_bag(path):
        raise DatasetError(
            f"{path} is not a ROS recording; allowed: a .bag file, a rosbag2 folder "
            "(metadata.yaml), a .mcap file or a folder of a split recording's .bag files"
        )
    if odometry is not None and tf is not None:
        raise DatasetError("poses come from an odometry topic or from /tf, not both")
    try:
        with _reader(path) as r:
            topic = _cloud_topic(r, path, topic)
            clouds = tuple(sorted({c.topic for c in r.connections if c.msgtype in POINTCLOUD2}))
            cons = [c for c in r.connections if c.topic == topic]
            stamps, headers = [], []
            for con, t, raw in r.messages(connections=cons):
                stamps.append(t)
                if odometry is not None or tf is not None:
                    h = r.deserialize(raw, con.msgtype).header
                    headers.append((h.stamp.sec * 10**9 + h.stamp.nanosec, h.frame_id))
            if not stamps:
                raise DatasetError(f"{path}: topic {topic} holds no messages")
            poses, bad = None, 0
            if odometry is not None:
                with _named(path):
                    tree, bad = _odometry_tree(r, path, odometry)
                    with _left_out(bad):
                        poses = tree.lookup(
                            odometry,
                            "scan",
                            _stamps(path, headers),
                            max_gap_s=max_pose_gap_s,
                            gaps=pose_gaps,
                        )
            elif tf is not None:
                fixed, _, child = tf.partition(":")
                with _named(path):
                    tree, bad = _tf_tree(r, path)
                    child = child or _frame(path, topic, headers)
                    with _left_out(bad):
                        poses = tree.lookup(
                            fixed.lstrip("/"),
                            child.lstrip("/"),
                            _stamps(path, headers),
                            max_gap_s=max_pose_gap_s,
                            gaps=pose_gaps,
                        )
    except DatasetError:
        raise
    except Exception as err:  # rosbags raises its own types for damaged files
        raise DatasetError(f"{path}: the recording cannot be read: {err}") from err
    ns = np.asarray(stamps, dtype=np.int64)
    if not np.array_equal(np.argsort(ns, kind="stable"), np.arange(len(ns))):
        raise DatasetError(f"{path}: {topic} is not in time order")
    return Bag(path, topic, ns, poses, sensor=sensor, clouds=clouds, bad_pose_samples=bad)


@contextmanager
def _left_out(bad: int) -> Iterator[None]:
    """A pose lookup's error, with how many samples were left out as no pose: where all of a
    link's were, the lookup alone could say only that its frame is in no transform."""
    try:
        yield
    except DatasetError as err:
        if not bad:
            raise
        raise DatasetError(
            f"{err} ({bad} odometry or /tf samples were left out as no pose: a zero or "
            "non-finite quaternion or position, an unnamed frame)",
            **err.detail,
            left_out=bad,
        ) from err


@contextmanager
def _named(path: Path) -> Iterator[None]:
    """A transform tree's errors, prefixed with the recording they are about."""
    try:
        yield
    except DatasetError as err:
        if str(err).startswith(f"{path}:"):
            raise
        raise DatasetError(f"{path}: {err}", **err.detail) from err


def _cloud_topic(r: Any, path: Path, topic: str | None) -> str:
    clouds = sorted({c.topic for c in r.connections if c.msgtype in POINTCLOUD2})
    if topic is None:
        if not clouds:
            have = sorted({f"{c.topic} ({c.msgtype})" for c in r.connections})
            raise DatasetError(
                f"{path}: no sensor_msgs/PointCloud2 topic, which the scans are read from; "
                f"it holds {', '.join(have) or 'no topics'}",
                topics=clouds,
            )
        if len(clouds) != 1:
            raise DatasetError(
                f"{path}: {len(clouds)} PointCloud2 topics ({', '.join(clouds)}); "
                "name one with --topic",
                topics=clouds,
            )
        return clouds[0]
    if topic not in clouds:
        raise DatasetError(
            f"{path}: no PointCloud2 topic {topic!r}; it has {', '.join(clouds) or 'none'}",
            topics=clouds,
        )
    return topic


def _stamps(path: Path, headers: list[tuple[int, str]]) -> np.ndarray:
    """The scans' header stamps, the times their poses are looked up at."""
    stamps = np.array([s for s, _ in headers], dtype=np.int64)
    if not stamps.any():
        raise DatasetError(f"{path}: the scans' header stamps are all zero; poses need them")
    return stamps


def _frame(path: Path, topic: str, headers: list[tuple[int, str]]) -> str:
    """The scans' frame (their header frame_id), the child frame of their /tf poses."""
    frames = sorted({f for _, f in headers})
    if len(frames) != 1 or not frames[0]:
        raise DatasetError(
            f"{path}: the scans of {topic} are in frames {frames}; name the LiDAR's frame "
            "with --tf FIXED:CHILD"
        )
    return frames[0]


def _pose(p: Any) -> np.ndarray | None:
    """geometry_msgs Pose or Transform → 4×4; None where it is no pose: a zero quaternion
    (a publisher's before it has one, which normalising would make the identity) or a
    non-finite value. A quaternion is scaled by its largest part first: one whose norm
    overflows (1e200) is a rotation still, not the identity."""
    xyz = p.position if hasattr(p, "position") else p.translation
    o = p.orientation if hasattr(p, "orientation") else p.rotation
    t, q = np.array([xyz.x, xyz.y, xyz.z], float), np.array([o.x, o.y, o.z, o.w], float)
    if not (np.isfinite(t).all() and np.isfinite(q).all()):
        return None
    big = np.abs(q).max()
    if not big > 0 or not np.linalg.norm(q / big) * big > 1e-9:
        return None
    return from_quaternion(t, q / big)


def _stamp(header: Any) -> int:
    return int(header.stamp.sec) * 10**9 + int(header.stamp.nanosec)


def _odometry_tree(r: Any, path: Path, topic: str) -> tuple[TransformTree, int]:
    """The odometry topic as one link, topic → "scan" (its frame names, often unset
    by hand-written nodes, are not needed), and how many of its samples were no pose."""
    cons = [c for c in r.connections if c.topic == topic]
    if not cons or cons[0].msgtype not in ODOMETRY:
        have = sorted({c.topic for c in r.connections if c.msgtype in ODOMETRY})
        raise DatasetError(
            f"{path}: no nav_msgs/Odometry topic {topic!r}; it has {', '.join(have) or 'none'}",
            topics=have,
        )
    tree, bad = TransformTree(), 0
    for con, _, raw in r.messages(connections=cons):
        msg = r.deserialize(raw, con.msgtype)
        pose = _pose(msg.pose.pose)
        if pose is None:
            bad += 1
            continue
        tree.add(topic, "scan", _stamp(msg.header), pose)
    if not tree.frames:
        raise DatasetError(
            f"{path}: odometry topic {topic} holds no usable pose ({bad} unusable messages)"
        )
    return tree, bad


def _tf_tree(r: Any, path: Path) -> tuple[TransformTree, int]:
    """Every transform on /tf (timed) and /tf_static (static), and how many were left out as
    no transform (an unnamed frame, a zero quaternion, a non-finite value: on a link off the
    LiDAR's chain such a sample must not make the drive unreadable)."""
    cons = [c for c in r.connections if c.topic in TF_TOPICS and c.msgtype in TF]
    if not cons:
        raise DatasetError(
            f"{path}: no /tf or /tf_static topic of tf2_msgs/TFMessage; name an odometry "
            "topic instead (--odometry)"
        )
    tree, bad = TransformTree(), 0
    for con, _, raw in r.messages(connections=cons):
        for tr in r.deserialize(raw, con.msgtype).transforms:
            parent, child = tr.header.frame_id.lstrip("/"), tr.child_frame_id.lstrip("/")
            pose = _pose(tr.transform)
            if pose is None or not parent or not child or parent == child:
                bad += 1
                continue
            tree.add(parent, child, _stamp(tr.header), pose, static=TF_TOPICS[con.topic])
    return tree, bad
