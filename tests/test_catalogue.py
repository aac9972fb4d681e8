"""The sensor catalogue and how a scan of any sensor becomes a model's input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from overlapmamba.core.errors import ProfileError
from overlapmamba.core.projection import project
from overlapmamba.core.sensors import CATALOGUE, get_profile, get_sensor, sensor_of_profile
from overlapmamba.core.sensors.beams import beam_of, row_beams
from overlapmamba.core.sensors.input import SensorInput, check_mode, project_input_reference
from overlapmamba.core.views import project_views

KITTI = get_profile("kitti-hdl64")
REQUIRED = {"vlp16", "vlp32c", "hdl32", "kitti-hdl64", "os1-64", "os1-128", "os0-128"}
REQUIRED |= {"os2-128", "xt32"}


def test_the_catalogue_holds_every_sensor_the_fleets_carry_with_its_source():
    assert set(CATALOGUE) >= REQUIRED
    for s in CATALOGUE.values():
        el = np.asarray(s.elevations_deg)
        assert (np.diff(el) < 0).all() and s.beams == len(el)
        assert s.source and s.columns > 0 and s.max_range > s.min_range
        assert get_sensor(s.name) is s and get_profile(s.name) == s.profile()
    beams = {n: CATALOGUE[n].beams for n in REQUIRED}
    assert beams == {
        "vlp16": 16,
        "vlp32c": 32,
        "hdl32": 32,
        "kitti-hdl64": 64,
        "os1-64": 64,
        "os1-128": 128,
        "os0-128": 128,
        "os2-128": 128,
        "xt32": 32,
    }


def test_non_uniform_sensors_keep_their_tables():
    gaps = lambda name: -np.diff(CATALOGUE[name].elevations_deg)  # noqa: E731
    # VLP-32C: dense near the horizon (a third of a degree), sparse at the edges.
    assert gaps("vlp32c").min() == pytest.approx(1 / 3, abs=0.01) and gaps("vlp32c").max() > 4
    el = CATALOGUE["vlp32c"].elevations_deg
    assert (el[0], el[-1]) == (15.0, -25.0)
    # HDL-64E: an upper block a third of a degree apart and a lower block half a degree.
    g = gaps("hdl64e")
    assert np.allclose(g[:31], 1 / 3, atol=1e-3) and np.allclose(g[32:], 0.5, atol=1e-3)
    # Uniform ones are uniform: VLP-16 2°, XT32 1°.
    assert np.allclose(gaps("vlp16"), 2.0) and np.allclose(gaps("xt32"), 1.0)


def test_profiles_the_models_know_are_unchanged():
    assert CATALOGUE["kitti-hdl64"].profile() == KITTI
    assert CATALOGUE["hdl32"].profile() == get_profile("hdl32")
    vlp = CATALOGUE["vlp16"].profile()
    assert (vlp.height, vlp.fov_up_deg, vlp.fov_down_deg) == (16, 16.0, -16.0)
    assert CATALOGUE["os0-128"].profile().max_range == 50.0  # its own range, under 80 m


def test_unknown_sensors_are_named_with_the_allowed_ones():
    with pytest.raises(ProfileError, match="unknown sensor 'mid360'; allowed: hdl32, hdl64e"):
        get_sensor("mid360")
    with pytest.raises(ProfileError, match="allowed:.*vlp16"):
        get_profile("velodyne-vlp16")


def test_a_user_defined_sensor_from_toml(tmp_path):
    f = tmp_path / "low.toml"
    f.write_text('[sensor]\nbase = "vlp16"\nname = "vlp16-30m"\nmax_range = 30.0\n')
    s = get_sensor(str(f))
    assert (s.name, s.max_range, s.beams) == ("vlp16-30m", 30.0, 16)
    f.write_text(
        'name = "two"\ntitle = "two beams"\nsource = "mine"\nelevations_deg = [1.0, -1.0]\n'
        "columns = 100\nmin_range = 0.5\nmax_range = 20.0\nrange_sigma = 0.01\n"
    )
    assert get_sensor(f).profile().height == 2
    f.write_text('name = "bad"\nelevations_deg = [-1.0, 1.0]\n')
    with pytest.raises(ProfileError, match="low.toml"):
        get_sensor(f)
    f.write_text('base = "nope"\n')
    with pytest.raises(ProfileError, match="base 'nope' is not in the catalogue"):
        get_sensor(f)
    # a dome (beams up to +90°, down to −90°): its own image ends at ±90°, so the service
    # can list it and project its scans (it was accepted, then every use was a 500)
    dome = [round(90 - 180 * k / 63, 3) for k in range(64)]
    f.write_text(f'base = "os1-64"\nname = "dome"\nelevations_deg = {dome}\n')
    p = get_sensor(f).profile()
    assert (p.fov_up_deg, p.fov_down_deg, p.height) == (90.0, -90.0, 64)
    f.write_text('base = "os1-64"\nname = "far"\nmin_range = 85.0\nmax_range = 200.0\n')
    with pytest.raises(ProfileError, match="min_range .85.0. must be below 80 m"):
        get_sensor(f)
    # a key beside a [sensor] table would be dropped: named instead
    f.write_text('max_rnge = 1\n[sensor]\nbase = "os1-64"\nname = "x"\n')
    with pytest.raises(ProfileError, match=r"keys \['max_rnge'\] lie outside its \[sensor\]"):
        get_sensor(f)


def test_a_profile_with_more_rows_than_a_sensor_has_beams_is_named():
    tall = get_profile("kitti-hdl64").replace(height=300)
    with pytest.raises(ProfileError, match="300 rows.*at most 256"):
        sensor_of_profile(tall)


def test_profile_files_name_their_base_beside_them_and_never_in_a_loop(tmp_path):
    (tmp_path / "rel").mkdir()
    (tmp_path / "rel" / "parent.toml").write_text('base = "kitti-hdl64"\nwidth = 1024\n')
    (tmp_path / "rel" / "child.toml").write_text('base = "parent.toml"\nmax_range = 40.0\n')
    p = get_profile(str(tmp_path / "rel" / "child.toml"))  # from any working folder
    assert (p.width, p.max_range) == (1024, 40.0)
    (tmp_path / "a.toml").write_text('base = "b.toml"\n')
    (tmp_path / "b.toml").write_text('base = "a.toml"\n')
    with pytest.raises(ProfileError, match="in a loop: .*a.toml → .*b.toml → .*a.toml"):
        get_profile(str(tmp_path / "a.toml"))
    (tmp_path / "self.toml").write_text('base = "self.toml"\n')
    with pytest.raises(ProfileError, match="in a loop"):
        get_profile(str(tmp_path / "self.toml"))
    (tmp_path / "bad.toml").write_text('base = "kitti-hdl64"\nfoo = 1\n')
    with pytest.raises(ProfileError, match="bad.toml"):
        get_profile(str(tmp_path / "bad.toml"))


def test_a_model_profile_has_a_sensor():
    assert sensor_of_profile(KITTI) is CATALOGUE["kitti-hdl64"]
    custom = KITTI.replace(name="kitti-50m", max_range=50.0)
    s = sensor_of_profile(custom)
    assert s.profile() == custom and s.beams == 64
    assert SensorInput(custom, s, "elevation").native


# ---- input projection ------------------------------------------------------------------------
def _cloud(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    az = rng.uniform(-np.pi, np.pi, n)
    el = np.radians(rng.uniform(-40, 40, n))
    r = rng.uniform(1, 90, n)
    return np.column_stack(
        [r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)]
    )


def test_the_models_own_sensor_is_projected_natively():
    xyz = _cloud(5000, 0)
    own = SensorInput(KITTI, CATALOGUE["kitti-hdl64"], "elevation")
    assert own.kind == "native" and own.key() == {}
    np.testing.assert_array_equal(own.project(xyz, views=3), project_views(xyz, KITTI, 3))
    np.testing.assert_array_equal(own.project(xyz)[0], project(xyz, KITTI))


@pytest.mark.parametrize("name", ["vlp16", "vlp32c", "os0-128", "xt32", "hdl32"])
@pytest.mark.parametrize("mode", ["elevation", "rows"])
def test_fast_projection_matches_the_reference(name, mode):
    xyz = _cloud(3000, 1)
    inp = SensorInput(KITTI, CATALOGUE[name], mode)
    np.testing.assert_array_equal(
        inp.project(xyz)[0], project_input_reference(xyz, KITTI, CATALOGUE[name], mode)
    )


def test_elevation_rows_keep_their_elevation_and_empty_rows_stay_empty():
    vlp = CATALOGUE["vlp16"]
    rows = row_beams(KITTI, vlp, "elevation")
    pitch = 28 / 64
    centre = 3.0 - (np.arange(64) + 0.5) * pitch
    shown = rows >= 0
    # every row shows a beam within a beam's half gap (1°) of its own elevation …
    assert np.abs(centre[shown] - np.asarray(vlp.elevations_deg)[rows[shown]]).max() <= 1.0 + 1e-9
    # … and the rows below the VLP-16's lowest beam (−15°, reach −16°) show nothing
    assert not shown[centre < -16.0].any() and shown[centre > -15.5].all()
    # rows stretch every beam over the image instead
    stretched = row_beams(KITTI, vlp, "rows")
    assert (stretched >= 0).all() and set(stretched) == set(range(16))
    assert (np.diff(stretched) >= 0).all() and np.bincount(stretched).tolist() == [4] * 16
    # HDL-32E into an HDL-64 model by rows: each row twice, as eval-real always did
    assert row_beams(KITTI, CATALOGUE["hdl32"], "rows").tolist() == np.repeat(range(32), 2).tolist()


def test_a_point_lands_on_the_rows_of_its_beam():
    vlp = CATALOGUE["vlp16"]
    inp = SensorInput(KITTI, vlp, "elevation")
    el = np.radians(-7.0)  # the VLP-16's −7° beam
    xyz = np.array([[10 * np.cos(el), 0.0, 10 * np.sin(el)]])
    img = inp.project(xyz)[0]
    hit_rows = np.flatnonzero((img > 0).any(1))
    want = np.flatnonzero(
        row_beams(KITTI, vlp, "elevation") == list(vlp.elevations_deg).index(-7.0)
    )
    assert hit_rows.tolist() == want.tolist() and len(want) >= 4
    assert np.allclose(img[hit_rows].max(1), 10.0, atol=1e-4)


@settings(max_examples=40, deadline=None)
@given(st.floats(-89, 89), st.sampled_from(sorted(CATALOGUE)))
def test_beam_of_is_the_nearest_beam(elevation, name):
    s = CATALOGUE[name]
    b = beam_of(np.array([elevation]), s)[0]
    gaps = np.abs(np.asarray(s.elevations_deg) - elevation)
    assert gaps[b] <= gaps.min() + 1e-9


def test_views_shift_the_sensor_input_like_the_native_one():
    xyz = _cloud(4000, 2)
    inp = SensorInput(KITTI, CATALOGUE["os1-64"], "elevation")
    v = inp.project(xyz, views=3)
    assert v.shape == (3, 64, 900)
    # view j: the sensor turned by j/3 of a column, its points by −j/3 (overlapmamba.core.views)
    theta = -np.radians(360 / 900 / 3)
    c, s = np.cos(theta), np.sin(theta)
    turned = xyz @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T
    same = np.isclose(inp.project(turned)[0], v[1], atol=1e-3)  # ranges differ in the last bit
    assert same.mean() > 0.999  # and a point may cross a column border by rounding


def test_modes_are_checked():
    assert check_mode("rows") == "rows"
    with pytest.raises(ValueError, match="allowed: elevation, elevation-lerp, elevation-fill"):
        check_mode("stretch")


def test_the_sensors_command_lists_the_catalogue(monkeypatch):
    import json

    from typer.testing import CliRunner

    from overlapmamba.cli import app, common

    # (the console took its width when first imported, in whichever test that was)
    monkeypatch.setattr(common.out, "width", 200)
    res = CliRunner().invoke(app, ["sensors"])
    assert res.exit_code == 0, res.output
    assert "vlp32c" in res.output and "+15.00° … -25.00°" in res.output
    res = CliRunner().invoke(app, ["sensors", "--json"])
    listed = json.loads(res.output)
    assert (
        listed["os0-128"]["elevations_deg"][0] == 45.0 and "Ouster" in listed["os0-128"]["source"]
    )


def test_the_input_mode_is_part_of_the_model_id():
    from overlapmamba.core.modelmeta import identity

    plain = identity("om-abc", 1)
    assert plain == {
        "views": 1,
        "sensor_input": "elevation",
        "column_phase": "sensor",
        "model_id": "om-abc",
        "graph_id": "",
    }
    rows = identity("om-abc", 1, "rows")
    assert rows["model_id"] != "om-abc" and rows["graph_id"] == "om-abc"
    assert identity("om-abc", 3)["model_id"] != identity("om-abc", 3, "rows")["model_id"]
    from overlapmamba.core.sensors.catalogue import catalogue_name

    assert catalogue_name("vlp16") == "vlp16"
    with pytest.raises(ProfileError, match="allowed: hdl32"):
        catalogue_name("sensors/mine.toml")  # files are for the service's [sensors] files
