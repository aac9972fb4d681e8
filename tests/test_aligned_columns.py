"""Aligned columns (overlapmamba.core.views, ``column_phase = "aligned"``): a turned scan's image
is the plain one rolled by whole columns; the yaw features go back to the sensor's columns;
the model id and the refusals."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from overlapmamba.core.io import read_points
from overlapmamba.core.modelmeta import EncoderMetadata, identity
from overlapmamba.core.poses import rotation_z, transform_points
from overlapmamba.core.sensors.catalogue import CATALOGUE
from overlapmamba.core.sensors.input import SensorInput
from overlapmamba.core.views import (
    check_column_phase,
    project_views,
    project_views_offset,
    unshift_features,
)
from tests.test_projection import KITTI, SMALL, random_scan

ROOT = Path(__file__).resolve().parents[1]


def turned(xyz: np.ndarray, theta: float) -> np.ndarray:
    """The scan of a sensor turned by ``theta`` degrees: its points turn by −θ."""
    return transform_points(xyz, rotation_z(-theta))


def roll_of(theta: float, off_plain: float, off_turned: float, width: int) -> float:
    """Columns the aligned image moves when the sensor turns by θ: the turn's own share and
    the two offsets'."""
    return theta * width / 360.0 + off_turned - off_plain


@pytest.mark.parametrize("views", [1, 2])
def test_an_aligned_scan_turned_by_any_angle_is_its_image_rolled_by_whole_columns(
    kitti_seq_dir, views
):
    xyz = read_points(kitti_seq_dir / "velodyne" / "000010.bin").xyz
    plain, off = project_views_offset(xyz, KITTI, views, aligned=True)
    assert -0.5 < off <= 0.5
    for theta in np.random.default_rng(3).uniform(-180, 180, 4):
        img, off_t = project_views_offset(turned(xyz, theta), KITTI, views, aligned=True)
        shift = roll_of(theta, off, off_t, KITTI.width)
        assert abs(shift - round(shift)) < 1e-3, (theta, shift)  # whole columns
        # up to points on a column edge (float rounding of the turned coordinates)
        assert np.isclose(img, np.roll(plain, round(shift), axis=-1), atol=1e-3).mean() > 0.999
        # the sensor's own columns do not: a continuous turn re-bins the points
        raw = project_views(turned(xyz, theta), KITTI, views)
        sensor = project_views(xyz, KITTI, views)
        best = max(
            np.isclose(raw, np.roll(sensor, k, axis=-1), atol=1e-3).mean()
            for k in (
                int(np.floor(theta * KITTI.width / 360)),
                int(np.ceil(theta * KITTI.width / 360)),
            )
        )
        assert best < 0.99
    # without aligned, the offset is 0 and the images are project_views'
    same, zero = project_views_offset(xyz, KITTI, views)
    assert zero == 0.0
    np.testing.assert_array_equal(same, project_views(xyz, KITTI, views))


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 300), st.floats(-180, 180))
def test_the_offset_is_within_half_a_column_and_follows_the_turn(seed, n, theta):
    pts = random_scan(np.random.default_rng(seed), n)
    img, off = project_views_offset(pts, SMALL, 1, aligned=True)
    assert img.shape == (1, SMALL.height, SMALL.width) and -0.5 < off <= 0.5
    empty = bool((img == np.float32(SMALL.empty_value)).all())
    if n == 0 or empty:  # no point, or none in the field of view: nothing to align
        assert off == 0.0 and empty
        return
    _, off_t = project_views_offset(turned(pts, theta), SMALL, 1, aligned=True)
    shift = roll_of(theta, off, off_t, SMALL.width)
    # whole columns, unless the mean bearing is all but undefined (points all around evenly)
    assert min(abs(shift - round(shift)), 1 - abs(shift - round(shift))) < 1e-3 or n < 3


def test_another_sensor_aligned_rolls_by_whole_columns(kitti_seq_dir):
    xyz = read_points(kitti_seq_dir / "velodyne" / "000020.bin").xyz
    vlp = SensorInput(KITTI, CATALOGUE["vlp16"], "elevation")
    plain, off = vlp.project_offset(xyz, aligned=True)
    theta = 123.456
    img, off_t = vlp.project_offset(turned(xyz, theta), aligned=True)
    shift = roll_of(theta, off, off_t, KITTI.width)
    assert abs(shift - round(shift)) < 1e-3
    assert np.isclose(img, np.roll(plain, round(shift), axis=-1), atol=1e-3).mean() > 0.999
    np.testing.assert_array_equal(vlp.project(xyz, aligned=True), plain)


@pytest.mark.parametrize("mode", ["bev", "bev-soft", "bev-span"])
def test_a_bev_scan_aligned_turned_by_any_angle_is_its_image_rolled_by_whole_columns(
    kitti_seq_dir, mode
):
    """The bird's-eye inputs' columns are the returns' azimuths; aligned, they start at the
    mean bearing of the returns the input keeps, so a turn rolls the image by whole columns,
    where in the sensor's columns a continuous turn changes the cells."""
    xyz = read_points(kitti_seq_dir / "velodyne" / "000030.bin").xyz
    bev = SensorInput(KITTI, CATALOGUE["vlp16"], mode)  # type: ignore[arg-type]
    plain, off = bev.project_offset(xyz, aligned=True)
    assert -0.5 < off <= 0.5 and off != 0.0
    np.testing.assert_array_equal(bev.project(xyz, aligned=True), plain)
    sensor, zero = bev.project_offset(xyz)
    assert zero == 0.0 and not np.array_equal(sensor, plain)
    for theta in np.random.default_rng(5).uniform(-180, 180, 3):
        img, off_t = bev.project_offset(turned(xyz, theta), aligned=True)
        shift = roll_of(theta, off, off_t, KITTI.width)
        assert abs(shift - round(shift)) < 1e-3, (theta, shift)
        rolled = np.roll(plain, round(shift), axis=-1)
        assert np.isclose(img, rolled, atol=1e-3).mean() > 0.999
        if mode != "bev":  # occupancy changes only where a return crosses a column edge
            raw = bev.project(turned(xyz, theta))
            whole = round(theta * KITTI.width / 360)
            assert np.isclose(raw, np.roll(sensor, whole, axis=-1), atol=1e-3).mean() < 0.999


def test_unshifting_the_yaw_features_is_a_circular_shift_back():
    rng = np.random.default_rng(0)
    f = rng.normal(size=(3, 4, 30)).astype(np.float32)
    # whole columns: a roll; columns m of an image at offset k show the sensor's m − k
    np.testing.assert_allclose(unshift_features(f, 3.0), np.roll(f, -3, axis=-1), atol=1e-5)
    per_scan = unshift_features(f, np.array([1.0, -2.0, 0.0]))
    for i, k in enumerate((1, -2, 0)):
        np.testing.assert_allclose(per_scan[i], np.roll(f[i], -k, axis=-1), atol=1e-5)
    # a fraction and back again (band-limited maps: an even width's Nyquist bin turned by a
    # fraction has no real sequence; an odd width has no such bin)
    odd = rng.normal(size=(2, 4, 31)).astype(np.float32)
    back = unshift_features(unshift_features(odd, 0.37), -0.37)
    np.testing.assert_allclose(back, odd, atol=1e-4)
    one = unshift_features(f[0], 0.25)
    assert one.shape == f[0].shape and one.dtype == np.float32


def test_the_phase_names_the_model():
    assert identity("om-abc", 1)["model_id"] == "om-abc"  # the sensor's columns: ids as before
    assert identity("om-abc", 1, column_phase="sensor")["column_phase"] == "sensor"
    aligned = identity("om-abc", 1, column_phase="aligned")
    assert aligned["model_id"] not in ("om-abc", identity("om-abc", 2)["model_id"])
    assert aligned["graph_id"] == "om-abc" and aligned["column_phase"] == "aligned"
    assert identity("om-abc", 3, column_phase="aligned")["model_id"] != aligned["model_id"]
    for bad in ("Aligned", "", "both"):
        with pytest.raises(ValueError, match="sensor, aligned"):
            check_column_phase(bad)
        with pytest.raises(ValueError, match="sensor, aligned"):
            identity("om-abc", 1, column_phase=bad)


def test_metadata_takes_aligned_for_every_input_and_refuses_unknown_phases():
    from overlapmamba.train.modelfile import read_metadata

    fields = read_metadata(ROOT / "models" / "overlapmamba-hdl64.onnx").model_dump(by_alias=True)
    assert EncoderMetadata.model_validate({**fields, "column_phase": "aligned"}).aligned
    bev = {**fields, "column_phase": "aligned", "sensor_input": "bev-span"}
    assert EncoderMetadata.model_validate(bev).aligned
    with pytest.raises(ValueError, match="sensor, aligned"):
        EncoderMetadata.model_validate({**fields, "column_phase": "north"})
    # a damaged token_views is a ValueError naming it (a TypeError escaped every handler)
    for bad in (None, [3], "x", 0, 2.5, True):
        net = {**fields["model_config"], "token_views": bad}
        with pytest.raises(ValueError, match="token_views is"):
            EncoderMetadata.model_validate({**fields, "model_config": net})


def test_another_phase_or_view_count_drops_the_calibration_chosen_on_the_old_descriptors(
    tmp_path,
):
    import shutil

    from overlapmamba.train.modelfile import read_metadata, with_column_phase, with_views

    src = tmp_path / "shipped.onnx"
    shutil.copy(ROOT / "models" / "overlapmamba-hdl64.onnx", src)
    shipped = read_metadata(src)
    assert shipped.calibration and shipped.column_phase == "sensor" and shipped.views == 3
    assert with_column_phase(src, "sensor").calibration == shipped.calibration  # no change
    assert with_views(src, tmp_path / "three.onnx", 3).calibration == shipped.calibration
    one = with_views(src, tmp_path / "one.onnx", 1)
    assert one.calibration == {} and one.model_id != shipped.model_id
    aligned = with_column_phase(src, "aligned")
    assert aligned.calibration == {} and aligned.model_id != shipped.model_id
    assert read_metadata(src).calibration == {}  # what the file now says


@pytest.mark.parametrize("harmonic", [1, 2, 4])
def test_every_harmonic_follows_the_turn_and_others_are_refused(harmonic):
    """benchmarks/column_phase.py compares the bearings' moments; each is turn-equivariant
    modulo whole columns."""
    from overlapmamba.core.views import scan_offset

    pts = random_scan(np.random.default_rng(7), 500).astype(np.float64)
    depth = np.linalg.norm(pts, axis=1)
    off = scan_offset(pts[:, 0], pts[:, 1], depth, KITTI.width, harmonic)
    theta = 71.13  # the sensor turned: its points turn by −θ
    t = turned(pts.astype(np.float32), theta).astype(np.float64)
    off_t = scan_offset(t[:, 0], t[:, 1], np.linalg.norm(t, axis=1), KITTI.width, harmonic)
    shift = roll_of(theta, off, off_t, KITTI.width)
    assert -0.5 < off <= 0.5 and abs(shift - round(shift)) < 1e-3
    with pytest.raises(ValueError, match="whole divisor of the 900 columns"):
        scan_offset(pts[:, 0], pts[:, 1], depth, KITTI.width, 7)


def test_the_range_cache_keeps_aligned_images_apart_with_their_offsets(
    kitti_seq_dir, tmp_path, monkeypatch
):
    """Evaluation of an aligned file reads aligned images and their offsets from the range
    cache: other files than the sensor's columns', the offsets beside them, and asking for
    the offsets alone projects them once."""
    pytest.importorskip("torch")
    from dataclasses import replace

    from overlapmamba.core.datasets import open_sequence
    from overlapmamba.train.rangecache import cache_key, range_images, range_offsets

    monkeypatch.setenv("OVERLAPMAMBA_CACHE", str(tmp_path))
    seq = open_sequence(kitti_seq_dir)
    seq = replace(seq, scan_paths=seq.scan_paths[:4], poses=seq.poses[:4])
    assert cache_key(seq, KITTI) != cache_key(seq, KITTI, aligned=True)
    offsets = range_offsets(seq, KITTI, progress=False)  # projects and caches both
    aligned = range_images(seq, KITTI, progress=False, aligned=True)
    plain = range_images(seq, KITTI, progress=False)
    for i in range(4):
        want, off = project_views_offset(seq.points(i), KITTI, 1, aligned=True)
        np.testing.assert_array_equal(aligned[i], want[0].astype(np.float16))
        assert offsets[i] == off
    assert not np.array_equal(aligned, plain)
    files = sorted(p.name for p in (tmp_path / "range_images").glob("*.npy"))
    assert len(files) == 3 and sum(f.endswith(".offsets.npy") for f in files) == 1
    # a torn offsets file is found and both are projected again
    offsets_file = next((tmp_path / "range_images").glob("*.offsets.npy"))
    offsets_file.write_bytes(b"torn")
    np.testing.assert_array_equal(range_offsets(seq, KITTI, progress=False), offsets)
