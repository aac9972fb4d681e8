"""A declared mount: a scan from a lower or tilted sensor put where the model's sensor sat."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from overlapmamba.core.sensors import CATALOGUE, get_profile
from overlapmamba.core.sensors.input import SensorInput
from overlapmamba.core.sensors.mount import REFERENCE_HEIGHT, Mount, to_reference
from overlapmamba.core.views import project_views
from overlapmamba.synth.mounting import MOUNTINGS

PROFILE = get_profile("kitti-hdl64")


def street(n: int = 20000, seed: int = 0) -> np.ndarray:
    """World points around the origin, z up from the ground: walls, poles and the road."""
    rng = np.random.default_rng(seed)
    az = rng.uniform(-np.pi, np.pi, n)
    r = rng.uniform(4, 40, n)
    z = np.where(rng.random(n) < 0.3, 0.0, rng.uniform(0, 8, n))
    return np.stack([r * np.cos(az), r * np.sin(az), z], axis=1)


@pytest.mark.parametrize("name", ["robot", "amr", "backpack"])
def test_a_mounted_scan_lands_where_the_reference_sensor_sees_the_same_points(name):
    m = MOUNTINGS[name]
    tilt = m.tilt() if m.tilt() is not None else np.eye(3)
    world = street()
    seen = (world - [0, 0, m.height]) @ tilt  # sensor ← platform: the inverse rotation
    mount = Mount(height=m.height, pitch_deg=m.pitch_deg, roll_deg=m.roll_deg)
    got = to_reference(seen, mount)
    np.testing.assert_allclose(got, world - [0, 0, REFERENCE_HEIGHT], atol=2e-4)


def test_the_models_own_sensor_at_the_reference_mount_is_its_native_image():
    xyz = (street() - [0, 0, REFERENCE_HEIGHT]).astype(np.float32)
    inp = SensorInput(
        PROFILE, CATALOGUE["kitti-hdl64"], "elevation", Mount(height=REFERENCE_HEIGHT)
    )
    np.testing.assert_allclose(inp.project(xyz, 1), project_views(xyz, PROFILE, 1), atol=1e-5)
    assert inp.kind == "native+mount" and inp.key()["mount"]["height"] == REFERENCE_HEIGHT
    low = SensorInput(PROFILE, CATALOGUE["vlp16"], "elevation", Mount(height=0.7))
    assert low.kind == "elevation+mount"
    assert low.key() != SensorInput(PROFILE, CATALOGUE["vlp16"], "elevation").key()
    lifted = low.project(xyz + np.float32([0, 0, REFERENCE_HEIGHT - 0.7]))  # seen from 0.7 m
    plain = SensorInput(PROFILE, CATALOGUE["vlp16"], "elevation").project(xyz)
    np.testing.assert_allclose(lifted, plain, atol=1e-3)


def test_mounts_parse_from_a_query_and_refuse_what_cannot_be():
    assert Mount.parse("0.7") == Mount(height=0.7)
    assert Mount.parse("1.8, 5") == Mount(height=1.8, pitch_deg=5.0)
    assert Mount.parse("1.8,5,-2") == Mount(height=1.8, pitch_deg=5.0, roll_deg=-2.0)
    for bad, message in [("abc", "as numbers"), ("1,2,3,4", r"HEIGHT\[,PITCH")]:
        with pytest.raises(ValueError, match=message):
            Mount.parse(bad)
    with pytest.raises(ValidationError, match="greater than 0"):
        Mount.parse("-1")
    with pytest.raises(ValidationError, match="less than or equal to 45"):
        Mount(height=1.0, pitch_deg=60.0)
