"""Yaw from per-column features: circular cross-correlation with sub-column refinement."""

from __future__ import annotations

import numpy as np
import pytest

from overlapmamba.core.poses import rotation_z, transform_points
from overlapmamba.core.projection import project
from overlapmamba.core.sensors import get_profile
from overlapmamba.core.yaw import circular_correlation, estimate_yaw

KITTI = get_profile("kitti-hdl64")


def test_integer_rolls_are_recovered_exactly():
    f = np.random.default_rng(0).normal(size=(8, 900))
    refs = np.stack([np.roll(f, k, axis=-1) for k in (0, 1, 225, 450, 899)])
    yaw, conf = estimate_yaw(f, refs)
    np.testing.assert_allclose(yaw, [0, 0.4, 90, 180, -0.4], atol=1e-9)
    np.testing.assert_allclose(conf, 1.0, atol=1e-9)


def test_correlation_of_unrelated_features_is_low():
    rng = np.random.default_rng(1)
    corr = circular_correlation(rng.normal(size=(8, 900)), rng.normal(size=(3, 8, 900)))
    assert corr.shape == (3, 900) and np.abs(corr).max() < 0.2
    with pytest.raises(ValueError, match="feature shapes differ"):
        circular_correlation(np.zeros((8, 900)), np.zeros((2, 4, 900)))


def test_features_that_are_constant_have_no_yaw_confidence():
    """A feature map with no variance (a reference sent as 2047 everywhere, a dead frame's
    query) has nothing to align: its confidence is 0, never the ratio of two rounding
    errors (it was ≈ 15.6 and 6.7e6, which ranked such a keyframe first). Every
    confidence is a cosine, in [−1, 1]."""
    rng = np.random.default_rng(3)
    f = rng.normal(size=(8, 900)) * 40 + 900
    flat = np.full((8, 900), 2047.0)
    for query, refs in [(f, flat[None]), (flat, f[None]), (np.zeros((8, 900)), f[None])]:
        for stored in (np.float64, np.float32, np.float16):
            _, conf = estimate_yaw(query.astype(stored), refs.astype(stored))
            np.testing.assert_array_equal(conf, 0.0)
    tiny = f[None] * 1e-200  # tiny but not constant: still a cosine
    corr = circular_correlation(f, np.concatenate([tiny, f[None] + 1e9]))
    assert np.all(np.abs(corr) <= 1.0)


def test_correlation_is_the_cosine_of_centred_maps_at_every_roll():
    """Against the definition, roll by roll: stored float16 references with channel means
    far from zero, a float32 query, one reference given as (C, W)."""
    rng = np.random.default_rng(2)
    q = (rng.normal(size=(4, 60)) + 3.0).astype(np.float32)
    refs = (rng.normal(size=(3, 4, 60)) * 2 - 5.0).astype(np.float16)

    def cosine(a, b):
        a = a - a.mean(axis=-1, keepdims=True)
        b = b - b.mean(axis=-1, keepdims=True)
        return float((a * b).sum() / np.linalg.norm(a) / np.linalg.norm(b))

    r64 = refs.astype(np.float64)
    q64 = q.astype(np.float64)
    want = [[cosine(q64, np.roll(r, -k, axis=-1)) for k in range(60)] for r in r64]
    np.testing.assert_allclose(circular_correlation(q, refs), want, atol=1e-12)
    np.testing.assert_allclose(circular_correlation(q, refs[1]), want[1:2], atol=1e-12)


@pytest.mark.real_data
def test_range_images_of_a_turned_real_scan_give_its_yaw(kitti_seq_dir):
    """The range image itself is an equivariant feature map: a sanity check of the sign and
    the sub-column refinement on real data, at angles that are not multiples of 0.4°."""
    from overlapmamba.core.io import read_points

    xyz = read_points(kitti_seq_dir / "velodyne" / "000030.bin").xyz
    query = np.clip(project(xyz, KITTI), 0, None)
    for theta in (13.37, -71.9, 158.2):
        # The sensor turned by +θ sees every point at −θ.
        turned = np.clip(project(transform_points(xyz, rotation_z(-theta)), KITTI), 0, None)
        yaw, conf = estimate_yaw(query, turned)
        assert abs(yaw[0] - theta) < 0.5, (theta, yaw)
        assert conf[0] > 0.8
