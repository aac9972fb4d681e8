"""Training augmentation: each transform does what it says, per scan, reproducibly."""

from __future__ import annotations

import numpy as np
import pytest

from overlapmamba.core.sensors import get_profile
from overlapmamba.train.augment import ROBUST, AugmentConfig, Augmenter
from overlapmamba.train.errors import ConfigError

PROFILE = get_profile("kitti-hdl64")
EMPTY = np.float32(PROFILE.empty_value)
OFF = AugmentConfig.none()


def images(n: int = 3, seed: int = 0) -> np.ndarray:
    """Range images with structure in both directions and a few empty pixels."""
    rng = np.random.default_rng(seed)
    rows = np.linspace(5, 60, PROFILE.height)[:, None]
    cols = 10 * np.sin(np.linspace(0, 6 * np.pi, PROFILE.width))[None, :]
    x = np.repeat((rows + cols + 20)[None], n, axis=0).astype(np.float32)
    x[rng.random(x.shape) < 0.05] = EMPTY
    return x


def only(**kw) -> Augmenter:
    fields = {
        "tilt_deg": 0.0,
        "yaw_jitter": False,
        "yaw_roll": False,
        "dropout": 0.0,
        "range_noise": 0.0,
        "fov_crop": 0.0,
    }
    return Augmenter(AugmentConfig(**{**fields, **kw}), PROFILE, circular=True)


def test_nothing_on_is_the_identity_and_input_is_not_modified():
    x = images()
    before = x.copy()
    out = Augmenter(OFF, PROFILE, circular=True)(x, np.random.default_rng(0))
    np.testing.assert_array_equal(out, before)
    np.testing.assert_array_equal(x, before)
    assert out.dtype == np.float32 and out is not x


def test_same_seed_same_batch_and_strength_varies_per_scan():
    x = images(8)
    aug = Augmenter(AugmentConfig(**ROBUST), PROFILE, circular=True)
    a = aug(x, np.random.default_rng(7))
    b = aug(x, np.random.default_rng(7))
    np.testing.assert_array_equal(a, b)
    lost = [(a[i] == EMPTY).mean() - (x[i] == EMPTY).mean() for i in range(8)]
    assert np.ptp(lost) > 0.02  # some scans lose more returns than others


def test_tilt_shifts_columns_vertically_by_a_cosine():
    x = images(1)
    out = only(tilt_deg=3.0)(x, np.random.default_rng(1))[0]
    shifts = []
    for j in range(0, PROFILE.width, 50):
        col, src = out[:, j], x[0, :, j]
        best = min(range(-8, 9), key=lambda s: np.abs(np.roll(src, s) - col)[10:-10].sum())
        shifts.append(best)
    shifts = np.array(shifts)
    assert shifts.max() >= 1 and shifts.min() <= -1  # up on one side, down on the other
    assert np.abs(shifts).max() <= 3.0 * PROFILE.height / PROFILE.fov_deg + 1


def test_yaw_roll_only_for_non_circular_models_by_default():
    x = images(4)
    default = AugmentConfig()  # off, but for the rolls of a non-circular model
    circular = Augmenter(default, PROFILE, circular=True)(x, np.random.default_rng(0))
    np.testing.assert_array_equal(circular, x)
    open_ = Augmenter(default, PROFILE, circular=False)(x, np.random.default_rng(0))
    for a, b in zip(open_, x, strict=True):
        assert any(np.array_equal(a, np.roll(b, k, axis=-1)) for k in range(PROFILE.width))
    assert not np.array_equal(open_, x)


def test_yaw_jitter_mixes_a_column_with_its_neighbour():
    x = images(1)
    out = only(yaw_jitter=True)(x, np.random.default_rng(3))[0]
    prev = np.roll(x[0], 1, axis=-1)
    assert np.all((out == x[0]) | (out == prev))
    assert 0 < (out != x[0]).mean() < 1


def test_dropout_noise_and_crop_touch_only_what_they_should():
    x = images(6)
    valid = x != EMPTY
    out = only(dropout=0.5)(x, np.random.default_rng(0))
    assert np.all(out[~valid] == EMPTY)
    kept = (out != EMPTY) & valid
    np.testing.assert_array_equal(out[kept], x[kept])
    assert (out == EMPTY).mean() > (x == EMPTY).mean() + 0.05

    noisy = only(range_noise=0.05)(x, np.random.default_rng(0))
    assert np.all(noisy[~valid] == EMPTY) and np.all(noisy[valid] > 0)
    assert 0 < np.abs(noisy[valid] - x[valid]).max() < 0.5

    beams = only(beam_dropout=0.5)(x, np.random.default_rng(0))
    for img, src in zip(beams, x, strict=True):  # whole rows emptied, the others untouched
        gone = np.all(img == EMPTY, axis=1) & ~np.all(src == EMPTY, axis=1)
        np.testing.assert_array_equal(img[~gone], src[~gone])
    assert 0 < sum(np.all(img == EMPTY, axis=1).sum() for img in beams) < 6 * PROFILE.height / 2
    # off, it draws nothing: a run without it keeps the random stream of the runs before it
    rng_a, rng_b = np.random.default_rng(3), np.random.default_rng(3)
    only(dropout=0.2)(x, rng_a)
    only(dropout=0.2, beam_dropout=0.0)(x, rng_b)
    assert rng_a.random() == rng_b.random()

    cropped = only(fov_crop=1.0, fov_min_deg=180.0)(x, np.random.default_rng(0))
    for img in cropped:
        empty_cols = np.all(img == EMPTY, axis=0)
        assert 0 < empty_cols.sum() <= PROFILE.width // 2 + 1
        # one contiguous sector (on the ring): the empty columns change state twice
        assert np.count_nonzero(empty_cols != np.roll(empty_cols, 1)) == 2


@pytest.mark.parametrize(
    "kw",
    [
        {"dropout": 1.0},
        {"beam_dropout": 1.0},
        {"tilt_deg": -1.0},
        {"fov_crop": 2.0},
        {"fov_min_deg": 0.0},
        {"sensor_like": 1.5},
    ],
)
def test_out_of_range_settings_are_refused(kw):
    with pytest.raises(ConfigError, match="out of range; allowed"):
        AugmentConfig(**kw)


def test_wrong_image_shape_is_refused():
    with pytest.raises(ValueError, match=r"expected range images \(B, 64, 900\)"):
        only()(np.zeros((2, 32, 900), np.float32), np.random.default_rng(0))


def ring_scan(sensor, radius: float = 20.0) -> np.ndarray:
    """A sensor's scan of a cylinder of ``radius`` m around it: every beam, every firing."""
    el = np.radians(np.asarray(sensor.elevations_deg))[:, None]
    az = np.linspace(-np.pi, np.pi, sensor.columns, endpoint=False)[None, :]
    r = radius / np.cos(el) + 0.01 * np.sin(7 * az)  # structure along azimuth
    xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)])
    return np.stack([np.broadcast_to(c, r.shape).ravel() for c in xyz], axis=1).astype(np.float32)


@pytest.mark.parametrize("name", ["vlp16", "xt32", "os0-128", "hdl32"])
def test_sensor_like_fills_the_rows_the_service_fills_with_that_sensor(name):
    from overlapmamba.core.sensors.catalogue import CATALOGUE
    from overlapmamba.core.sensors.input import SensorInput
    from overlapmamba.core.views import project_views
    from overlapmamba.train.augment import SensorLook

    own = project_views(ring_scan(CATALOGUE["kitti-hdl64"]), PROFILE, 1)[0]
    served = SensorInput(PROFILE, CATALOGUE[name], "elevation").project(ring_scan(CATALOGUE[name]))[
        0
    ]
    seen = own.copy()
    SensorLook(PROFILE, CATALOGUE[name]).apply(seen, 0.0, EMPTY)
    rows_served = (served != EMPTY).any(axis=1)
    rows_seen = (seen != EMPTY).any(axis=1)
    assert (rows_seen & ~rows_served).sum() == 0  # nothing where that sensor has no beam
    assert rows_seen.sum() >= rows_served.sum() - 1  # and its rows, as the service fills them
    both = (served != EMPTY) & (seen != EMPTY)
    assert np.abs(served[both] - seen[both]).max() < 0.3  # a wall 20 m away, half a row apart


def test_sensor_like_draws_only_when_on_and_keeps_only_what_the_sensor_reaches():
    x = images(6)
    plain = only(dropout=0.3)(x, np.random.default_rng(3))
    same = only(dropout=0.3, sensor_like=0.0)(x, np.random.default_rng(3))
    np.testing.assert_array_equal(plain, same)  # off: the random stream is untouched
    out = only(sensor_like=1.0, sensor_like_names=("vlp16",))(x, np.random.default_rng(3))
    assert ((out == EMPTY).all(axis=2).sum(axis=1) >= 15).all()  # VLP-16 stops at −15°
    kept = out != EMPTY
    assert kept.any() and set(np.unique(out[kept])) <= set(np.unique(x[x != EMPTY]))
    with pytest.raises(ConfigError, match="not in the catalogue; allowed: .*vlp16"):
        AugmentConfig(sensor_like=0.5, sensor_like_names=("vlp-17",))


def test_sensor_like_leaves_scans_of_other_sensors_alone_and_keeps_the_stream():
    x = images(6)
    native = np.array([True, False, True, False, False, True])
    aug = only(sensor_like=1.0, dropout=0.2)
    out = aug(x, np.random.default_rng(4), native)
    every = aug(x, np.random.default_rng(4))
    drop = only(dropout=0.2, sensor_like=1.0, sensor_like_names=())
    np.testing.assert_array_equal(out[native], every[native])  # the same draws for each scan
    others = drop(x, np.random.default_rng(4), np.zeros(6, bool))
    np.testing.assert_array_equal(out[~native], others[~native])  # dropout alone on the rest
    assert not np.array_equal(out[~native], every[~native])
    with pytest.raises(ValueError, match=r"native: one flag a scan \(6\)"):
        aug(x, np.random.default_rng(4), np.ones(5, bool))


def test_seen_as_other_gives_each_scan_one_other_sensors_look_and_nothing_else():
    from overlapmamba.core.sensors.catalogue import CATALOGUE
    from overlapmamba.train.augment import SensorLook

    x = images(5)
    aug = only(dropout=0.3)  # the sensor term needs no sensor_like, and ignores the rest
    out = aug.seen_as_other(x, np.random.default_rng(6))
    np.testing.assert_array_equal(out, aug.seen_as_other(x, np.random.default_rng(6)))
    assert not np.shares_memory(out, x) and not np.array_equal(out, x)
    others = [SensorLook(PROFILE, s) for s in CATALOGUE.values() if s.profile() != PROFILE]
    for got, img in zip(out, x, strict=True):  # each is exactly one sensor's look at a phase
        looks = []
        for look in others:
            for phase in np.linspace(0, 1, 41)[:-1]:
                seen = img.copy()
                look.apply(seen, phase, EMPTY)
                looks.append(np.array_equal(seen, got))
        assert any(looks)
    one = only(sensor_like_names=("vlp16",)).seen_as_other(x, np.random.default_rng(0))
    assert ((one == EMPTY).all(axis=2).sum(axis=1) >= 15).all()  # VLP-16 stops at −15°
    with pytest.raises(ValueError, match=r"expected range images \(K, 64, 900\)"):
        aug.seen_as_other(x[0], np.random.default_rng(0))
    with pytest.raises(ValueError, match="no other sensor"):
        only(sensor_like_names=("kitti-hdl64",)).seen_as_other(x, np.random.default_rng(0))


def test_far_loss_takes_far_returns_first_and_draws_only_when_on():
    x = np.repeat(np.linspace(1, 79, PROFILE.width, dtype=np.float32)[None, None], 64, axis=1)
    x = np.repeat(x, 8, axis=0)  # range grows along each row
    same = only(dropout=0.1, far_loss=0.0)(x, np.random.default_rng(5))
    np.testing.assert_array_equal(same, only(dropout=0.1)(x, np.random.default_rng(5)))
    out = only(far_loss=0.9)(x, np.random.default_rng(5))
    lost = out == EMPTY
    assert lost[..., 600:].mean() > 3 * lost[..., :300].mean() > 0
    assert lost.mean() < 0.45 and np.array_equal(out[~lost], x[~lost])


def test_range_cut_empties_every_return_beyond_one_drawn_range_and_draws_only_when_on():
    x = np.repeat(np.linspace(1, 79, PROFILE.width, dtype=np.float32)[None, None], 64, axis=1)
    x = np.repeat(x, 16, axis=0)  # range grows along each row
    same = only(dropout=0.1, range_cut=0.0)(x, np.random.default_rng(5))
    np.testing.assert_array_equal(same, only(dropout=0.1)(x, np.random.default_rng(5)))
    out = only(range_cut=1.0, range_cut_min_m=30.0)(x, np.random.default_rng(5))
    cuts = []
    for got, img in zip(out, x, strict=True):
        lost = got == EMPTY
        assert np.array_equal(got[~lost], img[~lost])  # what is kept is untouched
        if not lost.any():  # drawn beyond the farthest return (79 m)
            continue
        cut = img[lost].min()  # one range a scan: everything from it on is gone, nothing before
        assert 30.0 <= cut <= PROFILE.max_range and (lost == (img >= cut)).all()
        cuts.append(cut)
    assert len(set(cuts)) > 8  # drawn per scan
    half = only(range_cut=0.5)(x, np.random.default_rng(1))
    whole = [(got == img).all() for got, img in zip(half, x, strict=True)]
    assert 0 < sum(whole) < len(x)  # a share of the scans keeps everything
    with pytest.raises(ConfigError, match="range_cut=1.5 is out of range"):
        AugmentConfig(range_cut=1.5)
    with pytest.raises(ConfigError, match="range_cut_min_m=90.0 m must be below"):
        only(range_cut=0.5, range_cut_min_m=90.0)
