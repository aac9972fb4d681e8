"""ROS 2 PointCloud2 messages as scan bodies: every layout robots send decodes to the same
points, malformed ones are refused with the reason. Messages are made by rosbags' own CDR
serializer (an implementation independent of ours) from real KITTI points."""

from __future__ import annotations

import numpy as np
import pytest

from overlapmamba.core.errors import DecodeError, NonFiniteError
from overlapmamba.core.io import decode

pytest.importorskip("rosbags")
from ros_messages import F32, F64, LAYOUTS, U8, U16, XYZ, XYZI, message, patch_u32


@pytest.fixture(scope="module")
def points(kitti_seq_dir) -> np.ndarray:
    """4,000 real KITTI points, x y z intensity."""
    from overlapmamba.core.io import read_points

    cloud = read_points(kitti_seq_dir / "velodyne" / "000000.bin")
    assert cloud.intensity is not None
    return np.concatenate([cloud.xyz, cloud.intensity[:, None]], axis=1)[:4000]


@pytest.mark.parametrize("name", list(LAYOUTS))
def test_every_layout_decodes_to_the_same_points(points, name):
    layout, step, kw = LAYOUTS[name]
    cloud = decode(message(points, layout, step, **kw), "pointcloud2")
    want = points[: len(cloud.xyz)]
    assert len(cloud.xyz) == len(points)
    np.testing.assert_array_equal(cloud.xyz, want[:, :3].astype(np.float32))
    if any(n == "intensity" for n, _, _ in layout):
        kind = next(t for n, _, t in layout if n == "intensity")
        expect = (
            want[:, 3]
            if kind in (F32, F64)
            else want[:, 3].astype({U16: np.uint16, U8: np.uint8}[kind])
        )
        np.testing.assert_array_equal(cloud.intensity, np.asarray(expect, np.float32))


def test_nan_returns_of_a_cloud_that_is_not_dense_are_dropped(points):
    pts = points.copy()
    pts[::10, :3] = np.nan
    cloud = decode(message(pts, XYZI, 16, dense=False), "pointcloud2")
    assert len(cloud.xyz) == len(pts) - len(pts[::10])
    with pytest.raises(NonFiniteError):  # a dense cloud may not hold them
        decode(message(pts, XYZI, 16, dense=True), "pointcloud2")
    wide = points[:300].astype(np.float64)
    wide[5, 0] = np.inf  # a missing return written as infinity: dropped too
    cloud = decode(
        message(wide, [("x", 0, F64), ("y", 8, F64), ("z", 16, F64)], 24, dense=False),
        "pointcloud2",
    )
    assert len(cloud.xyz) == 299
    wide[6, 1] = 1e300  # finite, but no float32: not a missing return, a fault (422)
    with pytest.raises(NonFiniteError, match="within float32 range"):
        decode(
            message(wide, [("x", 0, F64), ("y", 8, F64), ("z", 16, F64)], 24, dense=False),
            "pointcloud2",
        )


def _malformed(good: bytes) -> dict[str, tuple[bytes, str]]:
    no_z = message(np.zeros((300, 4), np.float32), XYZ[:2], 8)
    int_x = message(
        np.zeros((300, 4), np.float32), [("x", 0, U16), ("y", 4, F32), ("z", 8, F32)], 12
    )
    beyond = message(np.zeros((300, 4), np.float32), XYZ, 12, declared=[*XYZ[:2], ("z", 10, F32)])
    twice = message(np.zeros((300, 4), np.float32), XYZI, 16, declared=[*XYZI, ("x", 12, F32)])
    stacked = message(
        np.zeros((300, 4), np.float32),
        XYZ,
        12,
        declared=[("x", 0, F32), ("y", 0, F32), ("z", 0, F32)],
    )
    # padding may repeat (PCL names every pad "_"): not refused
    padded = message(
        np.ones((300, 4), np.float32), XYZ, 16, declared=[*XYZ, ("_", 12, U8), ("_", 13, U8)]
    )
    assert len(decode(padded, "pointcloud2").xyz) == 300
    return {
        "empty": (b"", "encapsulation header"),
        "JSON": (b'{"points": []}', "encapsulation header"),
        "truncated header": (good[:9], "ends inside its header"),
        "truncated data": (good[:-50], "ends inside its data"),
        "no z": (no_z, "missing ['z']"),
        "integer x": (int_x, "field x has datatype 4"),
        "field beyond the point": (beyond, "does not fit in point_step"),
        "data shorter than declared": (patch_u32(good, "height", +1), "height × row_step"),
        "huge field count": (patch_u32(good, "fields", 10**6), "allowed: at most 64"),
        "huge frame_id": (patch_u32(good, "frame_id", 2**31), "allowed: at most 256"),
        "x twice": (twice, "field x is declared twice"),
        "x, y, z in one place": (stacked, "fields x (offset 0, 4 bytes) and y (offset 0"),
    }


def test_malformed_messages_are_refused_with_the_reason(points):
    good = message(points[:500], XYZI, 16)
    assert len(decode(good, "pointcloud2").xyz) == 500
    for name, (body, says) in _malformed(good).items():
        with pytest.raises(DecodeError) as err:
            decode(body, "pointcloud2")
        assert says in str(err.value), (name, str(err.value))
