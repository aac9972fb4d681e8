"""The ``bev`` sensor input: a polar bird's-eye occupancy of every scan (rings of range ×
height bands above the reference ground in the rows, the model's azimuth columns), the
model's own sensor's scans too; in the core, the service's encoder and training. And
``bev-soft``: the same cells, each return shared between its two nearest columns."""

from __future__ import annotations

import numpy as np
import pytest
from service_kit import scan
from test_catalogue import _cloud

from overlapmamba.core.points import PointCloud
from overlapmamba.core.sensors import CATALOGUE, SensorProfile, get_profile
from overlapmamba.core.sensors.bev import (
    BEV_BANDS,
    BEV_MODES,
    BEV_RINGS,
    bev_cells,
    cells_reference,
    project_bev_offset,
    project_bev_reference,
)
from overlapmamba.core.sensors.catalogue import COMMON_MAX_RANGE
from overlapmamba.core.sensors.input import SensorInput
from overlapmamba.core.sensors.mount import REFERENCE_HEIGHT, Mount

KITTI = get_profile("kitti-hdl64")
NB = len(BEV_BANDS) - 1


def _wall(sensor: str, r: float, az_deg: float, height: float = REFERENCE_HEIGHT) -> np.ndarray:
    """The returns of every beam of ``sensor``, ``height`` above the ground, off a wall
    ``r`` metres away square to azimuth ``az_deg`` (a strip ±2° wide), up to 4 m high."""
    el = np.radians(np.asarray(CATALOGUE[sensor].elevations_deg))
    az = np.radians(az_deg + np.linspace(-2.0, 2.0, 41))
    e, a = np.meshgrid(el, az)
    z = r * np.tan(e)
    keep = (z + height >= 0) & (z + height <= 4.0)
    pts = np.stack([r * np.cos(a), r * np.sin(a), z], -1)[keep]
    return pts.reshape(-1, 3)


def _cells(image: np.ndarray) -> set[tuple[int, int]]:
    return {(int(r), int(c)) for r, c in zip(*np.nonzero(image > 0), strict=True)}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fast_bev_projection_matches_the_reference(seed):
    xyz = _cloud(4000, seed)
    xyz[:, 2] = np.random.default_rng(seed).uniform(-2.0, 2.5, len(xyz))  # every band, and out
    got = SensorInput(KITTI, CATALOGUE["vlp16"], "bev").project(xyz)[0]
    np.testing.assert_array_equal(got, project_bev_reference(xyz, KITTI))
    assert set(np.unique(got)) == {KITTI.empty_value, 1.0}
    assert (got[BEV_RINGS * NB :] == KITTI.empty_value).all()  # rows past the layout stay empty


@pytest.mark.parametrize("seed", [0, 1])
def test_fast_span_projection_matches_the_reference(seed):
    xyz = _cloud(3000, seed)
    xyz[:, 2] = np.random.default_rng(seed).uniform(-2.0, 2.5, len(xyz))
    xyz[:5, :2] = [[20.0, -0.01], [20.0, 0.01], [-20.0, 0.02], [-20.0, -0.02], [-20.0, 0.0]]
    got = SensorInput(KITTI, CATALOGUE["os1-128"], "bev-span").project(xyz)[0]
    np.testing.assert_allclose(got, project_bev_reference(xyz, KITTI, "bev-span"), atol=1e-6)
    hard = project_bev_reference(xyz, KITTI)
    assert ((hard > 0) <= (got > KITTI.empty_value)).all() and got.max() == 1.0


def test_every_sub_column_view_of_spans_matches_the_slow_cover():
    """Each view j of ``bev-span`` covers what the returns moved j/views of a column on cover,
    span by span (the fast cover keeps the longest piece reaching into a column from each
    side): returns on column edges, on the seam and stacked in one cell included."""
    rng = np.random.default_rng(5)
    W = KITTI.width
    u = np.concatenate(
        [
            rng.uniform(0.0, W, 2000),
            [0.0, 0.5, 1.0, W - 0.5, W - 1e-4, 7.25, 7.25, 7.75, 8.0, 8.5],
        ]
    ).astype(np.float32)
    row = rng.integers(0, 3, len(u))
    got = bev_cells(u, row, KITTI, 3, "bev-span")
    for j in range(3):
        # the slow cover takes float32 columns: near 900 they step by 6e-5
        moved = np.mod(u.astype(np.float64) + j / 3, W).astype(np.float32)
        want = cells_reference(moved, row, KITTI, "bev-span")
        np.testing.assert_allclose(got[j], want, atol=1.5e-4)
        assert ((got[j] > KITTI.empty_value) == (want > KITTI.empty_value)).all()


def _strip(step_deg: float, r: float = 20.0, z: float = 0.0) -> np.ndarray:
    """Returns off a wall ``r`` m away, one every ``step_deg`` of azimuth over 10°–14°."""
    az = np.radians(np.arange(10.0, 14.0, step_deg))
    return np.stack([r * np.cos(az), r * np.sin(az), np.full(len(az), z)], -1)


def test_a_span_reads_a_surface_whole_however_densely_it_is_sampled():
    """A wall sampled every 0.05° and every 0.3° (under the 0.4° column): bev-span fills the
    same cells, whole (1) but where the returns end; bev-soft's cells read lower where fewer
    returns fall in them."""
    span, soft = (SensorInput.own(KITTI, m) for m in ("bev-span", "bev-soft"))
    dense, sparse = _strip(0.05), _strip(0.3)
    a, b = span.project(dense)[0], span.project(sparse)[0]
    filled = _cells(a + 1.0)
    assert filled == _cells(b + 1.0)
    inner = sorted(c for _, c in filled)[2:-2]
    row = next(iter(filled))[0]
    assert (a[row, inner] == 1.0).all() and (b[row, inner] == 1.0).all()
    s_dense, s_sparse = soft.project(dense)[0], soft.project(sparse)[0]
    assert s_sparse[row, inner].mean() < s_dense[row, inner].mean() - 0.1


@pytest.mark.parametrize("seed", [0, 1])
def test_fast_soft_projection_matches_the_reference(seed):
    xyz = _cloud(3000, seed)
    xyz[:, 2] = np.random.default_rng(seed).uniform(-2.0, 2.5, len(xyz))
    got = SensorInput(KITTI, CATALOGUE["os1-128"], "bev-soft").project(xyz)[0]
    np.testing.assert_array_equal(got, project_bev_reference(xyz, KITTI, "bev-soft"))
    hard = project_bev_reference(xyz, KITTI)
    # every occupied bev cell is occupied here too, with the neighbours its returns share
    assert ((hard > 0) <= (got > KITTI.empty_value)).all()
    assert (got > KITTI.empty_value).sum() > (hard > 0).sum()
    assert got.max() <= 1.0 and ((got > KITTI.empty_value) & (got < 1.0)).any()


def _turned(xyz: np.ndarray, columns: float) -> np.ndarray:
    theta = -2 * np.pi * columns / KITTI.width  # the columns grow clockwise
    c, s = np.cos(theta), np.sin(theta)
    return xyz @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T


@pytest.mark.parametrize("mode", ["bev-soft", "bev-span"])
def test_a_soft_image_moves_with_a_turn_where_a_bev_image_jumps(mode):
    """A turn by a tenth of a column changes no bev-soft or bev-span cell by more than a
    tenth of the cell range (so the network sees a small change for a small turn), while bev
    cells flip whole; a turn by whole columns rolls them as it rolls the bev one."""
    xyz = _cloud(3000, 7)
    xyz[:, 2] = np.random.default_rng(7).uniform(-1.4, 1.2, len(xyz))
    full = np.float32(1.0 - KITTI.empty_value)
    soft, bev = (SensorInput.own(KITTI, m) for m in (mode, "bev"))
    a, b = soft.project(xyz)[0], soft.project(_turned(xyz, 0.1))[0]
    assert np.abs(a - b).max() <= 0.1 * full + 1e-3 and np.abs(a - b).max() > 0.05 * full
    jumps = np.abs(bev.project(xyz)[0] - bev.project(_turned(xyz, 0.1))[0]).max()
    assert jumps == full
    rolled = soft.project(_turned(xyz, 37))[0]
    np.testing.assert_allclose(np.roll(a, 37, axis=1), rolled, atol=1e-3)


def test_a_wall_fills_the_same_cells_whichever_sensor_sees_it():
    """A wall 20 m away is hit by 2 of a VLP-16's beams in each band and by many of an
    HDL-64E's: a range image puts them on different rows, the bev input in the same cells.
    Its cells are the ring of 20 m in every band the wall reaches, over the columns it spans."""
    images = {
        s: SensorInput(KITTI, CATALOGUE[s], "bev").project(_wall(s, 20.0, 30.0))[0]
        for s in ("kitti-hdl64", "vlp16", "xt32", "os1-128", "os0-128")
    }
    ring = int(20.0 * BEV_RINGS / COMMON_MAX_RANGE)
    rows = {r for r, _ in _cells(images["kitti-hdl64"])}
    assert rows == {ring * NB + b for b in range(NB)}
    for s, image in images.items():
        assert _cells(image) == _cells(images["kitti-hdl64"]), s
    # the range images of the same walls do not agree
    elev = {
        s: SensorInput(KITTI, CATALOGUE[s], "elevation").project(_wall(s, 20.0, 30.0))[0]
        for s in ("kitti-hdl64", "vlp16")
    }
    assert _cells(elev["kitti-hdl64"]) != _cells(elev["vlp16"])


def test_ground_far_returns_and_what_stands_above_the_top_band_are_left_out():
    inp = SensorInput(KITTI, CATALOGUE["os0-128"], "bev")
    road = np.array([[8.0, 0.0, -REFERENCE_HEIGHT + 0.05]])  # 5 cm above the road: ground
    low = np.array([[8.0, 0.0, -REFERENCE_HEIGHT + BEV_BANDS[0] + 0.01]])
    roof = np.array([[8.0, 0.0, -REFERENCE_HEIGHT + BEV_BANDS[-1] + 0.01]])
    far = np.array([[COMMON_MAX_RANGE + 0.5, 0.0, 0.0]])
    assert _cells(inp.project(road)[0]) == set()
    assert _cells(inp.project(roof)[0]) == set()
    assert _cells(inp.project(far)[0]) == set()
    assert {r for r, _ in _cells(inp.project(low)[0])} == {int(8.0 * BEV_RINGS / 50.0) * NB}


def test_a_low_mount_is_levelled_onto_the_reference_ground():
    """A robot's VLP-16 half a metre up sees the same wall as the car's HDL-64E: once levelled
    and moved to the reference height, the same cells; its road 4 m ahead stays ground."""
    car = SensorInput(KITTI, CATALOGUE["kitti-hdl64"], "bev").project(_wall("kitti-hdl64", 15, 0))
    robot_in = SensorInput(KITTI, CATALOGUE["vlp16"], "bev", Mount(height=0.5))
    robot = robot_in.project(_wall("vlp16", 15.0, 0.0, height=0.5))
    # the robot's beams reach up to 0.5 m + 15 m · tan 15° ≈ 4.5 m: both bands, as the car's
    assert _cells(robot[0]) == _cells(car[0])
    road = np.array([[4.0, 0.0, -0.5]])
    assert _cells(robot_in.project(road)[0]) == set()
    assert _cells(SensorInput(KITTI, CATALOGUE["vlp16"], "bev").project(road)[0])  # unlevelled
    assert robot_in.kind == "bev+mount"


def test_the_modes_type_names_every_mode():
    from typing import get_args

    from overlapmamba.core.sensors.input import MODES, Mode

    assert get_args(Mode) == MODES and set(BEV_MODES) <= set(MODES)


def test_every_scan_goes_through_it_and_caches_apart():
    own = SensorInput.own(KITTI, "bev")
    assert not own.native and own.kind == "bev"
    key = own.key()
    assert key["bev"] == {
        "bands_m": list(BEV_BANDS),
        "rings": BEV_RINGS,
        "ground_m": REFERENCE_HEIGHT,
        "max_range_m": COMMON_MAX_RANGE,
    }
    assert key != SensorInput.own(KITTI, "structure").key()
    with pytest.raises(ValueError, match="rows are rings of range × height bands"):
        own.rows()
    small = SensorProfile.model_validate({**KITTI.model_dump(), "name": "tiny", "height": 16})
    with pytest.raises(ValueError, match="32 rings × 2 bands need more rows than profile 'tiny'"):
        SensorInput(small, CATALOGUE["vlp16"], "bev")
    with pytest.raises(ValueError, match="points must have shape"):
        own.project(np.zeros((5, 2)))
    soft = SensorInput.own(KITTI, "bev-soft")
    assert soft.kind == "bev-soft" and not soft.native
    assert soft.key()["bev"] == {**key["bev"], "cells": "soft"} and soft.key() != key
    with pytest.raises(ValueError, match="bev-soft input's rows are rings"):
        soft.rows()
    assert SensorInput.own(KITTI, "bev-span").key()["bev"] == {**key["bev"], "cells": "span"}
    assert (
        SensorInput(KITTI, CATALOGUE["vlp16"], "bev-soft", Mount(height=0.5)).kind
        == "bev-soft+mount"
    )


def test_a_turn_by_whole_columns_rolls_the_image():
    xyz = _cloud(3000, 5)
    xyz[:, 2] = np.random.default_rng(5).uniform(-1.4, 1.2, len(xyz))
    k = 37
    theta = -2 * np.pi * k / KITTI.width  # the columns grow clockwise
    c, s = np.cos(theta), np.sin(theta)
    turned = xyz @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T
    a, b = project_bev_offset(xyz, KITTI, 1)[0][0], project_bev_offset(turned, KITTI, 1)[0][0]
    same = (np.roll(a, k, axis=1) == b).mean()
    assert same > 0.999  # points on a column edge may fall either side


@pytest.mark.parametrize("mode", ["bev", "bev-soft"])
def test_a_file_taking_bev_projects_every_scan_the_service_describes(tmp_path, mode):
    from service_kit import rewritten

    from overlapmamba.service.sensors import Sensors

    enc = rewritten(tmp_path, mode)
    cloud = PointCloud(scan(3)[:, :3])
    own = Sensors(enc.meta).input("kitti-hdl64")
    assert own.kind == mode
    np.testing.assert_array_equal(enc.project(cloud), own.project(cloud, enc.views))
    values = np.unique(enc.project(cloud))
    if mode == "bev":
        assert set(values) == {KITTI.empty_value, 1.0}
    else:
        assert values.min() == KITTI.empty_value and values.max() <= 1.0 and len(values) > 100
    assert Sensors(enc.meta).input("vlp16").kind == mode


def test_training_sees_a_bev_scan_through_a_sparser_sensors_beams(tiny_seq):
    """The sensor term on the bev input: a HDL-64E scan is projected again from only its
    beams nearest a 32- or 16-beam sensor's, and lands in fewer cells, all of them the
    whole scan's; a VLP-16 has no sparser sensor in the catalogue, and is never drawn."""
    pytest.importorskip("torch")
    from overlapmamba.core.datasets import open_sequence
    from overlapmamba.core.sensors.beams import beams_near
    from overlapmamba.train.train_inputs import Images, _sparser_beams

    hdl = CATALOGUE["kitti-hdl64"]
    options = _sparser_beams("kitti-hdl64")
    assert {len(b) for b in options} <= set(range(2, 33)) and len(options) >= 2
    assert any(np.array_equal(b, beams_near(hdl, CATALOGUE["vlp16"])) for b in options)
    assert _sparser_beams("vlp16") == []
    seq = open_sequence(tiny_seq)
    images = Images([seq], KITTI, progress=False, mode="bev")
    idx = np.array([5, 9, 11])
    at, seen = images.sparser(idx, np.random.default_rng(0), 2)
    assert at.tolist() == [0, 1] and seen.shape == (2, KITTI.height, KITTI.width)
    whole = images[idx[:2]] > 0
    assert ((seen > 0) <= whole).all() and (seen > 0).sum() < whole.sum()
    again = images.sparser(idx, np.random.default_rng(0), 2)[1]
    np.testing.assert_array_equal(seen, again)  # the epoch's generator decides: resume exact
