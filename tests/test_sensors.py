from __future__ import annotations

import json

import pytest

from overlapmamba.core.errors import ProfileError
from overlapmamba.core.sensors import BUILTIN_PROFILES, SensorProfile, get_profile


def test_builtin_profiles_match_the_issue():
    k = get_profile("kitti-hdl64")
    assert (k.fov_up_deg, k.fov_down_deg, k.height, k.width, k.max_range) == (3, -25, 64, 900, 80)
    h = get_profile("hdl32")
    assert (h.fov_up_deg, h.fov_down_deg, h.height, h.width) == (10.67, -30.67, 32, 900)
    assert set(BUILTIN_PROFILES) == {"kitti-hdl64", "hdl32"}


def test_unknown_profile_names_the_allowed_ones():
    # the built-in profiles and every catalogue sensor, sorted, then the file alternative
    with pytest.raises(ProfileError, match="allowed: hdl32, hdl64e, kitti-hdl64, os0-128, ") as e:
        get_profile("velodyne-vlp16")
    assert "vlp16, vlp32c, xt32, or a path to a .json/.toml profile file" in str(e.value)


@pytest.mark.parametrize(
    "change",
    [
        {"fov_up_deg": -30.0},
        {"max_range": 0.0},
        {"min_range": 90.0},
        {"empty_value": 5.0},
        {"height": 0},
        {"empty_value": float("nan")},
    ],
)
def test_invalid_overrides_are_rejected(change):
    with pytest.raises(ProfileError):
        get_profile("kitti-hdl64").replace(**change)


def test_custom_profiles_from_json_and_toml(tmp_path):
    j = tmp_path / "os1.json"
    j.write_text(
        json.dumps(
            {
                "name": "os1-64",
                "fov_up_deg": 22.5,
                "fov_down_deg": -22.5,
                "height": 64,
                "width": 1024,
                "max_range": 120,
            }
        )
    )
    assert get_profile(j).width == 1024
    t = tmp_path / "narrow.toml"
    t.write_text('[sensor]\nbase = "kitti-hdl64"\nname = "kitti-50m"\nmax_range = 50.0\n')
    p = get_profile(str(t))
    assert (p.name, p.max_range, p.height) == ("kitti-50m", 50.0, 64)
    bad = tmp_path / "bad.json"
    bad.write_text('{"name": "x", "fov_up_deg": 1}')
    with pytest.raises(ProfileError, match="bad.json"):
        get_profile(bad)
    with pytest.raises(ProfileError, match="cannot read"):
        get_profile(tmp_path / "missing.toml")


def test_profiles_are_immutable():
    with pytest.raises(Exception):  # noqa: B017 — pydantic raises ValidationError on frozen
        get_profile("hdl32").width = 10  # type: ignore[misc]
    assert isinstance(get_profile(get_profile("hdl32")), SensorProfile)
