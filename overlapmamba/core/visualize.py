"""Range images as pictures for people (numpy only; writing the PNG is the caller's job)."""

from __future__ import annotations

import numpy as np

from overlapmamba.core.sensors import SensorProfile

# Anchor colours of a perceptually ordered ramp (near = yellow … far = dark blue).
_RAMP = np.array(
    [[253, 231, 37], [94, 201, 98], [33, 145, 140], [59, 82, 139], [68, 1, 84]], dtype=np.float64
)


def colorize(image: np.ndarray, profile: SensorProfile, *, scale: int = 1) -> np.ndarray:
    """(H, W) range image → (H·s, W, 3) uint8 RGB; empty pixels are black.

    Depth is mapped on a log scale so the near field, where most structure is, gets most of
    the colour range. ``scale`` repeats rows so a 64-row image is readable on screen.
    """
    valid = image != np.float32(profile.empty_value)
    lo = max(profile.min_range, 0.5)
    t = np.log(np.clip(image, lo, profile.max_range) / lo) / np.log(profile.max_range / lo)
    pos = np.clip(t, 0.0, 1.0) * (len(_RAMP) - 1)
    i = np.minimum(pos.astype(int), len(_RAMP) - 2)
    frac = (pos - i)[..., None]
    rgb = _RAMP[i] * (1 - frac) + _RAMP[i + 1] * frac
    rgb[~valid] = 0
    return np.repeat(rgb.astype(np.uint8), scale, axis=0)
