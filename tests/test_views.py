"""Sub-column views (overlapmamba.core.views): what each view is, how views combine, refusals."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from overlapmamba.core.io import read_points
from overlapmamba.core.poses import rotation_z, transform_points
from overlapmamba.core.projection import project
from overlapmamba.core.views import MAX_VIEWS, combine_views, project_views, view_turns
from tests.test_projection import KITTI, SMALL, random_scan


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 300), st.integers(1, 4))
def test_view_zero_is_the_projection_and_view_j_the_sensor_turned(seed, n, views):
    pts = random_scan(np.random.default_rng(seed), n)
    images = project_views(pts, SMALL, views)
    assert images.shape == (views, SMALL.height, SMALL.width) and images.dtype == np.float32
    np.testing.assert_array_equal(images[0], project(pts, SMALL))
    for j, turn in enumerate(view_turns(views, SMALL)):
        # the sensor turned by j/views of a column: its points turn the other way
        turned = project(transform_points(pts, rotation_z(-turn)), SMALL)
        # turned points keep their range to float32 rounding; one sitting on a column
        # boundary may land in the next column: rarely
        assert np.isclose(images[j], turned, rtol=1e-5, atol=0).mean() >= 0.99


def test_a_turn_by_whole_columns_rolls_every_view(kitti_seq_dir):
    xyz = read_points(kitti_seq_dir / "velodyne" / "000010.bin").xyz
    images = project_views(xyz, KITTI, 3)
    # the sensor turned by +7 columns: the points by −7, every view rolls by +7 columns, up to
    # points on a column boundary (float rounding)
    turned = project_views(transform_points(xyz, rotation_z(-7 * 360.0 / KITTI.width)), KITTI, 3)
    assert np.isclose(turned, np.roll(images, 7, axis=-1), atol=1e-3).mean() > 0.99
    # the views differ from each other: each is its own sub-column phase
    assert all(not np.isclose(images[j], images[0], atol=1e-3).all() for j in (1, 2))
    assert all(np.isclose(images[j], images[0], atol=1e-3).mean() < 0.9 for j in (1, 2))


def test_views_combine_into_the_unit_mean_and_view_zeros_yaw():
    rng = np.random.default_rng(0)
    desc = rng.normal(size=(6, 5)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    yaw = rng.normal(size=(6, 2, 7)).astype(np.float32)
    d, y = combine_views(desc, yaw, 3)
    assert d.shape == (2, 5) and y.shape == (2, 2, 7)
    want = desc.reshape(2, 3, 5).mean(1)
    np.testing.assert_allclose(d, want / np.linalg.norm(want, axis=1, keepdims=True), rtol=1e-6)
    np.testing.assert_array_equal(y, yaw[[0, 3]])
    same = combine_views(desc, yaw, 1)
    assert same[0] is desc and same[1] is yaw


@pytest.mark.parametrize("views", [0, -1, MAX_VIEWS + 1, 1.5, "2", True])
def test_a_count_outside_the_allowed_is_refused(views):
    with pytest.raises(ValueError, match=f"from 1 to {MAX_VIEWS}"):
        project_views(np.zeros((3, 3), np.float32), SMALL, views)


def test_outputs_that_are_not_whole_scans_are_refused():
    with pytest.raises(ValueError, match="not whole scans of 2 views"):
        combine_views(np.zeros((3, 4), np.float32), np.zeros((3, 1, 2), np.float32), 2)
    with pytest.raises(ValueError, match="not whole scans"):
        combine_views(np.zeros((4, 4), np.float32), np.zeros((2, 1, 2), np.float32), 2)


def test_the_range_cache_keeps_each_count_apart(kitti_seq_dir, tmp_path, monkeypatch):
    pytest.importorskip("torch")
    from overlapmamba.core.datasets import open_sequence
    from overlapmamba.train.rangecache import cache_key, range_images

    monkeypatch.setenv("OVERLAPMAMBA_CACHE", str(tmp_path))
    seq = open_sequence(kitti_seq_dir)
    one, two = range_images(seq, KITTI, progress=False), range_images(seq, KITTI, views=2)
    assert one.shape == (len(seq), 64, 900) and two.shape == (len(seq), 2, 64, 900)
    assert cache_key(seq, KITTI) != cache_key(seq, KITTI, 2)
    np.testing.assert_array_equal(two[:, 0], one)  # view 0 is the plain projection
    i = 37
    want = project_views(seq.points(i), KITTI, 2).astype(np.float16)
    np.testing.assert_array_equal(two[i], want)
    assert len(list((tmp_path / "range_images").glob("*.npy"))) == 2


def test_the_range_cache_keeps_each_sensor_input_apart(kitti_seq_dir, tmp_path, monkeypatch):
    """The same scans as another sensor's (thinned KITTI rings would be, here the sensor
    table alone differs) or by another mode are other images: other cache files; the
    model's own sensor keeps the key it always had."""
    pytest.importorskip("torch")
    from dataclasses import replace

    from overlapmamba.core.datasets import open_sequence
    from overlapmamba.core.sensors import CATALOGUE
    from overlapmamba.core.sensors.input import SensorInput
    from overlapmamba.train.rangecache import cache_key, range_images

    monkeypatch.setenv("OVERLAPMAMBA_CACHE", str(tmp_path))
    seq = open_sequence(kitti_seq_dir)
    seq = replace(seq, scan_paths=seq.scan_paths[:5], poses=seq.poses[:5])
    own = SensorInput(KITTI, CATALOGUE["kitti-hdl64"], "elevation")
    vlp = SensorInput(KITTI, CATALOGUE["vlp16"], "elevation")
    vlp_rows = SensorInput(KITTI, CATALOGUE["vlp16"], "rows")
    keys = {cache_key(seq, KITTI, 1, s) for s in (own, vlp, vlp_rows)}
    assert len(keys) == 3 and cache_key(seq, KITTI, 1, own) == cache_key(seq, KITTI)
    images = range_images(seq, KITTI, sensor=vlp, progress=False)
    np.testing.assert_array_equal(images[2], vlp.project(seq.points(2))[0].astype(np.float16))
    with pytest.raises(ValueError, match="not the profile"):
        range_images(seq, SMALL, sensor=vlp, progress=False)
