"""ROS 2 PointCloud2 messages for tests, made by rosbags' own CDR serializer (an
implementation independent of ``overlapmamba.core.io.pointcloud2``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from rosbags.typesys import Stores, get_typestore

from overlapmamba.core.poses import quaternion, rotation_z

STORE = get_typestore(Stores.ROS2_HUMBLE)
PC2 = STORE.types["sensor_msgs/msg/PointCloud2"]
FIELD = STORE.types["sensor_msgs/msg/PointField"]
HEADER = STORE.types["std_msgs/msg/Header"]
TIME = STORE.types["builtin_interfaces/msg/Time"]
F32, F64, U16, U8 = 7, 8, 4, 2
MEDIA = "application/x-ros2-pointcloud2"
MOUNT = rotation_z(1.5)  # base_link ← velodyne in the recordings' /tf_static
MOUNT[:3, 3] = (0.8, 0.0, 1.73)
ODOM_IN_MAP = rotation_z(30.0)  # map ← odom
ODOM_IN_MAP[:3, 3] = (10.0, -5.0, 0.0)


def message(
    pts: np.ndarray,
    layout: list[tuple[str, int, int]],  # (name, offset, datatype)
    point_step: int,
    *,
    big: bool = False,
    height: int = 1,
    row_pad: int = 0,
    dense: bool = True,
    cdr_big: bool = False,
    declared: list[tuple[str, int, int]] | None = None,  # fields the message claims
) -> bytes:
    kinds = {F32: "f4", F64: "f8", U16: "u2", U8: "u1"}
    order = ">" if big else "<"
    dt = np.dtype(
        {
            "names": [n for n, _, _ in layout],
            "formats": [order + kinds[t] for _, _, t in layout],
            "offsets": [o for _, o, _ in layout],
            "itemsize": point_step,
        }
    )
    rec = np.zeros(len(pts), dt)
    for col, (name, _, _) in enumerate(layout):
        rec[name] = pts[:, min(col, 3)]
    width = len(pts) // height
    rows = rec[: width * height].tobytes()
    row_step = width * point_step + row_pad
    data = b"".join(
        rows[r * width * point_step : (r + 1) * width * point_step] + b"\xee" * row_pad
        for r in range(height)
    )
    msg = PC2(
        header=HEADER(stamp=TIME(sec=12, nanosec=5), frame_id="os_sensor"),
        height=height,
        width=width,
        fields=[FIELD(name=n, offset=o, datatype=t, count=1) for n, o, t in declared or layout],
        is_bigendian=big,
        point_step=point_step,
        row_step=row_step,
        data=np.frombuffer(data, np.uint8),
        is_dense=dense,
    )
    return bytes(STORE.serialize_cdr(msg, PC2.__msgtype__, little_endian=not cdr_big))


XYZ = [("x", 0, F32), ("y", 4, F32), ("z", 8, F32)]
XYZI = [*XYZ, ("intensity", 12, F32)]
LAYOUTS = {
    "xyz float32, packed": (XYZ, 12, {}),
    "xyzi float32, padded to 32 (Velodyne driver)": (
        [("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("intensity", 16, F32)],
        32,
        {},
    ),
    "xyz float64 + uint16 intensity": (
        [("x", 0, F64), ("y", 8, F64), ("z", 16, F64), ("intensity", 24, U16)],
        32,
        {},
    ),
    "xyzi float32, big endian": (XYZI, 16, {"big": True}),
    "organised 4 rows, row padding": (XYZI, 16, {"height": 4, "row_pad": 8}),
    "xyzi, CDR big endian, uint8 intensity": (
        [*XYZ, ("intensity", 12, U8)],
        16,
        {"cdr_big": True},
    ),
}


def patch_u32(msg: bytes, which: str, value: int) -> bytes:
    """A little-endian message of ``message`` (frame_id "os_sensor") with one uint32 set:
    ``frame_id`` (its length), ``height`` (increased by value), ``width`` or ``fields``
    (their count)."""
    frame = len(b"os_sensor\0")
    at = {"frame_id": 12}  # after encapsulation (4) and stamp (8)
    at["height"] = 16 + frame + (-(frame) % 4)
    at["width"] = at["height"] + 4
    at["fields"] = at["height"] + 8
    b = bytearray(msg)
    old = int.from_bytes(b[at[which] : at[which] + 4], "little")
    new = old + value if which == "height" else value
    b[at[which] : at[which] + 4] = new.to_bytes(4, "little")
    return bytes(b)


def write_recordings(
    out: Path,
    clouds: list[np.ndarray],
    poses: np.ndarray,
    step_s: float = 0.1,
    *,
    start_s: float = 1.0,
    static: bool = True,
) -> dict[str, Path]:
    """The same drive (x y z intensity scans on /points in frame "velodyne", their 4×4
    poses as nav_msgs/Odometry on /odom and as the tf chain map → odom → base_link →
    velodyne on /tf and /tf_static) as a rosbag2 with SQLite storage, a rosbag2 with MCAP
    storage, a bare MCAP file and a ROS 1 bag, written by rosbags.

    The tf chain makes the poses take every step of a lookup: map → odom is re-sent before
    each scan, odom → base_link is sent 20 ms before and after each scan, moved ∓ 0.2 m and
    ∓ 2° (so only interpolation gives the pose at the scan's stamp), and base_link →
    velodyne (the LiDAR's mounting) is static. ``start_s``: the first scan's time;
    ``static``: whether /tf_static is written (a split recording's later parts lack it)."""
    import shutil

    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import get_types_from_msg

    ros1 = get_typestore(Stores.ROS1_NOETIC)
    if "tf2_msgs/msg/TFMessage" not in ros1.types:  # not among Noetic's built-in types
        ros1.register(
            get_types_from_msg(
                "geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"
            )
        )
    paths = {}
    for name, store, plugin in (
        ("rosbag2-sqlite", STORE, StoragePlugin.SQLITE3),
        ("rosbag2-mcap", STORE, StoragePlugin.MCAP),
        ("ros1.bag", ros1, None),
    ):
        path = out / name
        writer = (
            Writer1(path) if plugin is None else Writer2(path, version=8, storage_plugin=plugin)
        )
        with writer as w:
            kw = {"typestore": store}
            pc = w.add_connection("/points", "sensor_msgs/msg/PointCloud2", **kw)
            od = w.add_connection("/odom", "nav_msgs/msg/Odometry", **kw)
            tf = w.add_connection("/tf", "tf2_msgs/msg/TFMessage", **kw)
            fixed = w.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", **kw)
            ser = store.serialize_ros1 if plugin is None else store.serialize_cdr

            if static:
                _send(w, fixed, store, ser, 1, ("base_link", "velodyne", MOUNT))
            for i, (pts, T) in enumerate(zip(clouds, poses, strict=True)):
                t = int((start_s + i * step_s) * 1e9)
                base = np.linalg.inv(ODOM_IN_MAP) @ T @ np.linalg.inv(MOUNT)
                _send(w, tf, store, ser, t - 30_000_000, ("map", "odom", ODOM_IN_MAP))
                for s, dt in ((-1, -20_000_000), (1, 20_000_000)):
                    moved = rotation_z(2.0 * s)
                    moved[0, 3] = 0.2 * s
                    _send(w, tf, store, ser, t + dt, ("odom", "base_link", base @ moved))
                w.write(pc, t, ser(_cloud(store, pts, t), "sensor_msgs/msg/PointCloud2"))
                w.write(od, t + 1000, ser(_odometry(store, T, t), "nav_msgs/msg/Odometry"))
        paths[name] = path
    bare = out / "drive.mcap"
    shutil.copy(next((out / "rosbag2-mcap").glob("*.mcap")), bare)
    paths["mcap"] = bare
    return paths


def _header(store, t: int, frame: str = "velodyne"):
    H, T = store.types["std_msgs/msg/Header"], store.types["builtin_interfaces/msg/Time"]
    extra = {"seq": 0} if "seq" in H.__dataclass_fields__ else {}
    return H(stamp=T(sec=t // 10**9, nanosec=t % 10**9), frame_id=frame, **extra)


def _send(w, con, store, ser, t: int, *links) -> None:
    w.write(con, t, ser(_tf(store, t, links), "tf2_msgs/msg/TFMessage"))


def _tf(store, t: int, links):
    ty = store.types
    out = []
    for parent, child, T in links:
        q = quaternion(T[:3, :3])
        out.append(
            ty["geometry_msgs/msg/TransformStamped"](
                header=_header(store, t, parent),
                child_frame_id=child,
                transform=ty["geometry_msgs/msg/Transform"](
                    translation=ty["geometry_msgs/msg/Vector3"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                    rotation=ty["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
                ),
            )
        )
    return ty["tf2_msgs/msg/TFMessage"](transforms=out)


def _cloud(store, pts: np.ndarray, t: int):
    F = store.types["sensor_msgs/msg/PointField"]
    data = np.ascontiguousarray(pts, dtype="<f4")
    return store.types["sensor_msgs/msg/PointCloud2"](
        header=_header(store, t),
        height=1,
        width=len(data),
        fields=[F(name=n, offset=4 * k, datatype=F32, count=1) for k, n in enumerate("xyz")]
        + [F(name="intensity", offset=12, datatype=F32, count=1)],
        is_bigendian=False,
        point_step=16,
        row_step=16 * len(data),
        data=np.frombuffer(data.tobytes(), np.uint8),
        is_dense=True,
    )


def _odometry(store, T: np.ndarray, t: int):
    ty = store.types
    q = quaternion(T[:3, :3])
    pose = ty["geometry_msgs/msg/Pose"](
        position=ty["geometry_msgs/msg/Point"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
        orientation=ty["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
    )
    twist = ty["geometry_msgs/msg/Twist"](
        linear=ty["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        angular=ty["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
    )
    return ty["nav_msgs/msg/Odometry"](
        header=_header(store, t),
        child_frame_id="velodyne",
        pose=ty["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=ty["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
    )
