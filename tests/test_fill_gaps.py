"""The ``elevation-fill`` input: one-column gaps in another sensor's rows filled
(:mod:`overlapmamba.core.sensors.gaps`)."""

from __future__ import annotations

import numpy as np
import pytest
from test_catalogue import _cloud

from overlapmamba.core.sensors import CATALOGUE, get_profile
from overlapmamba.core.sensors.gaps import fill_gaps, gaps
from overlapmamba.core.sensors.input import SensorInput, check_mode

KITTI = get_profile("kitti-hdl64")


def _fill_reference(image: np.ndarray, empty: float) -> np.ndarray:
    """Cell by cell: an empty cell between two returns in its row (wrapping) takes the
    nearer."""
    out = image.copy()
    H, W = image.shape
    for r in range(H):
        for c in range(W):
            left, right = image[r, (c - 1) % W], image[r, (c + 1) % W]
            if image[r, c] == empty and left != empty and right != empty:
                out[r, c] = min(left, right)
    return out


@pytest.mark.parametrize("empty", [-1.0, 0.0])
def test_fill_matches_the_cell_by_cell_reference(empty):
    rng = np.random.default_rng(3)
    image = rng.uniform(1.0, 80.0, (2, 6, 40)).astype(np.float32)
    image[rng.random(image.shape) < 0.3] = empty
    got = fill_gaps(image, empty)
    for v in range(2):
        np.testing.assert_array_equal(got[v], _fill_reference(image[v], empty))
    assert got.dtype == np.float32 and (got != image).any()


def test_only_one_column_gaps_are_filled_and_rows_wrap():
    e = -1.0
    row = np.array([[5.0, e, 7.0, e, e, 9.0, 4.0, e]], np.float32)
    got = fill_gaps(row, e)[0]
    # a one-column gap takes the nearer neighbour; two empty cells stay; the last cell's
    # neighbours are 4 m (left) and 5 m (the first cell, across the wrap)
    np.testing.assert_array_equal(got, [5.0, 5.0, 7.0, e, e, 9.0, 4.0, 4.0])
    np.testing.assert_array_equal(gaps(row, e)[0], [0, 1, 0, 0, 0, 0, 0, 1])
    assert (fill_gaps(np.full((3, 8), e, np.float32), e) == e).all()  # nothing to fill from


def test_bad_images_and_empty_values_are_refused():
    with pytest.raises(ValueError, match="W >= 3"):
        gaps(np.zeros((4, 2), np.float32), -1.0)
    with pytest.raises(ValueError, match="empty_value must be 0 or negative"):
        fill_gaps(np.zeros((4, 8), np.float32), 5.0)


def test_the_mode_fills_other_sensors_and_keeps_the_models_own_native():
    assert check_mode("elevation-fill") == "elevation-fill"
    for name in ("os1-128", "vlp16"):
        xyz = _cloud(20_000, 7)
        filled = SensorInput(KITTI, CATALOGUE[name], "elevation-fill")
        plain = SensorInput(KITTI, CATALOGUE[name], "elevation")
        want = fill_gaps(plain.project(xyz, 3), KITTI.empty_value)
        np.testing.assert_array_equal(filled.project(xyz, 3), want)
        assert filled.kind == "elevation-fill" and filled.key()["mode"] == "elevation-fill"
        img, off = filled.project_offset(xyz, aligned=True)
        ref, ref_off = plain.project_offset(xyz, aligned=True)
        assert off == ref_off
        np.testing.assert_array_equal(img, fill_gaps(ref, KITTI.empty_value))
    own = SensorInput(KITTI, CATALOGUE["kitti-hdl64"], "elevation-fill")
    xyz = _cloud(20_000, 8)
    assert own.native and own.kind == "native" and own.key() == {}
    np.testing.assert_array_equal(
        own.project(xyz, 3),
        SensorInput(KITTI, CATALOGUE["kitti-hdl64"], "elevation").project(xyz, 3),
    )


def test_a_sparse_sensors_lost_returns_leave_gaps_the_fill_closes():
    """An OS1-128 fires 1,024 times a turn into 900 columns: a lost return is a hole in its
    row. A wall all around, every firing of the beam nearest the horizon, one in fifty lost."""
    sensor = CATALOGUE["os1-128"]
    rng = np.random.default_rng(0)
    az = np.pi - (np.arange(sensor.columns) + 0.5) / sensor.columns * 2 * np.pi
    az = az[rng.random(az.size) >= 0.02]
    el = np.radians(np.asarray(sensor.elevations_deg)[63])
    xyz = 10.0 * np.column_stack(
        [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.full_like(az, np.sin(el))]
    )
    plain = SensorInput(KITTI, sensor, "elevation").project(xyz)[0]
    filled = SensorInput(KITTI, sensor, "elevation-fill").project(xyz)[0]
    row = int(np.flatnonzero((plain > 0).any(axis=1))[0])
    assert (plain[row] < 0).sum() >= 5  # holes where returns were lost
    assert (filled[row] > 0).all()
    np.testing.assert_allclose(filled[row], 10.0, atol=1e-4)


def test_the_reach_mode_cuts_every_scan_at_the_common_range_and_fills_other_sensors():
    from overlapmamba.core.sensors.catalogue import COMMON_MAX_RANGE

    xyz = _cloud(20_000, 9)
    near = xyz[np.linalg.norm(xyz, axis=1) < COMMON_MAX_RANGE]
    assert 0 < len(near) < len(xyz)
    own_sensor, other = CATALOGUE["kitti-hdl64"], CATALOGUE["os1-128"]
    own = SensorInput(KITTI, own_sensor, "elevation-reach")
    assert not own.native and own.kind == "elevation-reach"
    assert own.key()["reach_m"] == COMMON_MAX_RANGE
    np.testing.assert_array_equal(  # the model's own scan: cut, its gaps not filled
        own.project(xyz, 3), SensorInput(KITTI, own_sensor, "elevation").project(near, 3)
    )
    reach = SensorInput(KITTI, other, "elevation-reach").project(xyz, 3)
    np.testing.assert_array_equal(
        reach, SensorInput(KITTI, other, "elevation-fill").project(near, 3)
    )
    assert (reach[reach > 0] < COMMON_MAX_RANGE).all()
    assert (SensorInput(KITTI, other, "elevation-fill").project(xyz, 3) >= COMMON_MAX_RANGE).any()


def test_the_fill_continuations_differ_from_their_control_only_in_the_input():
    """fill-towns-pilot and reach-towns-pilot are measured against lerp-towns-pilot-control at
    an equal budget: the same data, validation, training config and network but the input."""
    pytest.importorskip("torch")
    from overlapmamba.train.presets import get_preset

    control = get_preset("lerp-towns-pilot-control")
    for name, mode in (
        ("fill-towns-pilot", "elevation-fill"),
        ("reach-towns-pilot", "elevation-reach"),
    ):
        p = get_preset(name)
        assert (p.data, p.val, p.train) == (control.data, control.val, control.train)
        assert p.model == {**control.model, "sensor_input": mode}
        assert check_mode(p.model["sensor_input"]) == mode
    cut, fill = get_preset("cut-towns-pilot"), get_preset("fill-towns-pilot")
    assert (cut.data, cut.val, cut.model) == (fill.data, fill.val, fill.model)
    assert cut.train == {**fill.train, "augment": {"range_cut": 0.5, "range_cut_min_m": 40.0}}
    assert get_preset("reach-towns-pilot-s1").train == {**p.train, "seed": 1}
    assert get_preset("cut-towns-pilot-s1").train == {**cut.train, "seed": 1}


@pytest.mark.anyio
async def test_a_file_taking_the_fill_serves_other_sensors_scans_by_it(tmp_path, encoder):
    """A file rewritten to ``elevation-fill`` (another model id) answers an OS1-128's scan
    with the filled image's descriptor; its own sensor's scans stay native (the shipped
    file's descriptor exactly)."""
    from service_kit import OCTET, rewritten, running, scan

    from overlapmamba.core.points import PointCloud
    from overlapmamba.service.settings import Settings

    fill = rewritten(tmp_path, "elevation-fill")
    s = scan(3)
    os1 = SensorInput(fill.meta.profile, CATALOGUE["os1-128"], "elevation-fill")
    want = fill.encode(fill.project(PointCloud(s[:, :3].copy()), os1)[None])[0][0]
    async with running(Settings(data_dir=tmp_path / "data"), fill) as c:
        r = await c.post("/v1/descriptors?sensor=os1-128", content=s.tobytes(), headers=OCTET)
        assert r.status_code == 200, r.text
        np.testing.assert_allclose(np.array(r.json()["descriptor"]), want, atol=1e-5)
        r = await c.post("/v1/descriptors", content=s.tobytes(), headers=OCTET)
        own = np.array(r.json()["descriptor"])
        kinds = {x["name"]: x["projection"] for x in (await c.get("/v1/sensors")).json()["sensors"]}
        assert kinds["kitti-hdl64"] == "native" and kinds["os1-128"] == "elevation-fill"
    async with running(Settings(data_dir=tmp_path / "shipped"), encoder) as c:
        r = await c.post("/v1/descriptors", content=s.tobytes(), headers=OCTET)
        np.testing.assert_allclose(np.array(r.json()["descriptor"]), own, atol=1e-6)
        r = await c.post("/v1/descriptors?sensor=os1-128", content=s.tobytes(), headers=OCTET)
        assert float(np.array(r.json()["descriptor"]) @ want) < 0.99999


def test_cut_margin_measures_the_paired_cosine_against_the_nearest_other_place():
    """benchmarks/cut_margin.py: the same pose's cosine, an unrelated one's, the nearest
    other place's, and whether the nearest car scan is the scan's own place."""
    from conftest import benchmark_module

    margins = benchmark_module("cut_margin").margins
    car = np.eye(4)
    near = np.eye(4, dtype=bool)
    near[2, 3] = near[3, 2] = True  # frames 2 and 3: one place
    other = np.array([2, 3, 0, 1])
    unit = lambda v: np.asarray(v) / np.linalg.norm(v)  # noqa: E731
    scans = np.stack(
        [
            unit([0.9, 0.1, 0, 0]),
            unit([0.2, 0.8, 0, 0]),
            unit([0, 0, 0.1, 0.9]),
            unit([1, 0, 0, 0.1]),
        ]
    )
    got = margins(scans, car, near, other)
    cos = scans @ car.T
    assert got["paired"] == pytest.approx(np.median(np.diag(cos)))
    assert got["unrelated"] == pytest.approx(np.median(cos[[0, 1, 2, 3], other]))
    assert got["margin"] == pytest.approx(got["paired"] - got["unrelated"])
    # scan 2 finds frame 3 (its own place: a hit); scan 3 finds frame 0 (another place: a miss)
    assert got["recall@1"] == 0.75
    wrong = [cos[0, 1:].max(), max(cos[1, 0], cos[1, 2:].max()), cos[2, :2].max(), cos[3, :2].max()]
    assert got["nearest_wrong"] == pytest.approx(np.median(wrong))


def test_cut_margin_descriptors_take_each_input_as_named(kitti_seq_dir):
    """benchmarks/cut_margin.py's descriptors: the shipped file's unit descriptors of real
    KITTI scans, one a frame, by the input it names: the cut (``elevation-reach``) moves
    them, and the uncut input takes the model's own sensor natively, as ``elevation``."""
    from conftest import ROOT, benchmark_module

    from overlapmamba.core.datasets import open_sequence
    from overlapmamba.service.encoder import Encoder

    cut_margin, fill_gaps_bench = benchmark_module("cut_margin"), benchmark_module("fill_gaps")
    enc, frames = Encoder(ROOT / "models" / "overlapmamba-hdl64.onnx"), [0, 40]
    seq = open_sequence(kitti_seq_dir)
    uncut = cut_margin.descriptors(enc, seq, "elevation-fill", frames)
    cut = cut_margin.descriptors(enc, seq, "elevation-reach", frames)
    assert uncut.shape == cut.shape == (2, enc.meta.descriptor_dim)
    np.testing.assert_allclose(np.linalg.norm(uncut, axis=1), 1.0, atol=1e-5)
    plain = fill_gaps_bench.descriptors(enc, fill_gaps_bench.images(enc, seq, frames))
    np.testing.assert_allclose(uncut, plain, atol=1e-6)
    assert (np.sum(uncut * cut, axis=1) < 0.99999).all()
