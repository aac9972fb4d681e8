"""The yaw features' magnitude spectrum as a first stage (overlapmamba.core.yaw_spectrum):
it does not turn with the scan, it mixes with the descriptor by squared distance, and bad
settings say what is allowed."""

from __future__ import annotations

import numpy as np
import pytest

from overlapmamba.core.yaw_spectrum import FirstStage, spectrum, unit


def _features(n: int = 5, c: int = 4, w: int = 64, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(n, c, w)).astype(np.float32)


def test_a_turn_by_whole_columns_changes_no_spectrum_and_another_place_does():
    yaw = _features()
    turned = np.roll(yaw, shift=(0, 0, 17), axis=(0, 1, 2))
    a, b = spectrum(yaw, 16), spectrum(turned, 16)
    assert a.shape == (5, 4 * 16)
    np.testing.assert_allclose(a, b, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-6)
    other = spectrum(_features(seed=1), 16)
    assert np.all(np.abs((a * other).sum(1)) < 0.99)  # other scans are not the same place


def test_the_spectrum_is_each_channels_rfft_magnitude_in_chunks():
    yaw = _features(n=300, c=2, w=32)  # more scans than one FFT call takes
    want = np.sqrt(np.abs(np.fft.rfft(yaw.astype(np.float64), axis=-1))[..., :5])
    want = want.reshape(300, -1)
    want /= np.linalg.norm(want, axis=1, keepdims=True)
    np.testing.assert_allclose(spectrum(yaw, 5, "sqrt"), want, atol=1e-5)
    plain = np.abs(np.fft.rfft(yaw.astype(np.float64), axis=-1))[..., :5].reshape(300, -1)
    np.testing.assert_allclose(
        spectrum(yaw, 5, "none"), plain / np.linalg.norm(plain, axis=1, keepdims=True), atol=1e-5
    )


def test_mixed_rows_add_the_two_squared_distances_by_their_share():
    rng = np.random.default_rng(2)
    desc, yaw = rng.normal(size=(2, 8)), _features(n=2)
    stage = FirstStage(0.75, 8, "sqrt")
    v = stage.vectors(desc, yaw)
    d2 = lambda x: float(((x[0] - x[1]) ** 2).sum())  # noqa: E731
    want = 0.25 * d2(unit(desc)) + 0.75 * d2(spectrum(yaw, 8))
    assert d2(v) == pytest.approx(want, rel=1e-5)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(FirstStage().vectors(desc, yaw), unit(desc))
    np.testing.assert_allclose(FirstStage(1.0, 8).vectors(desc, yaw), spectrum(yaw, 8))


def test_first_stages_parse_and_name_themselves_and_refuse_what_is_not_allowed():
    for text in ("descriptor", "spectrum:32:sqrt", "mixed:0.75:32:sqrt", "mixed:0.5:8:none"):
        assert FirstStage.parse(text).name == text
    assert FirstStage.parse("mixed:1:16:sqrt") == FirstStage(1.0, 16, "sqrt")
    with pytest.raises(ValueError, match="is not descriptor, spectrum:BINS:COMPRESS"):
        FirstStage.parse("spectrum:32")
    with pytest.raises(ValueError, match="mix must be in"):
        FirstStage.parse("mixed:1.5:32:sqrt")
    with pytest.raises(ValueError, match="not one of none, sqrt"):
        FirstStage.parse("spectrum:32:log")
    with pytest.raises(ValueError, match="first stage 'spectrum:x:sqrt'"):
        FirstStage.parse("spectrum:x:sqrt")
    with pytest.raises(ValueError, match="bins must be"):
        FirstStage(1.0, 0)
    with pytest.raises(ValueError, match="64 columns have 33 frequencies"):
        spectrum(_features(), 40)
    with pytest.raises(ValueError, match=r"must be \(N, C, W\)"):
        spectrum(np.zeros((4, 64)), 8)
