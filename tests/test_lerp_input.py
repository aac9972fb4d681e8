"""The ``elevation-lerp`` input: another sensor's scan made into the model's own sensor's
beams (``LerpPlan`` and ``lerp_rows`` of :mod:`overlapmamba.core.sensors.beams`)."""

from __future__ import annotations

import numpy as np
import pytest
from test_catalogue import _cloud

from overlapmamba.core.sensors import CATALOGUE, get_profile
from overlapmamba.core.sensors.beams import LerpPlan
from overlapmamba.core.sensors.input import SensorInput, check_mode
from overlapmamba.core.views import project_views

KITTI = get_profile("kitti-hdl64")
OWN = CATALOGUE["kitti-hdl64"]
H = 1.73  # m: the ground below the sensor


def _ring_scan(elevations_deg, surface, cols: int = 900) -> np.ndarray:
    """One point per beam and column centre; ``surface(el, az)`` → its range (or 0: none)."""
    az = np.pi - (np.arange(cols) + 0.5) / cols * 2 * np.pi  # the column centres
    pts = []
    for e in np.radians(np.asarray(elevations_deg)):
        r = surface(e, az)
        ok = r > 0
        pts.append(
            np.column_stack(
                [
                    r * np.cos(e) * np.cos(az),
                    r * np.cos(e) * np.sin(az),
                    r * np.sin(e) * np.ones_like(az),
                ]
            )[ok]
        )
    return np.concatenate(pts)


def _ground(e, az):
    return (H / np.sin(-e) if e < -np.radians(1.0) else 0.0) * np.ones_like(az)


def _own_rows(plan: LerpPlan) -> tuple[np.ndarray, np.ndarray]:
    """The rows that show one own beam, and that beam's elevation (a row two share shows
    the nearer return of the two)."""
    el = np.asarray(OWN.elevations_deg)
    rows, first, count = np.unique(plan.row, return_index=True, return_counts=True)
    return rows[count == 1], el[first[count == 1]]


def test_the_mode_is_known_and_the_models_own_sensor_stays_native():
    assert check_mode("elevation-lerp") == "elevation-lerp"
    xyz = _cloud(4000, 3)
    own = SensorInput(KITTI, OWN, "elevation-lerp")
    assert own.kind == "native" and own.key() == {}
    np.testing.assert_array_equal(own.project(xyz, views=3), project_views(xyz, KITTI, 3))
    other = SensorInput(KITTI, CATALOGUE["vlp16"], "elevation-lerp")
    assert other.key()["mode"] == "elevation-lerp" and other.kind == "elevation-lerp"


@pytest.mark.parametrize("name", ["vlp16", "hdl32", "xt32"])
def test_a_flat_ground_is_made_exactly_at_the_models_own_beams(name):
    """Between two of a sparse sensor's beams on a flat ground, the own beam's range is the
    ground's at the own beam's elevation (the plain ``elevation`` input repeats the nearest
    beam's range instead)."""
    sensor = CATALOGUE[name]
    xyz = _ring_scan(sensor.elevations_deg, _ground)
    lerp = SensorInput(KITTI, sensor, "elevation-lerp").project(xyz)[0]
    plain = SensorInput(KITTI, sensor, "elevation").project(xyz)[0]
    plan = LerpPlan.of(KITTI, sensor)
    rows, el = _own_rows(plan)
    seen = [e for e in sensor.elevations_deg if e < -1.0 and H / np.sin(np.radians(-e)) < 80]
    between = (el < max(seen)) & (el > min(seen))  # between two beams that meet the ground
    assert between.sum() >= 20
    truth = H / np.sin(np.radians(-el[between]))[:, None]
    err = np.abs(lerp[rows[between]] - truth) / truth
    assert err.max() < 1e-3
    assert (np.abs(plain[rows[between]] - truth) / truth).max() > 0.02


def test_a_wall_is_interpolated_and_an_edge_is_not():
    """A wall 20 m away seen by every beam: each own beam between two takes the wall's range
    at its elevation (to within the wall's own curvature). A post 5 m away in front of the
    wall's upper half: the own beams between the post's lowest beam and the wall's highest
    take one of the two ranges, never a range in the gap between them."""
    sensor = CATALOGUE["vlp16"]
    wall = _ring_scan(sensor.elevations_deg, lambda e, az: 20.0 / np.cos(e) * np.ones_like(az))
    lerp = SensorInput(KITTI, sensor, "elevation-lerp").project(wall)[0]
    plan = LerpPlan.of(KITTI, sensor)
    rows, el = _own_rows(plan)
    inside = (el < 2.0) & (el > -14.0)
    truth = 20.0 / np.cos(np.radians(el[inside]))[:, None]
    assert (np.abs(lerp[rows[inside]] - truth) / truth).max() < 0.005

    def post(e, az):
        return np.where(e > np.radians(-4.0), 5.0 / np.cos(e), 20.0 / np.cos(e)) * np.ones_like(az)

    image = _image(sensor, post)
    shown = image[rows[inside]]
    assert ((shown < 5.2) | (shown > 19.5)).all()
    assert (shown < 5.2).any() and (shown > 19.5).any()


def _image(sensor, surface, mode: str = "elevation-lerp") -> np.ndarray:
    return SensorInput(KITTI, sensor, mode).project(_ring_scan(sensor.elevations_deg, surface))[0]


def test_a_beam_without_a_return_leaves_its_nearest():
    """The sky above a ground: the own beams between the highest beam that meets the ground
    and the lowest that meets nothing keep their nearest beam (the ground's range or empty),
    none takes a range made up from one side."""
    sensor = CATALOGUE["vlp16"]
    image, plain = _image(sensor, _ground), _image(sensor, _ground, "elevation")
    plan = LerpPlan.of(KITTI, sensor)
    rows, el = _own_rows(plan)
    sky = el > -1.0
    assert (image[rows[sky]] == KITTI.empty_value).all()
    assert (plain[rows[sky]] == KITTI.empty_value).all()


def test_views_and_aligned_columns_take_the_lerp_too():
    sensor = CATALOGUE["hdl32"]
    xyz = _ring_scan(sensor.elevations_deg, _ground)
    inp = SensorInput(KITTI, sensor, "elevation-lerp")
    views = inp.project(xyz, views=3)
    assert views.shape == (3, 64, 900)
    np.testing.assert_array_equal(views[0], inp.project(xyz)[0])
    img, off = inp.project_offset(np.asarray(xyz) @ np.diag([1.0, 1.0, 1.0]), aligned=True)
    assert img.shape == (1, 64, 900) and np.isfinite(off)


@pytest.mark.anyio
async def test_a_file_taking_the_lerp_serves_other_sensors_scans_by_it(tmp_path, encoder):
    """A file rewritten to ``elevation-lerp`` (another model id) answers a VLP-16's scan with
    the lerp image's descriptor, not the shipped input's; its own sensor's stay native."""
    from service_kit import OCTET, rewritten, running, scan

    from overlapmamba.core.points import PointCloud
    from overlapmamba.service.settings import Settings

    lerp = rewritten(tmp_path, "elevation-lerp")
    s = scan(3)
    cloud = PointCloud(s[:, :3].copy())
    vlp = SensorInput(lerp.meta.profile, CATALOGUE["vlp16"], "elevation-lerp")
    want = lerp.encode(lerp.project(cloud, vlp)[None])[0][0]
    async with running(Settings(data_dir=tmp_path / "data"), lerp) as c:
        r = await c.post("/v1/descriptors?sensor=vlp16", content=s.tobytes(), headers=OCTET)
        assert r.status_code == 200, r.text
        got = np.array(r.json()["descriptor"])
        np.testing.assert_allclose(got, want, atol=1e-5)
        kinds = {x["name"]: x["projection"] for x in (await c.get("/v1/sensors")).json()["sensors"]}
        assert kinds["kitti-hdl64"] == "native" and kinds["vlp16"] == "elevation-lerp"
    async with running(Settings(data_dir=tmp_path / "shipped"), encoder) as c:
        r = await c.post("/v1/descriptors?sensor=vlp16", content=s.tobytes(), headers=OCTET)
        assert float(np.array(r.json()["descriptor"]) @ got) < 0.99999
