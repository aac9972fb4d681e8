"""One-column gaps in a range image's rows, filled (the ``elevation-fill`` input).

A sensor that fires about once a model column leaves a hole wherever one firing is lost.
An OS1-128 or OS0-128 fires 1,024 times a turn into the KITTI model's 900 columns: most
columns hold one firing of a beam, and each lost return (a dark or glancing surface, the
simulator's random dropout) is an empty cell between two returns. An HDL-64E fires 2,083 times
a turn, two or three firings a column, so a lost one is covered by its neighbour in the same
column and the network never saw such holes. :func:`fill_gaps` gives every empty cell whose
two neighbours in its row hold returns the nearer of their two ranges (the projection keeps
the nearest return of a cell too); rows are circular, as azimuth is. Wider gaps (the sky, a
window, the far side of an edge) are left as they are.

The inputs that fill them are ``elevation-fill`` and ``elevation-reach``
(:mod:`overlapmamba.core.sensors.input`), measured with the shipped weights by
``benchmarks/fill_gaps.py`` and ``benchmarks/across_pairs.py``.
"""

from __future__ import annotations

import numpy as np


def gaps(images: np.ndarray, empty_value: float) -> np.ndarray:
    """(…, H, W) bool: the one-column gaps of each row (an empty cell between two returns;
    the rows wrap around). ``empty_value`` marks an empty cell."""
    if images.ndim < 2 or images.shape[-1] < 3:
        raise ValueError(f"images must have shape (..., H, W) with W >= 3; got {images.shape}")
    empty = images == np.float32(empty_value)
    left, right = np.roll(empty, 1, axis=-1), np.roll(empty, -1, axis=-1)
    return empty & ~left & ~right


def fill_gaps(images: np.ndarray, empty_value: float) -> np.ndarray:
    """(…, H, W) float32 range images → a copy with every one-column gap holding the nearer
    of its two neighbours' ranges. Returns are positive ranges and ``empty_value`` (≤ 0)
    marks an empty cell, as :class:`~overlapmamba.core.sensors.profile.SensorProfile` says."""
    if empty_value > 0:
        raise ValueError(
            f"empty_value must be 0 or negative (a range is positive); got {empty_value}"
        )
    hole = gaps(images, empty_value)
    nearer = np.minimum(np.roll(images, 1, axis=-1), np.roll(images, -1, axis=-1))
    out = np.array(images, dtype=np.float32, copy=True)
    out[hole] = nearer[hole]
    return out
