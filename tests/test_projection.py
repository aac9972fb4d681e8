"""Range projection: fast vs reference, yaw-roll property, and the real reference images."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from overlapmamba.core.io import read_points
from overlapmamba.core.poses import rotation_z, transform_points
from overlapmamba.core.projection import (
    pixel_coordinates,
    pixel_index,
    project,
    project_reference,
    project_with_index,
    valid_mask,
)
from overlapmamba.core.sensors import get_profile

KITTI = get_profile("kitti-hdl64")
SMALL = KITTI.replace(name="small", height=16, width=90, max_range=40.0)


def random_scan(rng: np.random.Generator, n: int) -> np.ndarray:
    """Points spread over the sensor's vertical FOV, 1–60 m away."""
    az = rng.uniform(-np.pi, np.pi, n)
    el = np.radians(rng.uniform(-26, 4, n))
    r = rng.uniform(1, 60, n)
    return np.column_stack(
        [r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)]
    ).astype(np.float32)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 400), st.sampled_from([-1.0, 0.0]))
def test_fast_projection_equals_reference(seed, n, empty):
    rng = np.random.default_rng(seed)
    pts = random_scan(rng, n)
    pts[: n // 4] = pts[n // 4 : 2 * (n // 4)] * 1.001  # force pixel collisions
    profile = SMALL.replace(empty_value=empty)
    np.testing.assert_array_equal(project(pts, profile), project_reference(pts, profile))


def placements(pts: np.ndarray, profile) -> np.ndarray:
    """pixel_coordinates' flat pixel of every point, H·W for a dropped one."""
    pc = pixel_coordinates(pts, profile)
    pix = np.full(len(pts), profile.height * profile.width, np.int64)
    pix[pc.keep] = pc.row.astype(np.int64) * profile.width + pc.col
    return pix


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 400))
def test_pixel_index_places_points_as_pixel_coordinates(seed, n):
    rng = np.random.default_rng(seed)
    pts = random_scan(rng, n) * rng.uniform(0.01, 2.0)  # some under min_range, some over max
    pts[: n // 5, 2] += 30.0  # and some above the field of view (rows clamped to 0)
    profile = SMALL.replace(min_range=2.0)
    pix, depth = pixel_index(np.ascontiguousarray(pts.T), profile)
    np.testing.assert_array_equal(pix, placements(pts, profile))
    np.testing.assert_array_equal(
        depth[pixel_coordinates(pts, profile).keep], pixel_coordinates(pts, profile).depth
    )


def test_pixel_index_on_real_scans(kitti_seq_dir):
    for frame in ("000000", "000050"):
        pts = read_points(kitti_seq_dir / "velodyne" / f"{frame}.bin").xyz
        pix, _ = pixel_index(np.ascontiguousarray(pts.T), KITTI)
        np.testing.assert_array_equal(pix, placements(pts, KITTI))


def test_nearest_point_wins_and_index_points_at_it():
    pts = np.array([[10, 0, 0], [5, 0, 0], [7, 0, 0], [0, 20, 0]], np.float32)
    image, index = project_with_index(pts, KITTI)
    row, col = np.argwhere(index == 1)[0]
    assert image[row, col] == pytest.approx(5.0)
    assert set(index[index >= 0]) == {1, 3}
    assert valid_mask(image, KITTI).sum() == 2


def test_points_outside_range_are_dropped():
    pts = np.array([[0, 0, 0], [80.0, 0, 0], [79.0, 0, 0], [0, 0.5, 0]], np.float32)
    pc = pixel_coordinates(pts, KITTI.replace(min_range=1.0))
    assert pc.keep.tolist() == [False, False, True, False]
    assert (project(pts, KITTI) > 0).sum() == 2


def test_column_zero_looks_backwards_and_columns_sweep_clockwise():
    W = KITTI.width
    pc = pixel_coordinates(np.array([[10, 0, 0], [0, 10, 0], [0, -10, 0]], np.float32), KITTI)
    assert pc.col.tolist() == [W // 2, W // 4, 3 * W // 4]


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(-899, 899))
def test_rotation_by_column_steps_rolls_the_image(seed, k):
    """Rotating a scan by k·360/W degrees about z rolls its range image by −k columns, up to
    points that sit on a column boundary (float rounding)."""
    rng = np.random.default_rng(seed)
    pts = random_scan(rng, 3000)
    rotated = transform_points(pts, rotation_z(k * 360.0 / KITTI.width))
    a = np.roll(project(pts, KITTI), -k, axis=1)
    b = project(rotated, KITTI)
    same = np.isclose(a, b, atol=1e-4)
    assert same.mean() > 0.995, f"only {same.mean():.4f} of pixels rolled exactly"


def test_projection_matches_overlapnet_reference_images(kitti_reference_dir):
    profile = KITTI.replace(max_range=50.0, empty_value=-1.0)
    for frame in ("000000", "000001"):
        ours = project(read_points(kitti_reference_dir / f"{frame}.bin"), profile)
        ref = np.load(kitti_reference_dir / f"depth_{frame}.npy")
        assert ref.shape == ours.shape == (64, 900)
        mask_agree = ((ours > 0) == (ref > 0)).mean()
        both = (ours > 0) & (ref > 0)
        depth_agree = (np.abs(ours - ref)[both] < 1e-3).mean()
        assert mask_agree >= 0.999, f"{frame}: masks agree on {mask_agree:.5f}"
        assert depth_agree >= 0.995, f"{frame}: depth within 1 mm on {depth_agree:.5f}"


def test_real_scan_rolls_under_yaw(kitti_seq_dir):
    pts = read_points(kitti_seq_dir / "velodyne" / "000010.bin").xyz
    k = 137
    rolled = np.roll(project(pts, KITTI), -k, axis=1)
    rotated = project(transform_points(pts, rotation_z(k * 360.0 / KITTI.width)), KITTI)
    assert np.isclose(rolled, rotated, atol=1e-3).mean() > 0.99
