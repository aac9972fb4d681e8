"""The transform tree behind poses from /tf: chains through a common ancestor, interpolation
between samples, the gap rule at and past the ends, and the trees it refuses."""

from __future__ import annotations

import numpy as np
import pytest

from overlapmamba.core.errors import DatasetError
from overlapmamba.core.poses import rotation_z, yaw_deg
from overlapmamba.core.tf_tree import TransformTree, interpolate

S = 10**9


def _T(yaw: float, x: float = 0.0, y: float = 0.0) -> np.ndarray:
    T = rotation_z(yaw)
    T[:2, 3] = (x, y)
    return T


def test_interpolation_is_linear_in_translation_and_along_the_arc_in_rotation():
    T0, T1 = _T(170.0, 0.0, 0.0), _T(-150.0, 4.0, 2.0)  # 40° apart across ±180°
    a = np.array([0.0, 0.25, 0.5, 1.0])
    got = interpolate(np.stack([T0] * 4), np.stack([T1] * 4), a)
    for g, yaw in zip(got, 170.0 + 40.0 * a, strict=True):  # nlerp: 0.08° off at 0.25
        np.testing.assert_allclose(g[:3, :3], rotation_z(yaw)[:3, :3], atol=1e-9)
    np.testing.assert_allclose(got[:, :3, 3], a[:, None] * [4.0, 2.0, 0.0], atol=1e-12)
    np.testing.assert_array_equal(got[0], T0)  # a sample's own time: the sample itself


def test_a_chain_is_composed_through_the_common_ancestor():
    tree = TransformTree()
    tree.add("map", "odom", 0, _T(90.0, 10.0), static=True)
    for t, x in ((1 * S, 0.0), (S + S // 10, 2.0)):
        tree.add("odom", "base", t, _T(0.0, x))
    tree.add("base", "lidar", 0, _T(0.0, 0.5), static=True)
    tree.add("base", "camera", 0, _T(-90.0, 0.2), static=True)
    at = np.array([1 * S, S + S // 20, S + S // 5 - S // 20])  # a sample, between, 50 ms past
    lidar = tree.lookup("map", "lidar", at)
    np.testing.assert_allclose(
        lidar[:, :3, 3], [[10, 0.5, 0], [10, 1.5, 0], [10, 2.5, 0]], atol=1e-12
    )
    np.testing.assert_allclose(yaw_deg(lidar), 90.0)
    sibling = tree.lookup("camera", "lidar", at)  # up to "base" and down again
    np.testing.assert_allclose(sibling[0], np.linalg.inv(_T(-90.0, 0.2)) @ _T(0.0, 0.5), atol=1e-12)
    np.testing.assert_allclose(tree.lookup("lidar", "map", at), np.linalg.inv(lidar), atol=1e-12)


def test_trees_and_times_that_cannot_give_a_pose_are_refused_by_name():
    tree = TransformTree()
    tree.add("odom", "base", 1 * S, np.eye(4))
    tree.add("odom", "base", 2 * S, np.eye(4))
    with pytest.raises(DatasetError, match=r"'odom' → 'base' within 0.1 s of time 2.200 s"):
        tree.lookup("odom", "base", np.array([2 * S + S // 5]))
    with pytest.raises(DatasetError, match=r"within 0.1 s of time 1.500 s \(nearest 0.500 s"):
        tree.lookup("odom", "base", np.array([S + S // 2]))  # a dropout between samples
    tree.add("gps", "antenna", 0, np.eye(4), static=True)
    with pytest.raises(DatasetError, match="not connected .* roots are 'gps' and 'odom'"):
        tree.lookup("antenna", "base", np.array([S]))
    with pytest.raises(DatasetError, match="frame 'lidar' is in no transform; frames: antenna"):
        tree.lookup("odom", "lidar", np.array([S]))
    tree.add("base", "gps", 0, np.eye(4), static=True)
    tree.add("antenna", "odom", 0, np.eye(4), static=True)
    with pytest.raises(DatasetError, match="cycle"):
        tree.lookup("odom", "base", np.array([S]))
    bad = np.eye(4)
    bad[0, 3] = np.nan
    for parent, child, T in (("a", "a", np.eye(4)), ("", "b", np.eye(4)), ("a", "b", bad)):
        with pytest.raises(DatasetError, match="frames must be named and differ|finite 4×4"):
            tree.add(parent, child, 0, T)


def test_times_without_a_pose_may_be_nan_and_are_an_error_when_no_time_has_one():
    """Odometry that starts a second after the LiDAR (the usual recording): the whole drive
    was refused. With ``gaps="nan"`` (what the client's drives ask for) those times' poses
    are NaN and the rest are looked up as before; a link with no sample near any time is
    still named, as is a chain whose links cover different times."""
    tree = TransformTree()
    tree.add("map", "odom", 0, np.eye(4), static=True)
    for k in range(10, 31):  # 1.0 … 3.0 s
        tree.add("odom", "base", k * S // 10, _T(0.0, k / 10))
    at = np.arange(0, 31, 5) * S // 10  # 0.0 … 3.0 s: the first two before the odometry
    with pytest.raises(DatasetError, match="within 0.1 s of time 0.000 s"):
        tree.lookup("map", "base", at)
    got = tree.lookup("map", "base", at, gaps="nan")
    assert np.isnan(got[:2]).all() and not np.isnan(got[2:]).any()
    np.testing.assert_allclose(got[2:, 0, 3], [1.0, 1.5, 2.0, 2.5, 3.0], atol=1e-12)
    with pytest.raises(DatasetError, match="'odom' → 'base' within 0.1 s of time 6.000 s"):
        tree.lookup("map", "base", np.array([5 * S, 6 * S]), gaps="nan")
    tree.add("base", "lidar", 5 * S, np.eye(4))  # a timed link only at 5 s
    with pytest.raises(DatasetError, match="within 0.1 s"):  # each time lacks one link
        tree.lookup("map", "lidar", np.array([2 * S, 5 * S]), gaps="nan")
    with pytest.raises(ValueError, match="gaps"):
        tree.lookup("map", "base", at, gaps="skip")


def test_samples_past_one_block_and_out_of_order_are_looked_up_as_any():
    """The samples are held in blocks of CHUNK (a list of 4×4 arrays took ≈ 300 bytes a
    sample: an hour of a robot's /tf, gigabytes): a link of several blocks, its samples
    arriving out of order across them, interpolates as one series."""
    from overlapmamba.core.tf_tree import CHUNK

    n = 2 * CHUNK + 7
    stamps = np.arange(n) * (S // 100)
    order = np.random.default_rng(0).permutation(n)  # the bag's order: not the clock's
    tree = TransformTree()
    for i in order:
        tree.add("odom", "base", int(stamps[i]), _T(0.0, 0.01 * i))
    at = stamps[[0, CHUNK, n - 1]] + S // 200  # half-way to the next sample (the last: past)
    got = tree.lookup("odom", "base", at)[:, 0, 3]
    np.testing.assert_allclose(got, [0.005, 0.01 * CHUNK + 0.005, 0.01 * (n - 1)], atol=1e-12)


def test_a_transform_that_is_not_rigid_is_refused():
    """Only the top three rows of a sample are kept: a last row other than [0, 0, 0, 1]
    (a projective matrix, a stray scale) is named rather than dropped."""
    T = _T(0.0, 1.0)
    T[3, 3] = 2.0
    with pytest.raises(DatasetError, match=r"not rigid: its last row is \[0.0, 0.0, 0.0, 2.0\]"):
        TransformTree().add("odom", "base", 0, T)


def test_a_frame_sent_with_a_second_parent_refuses_only_the_lookups_through_it():
    """Found in review: tf2 lets a frame change parents (a tracker moving a person's frame
    from odom to map); one such frame anywhere refused the whole drive, although the LiDAR's
    chain never passes through it."""
    tree = TransformTree()
    tree.add("odom", "base", 1 * S, np.eye(4))
    tree.add("base", "lidar", 0, _T(0.0, 0.5), static=True)
    tree.add("odom", "person", 1 * S, np.eye(4))
    tree.add("map", "person", 2 * S, np.eye(4))  # re-parented: noted, not kept
    tree.add("map", "person", 3 * S, np.eye(4))
    np.testing.assert_allclose(tree.lookup("odom", "lidar", np.array([S]))[0], _T(0.0, 0.5))
    with pytest.raises(DatasetError, match="'person' has two parents, 'odom' and 'map'") as err:
        tree.lookup("lidar", "person", np.array([S]))
    assert err.value.detail["parents"] == ["odom", "map"]
    # a fixed frame reached only through the second parent (found in the day's review)
    tree.add("base", "velodyne", 0, np.eye(4), static=True)
    tree.add("map", "base", 2 * S, np.eye(4))
    for target in ("map", "person"):
        with pytest.raises(DatasetError, match="'base' has two parents, 'odom' and 'map'"):
            tree.lookup(target, "velodyne", np.array([S]))
