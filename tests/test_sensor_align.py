"""benchmarks/sensor_align.py: the per-sensor maps of descriptors into the model sensor's."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import benchmark_module


@pytest.fixture(scope="module")
def align():
    return benchmark_module("sensor_align")


def places(rng: np.random.Generator, n: int, dim: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Unit descriptors of n places along a drive (positions 10 m apart), crowded in a cone
    as a trained network's are."""
    d = rng.normal(size=(n, dim)) * 0.2 + np.eye(dim)[0]
    pos = np.column_stack([np.arange(n) * 10.0, np.zeros(n), np.zeros(n)])
    return d / np.linalg.norm(d, axis=1, keepdims=True), pos


def test_shift_undoes_a_sensors_offset_and_linear_its_mixing(align):
    rng = np.random.default_rng(0)
    model, pos = places(rng, 200)
    offset = rng.normal(size=16) * 0.5
    shifted = model + offset  # a sensor whose descriptors sit elsewhere by one vector
    mixed = (model - model.mean(0)) @ np.linalg.qr(rng.normal(size=(16, 16)))[0] + offset
    raw = align.recall(model, pos, shifted, pos)["ar@1"]
    assert raw < 0.5
    assert align.recall(model, pos, align.fit(shifted, model, "shift")(shifted), pos)["ar@1"] == 1
    assert align.recall(model, pos, align.fit(mixed, model, "shift")(mixed), pos)["ar@1"] < 0.5
    # the maps renormalise: the linear one undoes the mixing of unit descriptors exactly
    np.testing.assert_allclose(align.fit(mixed, model, "linear", 0.0)(mixed), model, atol=1e-5)
    assert align.recall(model, pos, align.fit(mixed, model, "linear", 0.01)(mixed), pos)[
        "ar@1"
    ] == pytest.approx(1.0)
    assert align.fit(model, model, "raw")(shifted) is shifted
    with pytest.raises(ValueError, match="unknown calibration 'rotate'; allowed: raw, shift"):
        align.fit(model, model, "rotate")
