"""The translation seed of a registration: where the query's structure best overlays the
keyframe's from above.

A revisit passes a place metres to the side or along the road from where the keyframe was
taken; GICP alone, with its 2 m correspondences, does not travel that far. Each side's steep
points (:func:`overlapmamba.service.registration.structure`) make a bird's-eye occupancy grid
(:func:`bev_spectrum`, kept as its spectrum: the query's once per seed yaw, the keyframe's once
per keyframe); their FFT cross-correlation's peak within ``max_shift`` is the seed
(:func:`seed_translation`). Single precision, 90 cells a side on the service's grid: the
smallest free of wrap-around within ``max_shift``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class BevGrid:
    cell: float = 2.0  # m: the grid's cells
    max_shift: float = 40.0  # m: the farthest translation the seed looks for
    reach: float = 64.0  # m: the grid's half-width (structure farther out is left out)


def _grid_size(g: BevGrid) -> tuple[int, int]:
    """(cells across the bird's-eye grid, FFT size). The correlation is circular: a shift s
    reads s − size too. Shifts beyond n − 1 cells overlap nothing, so a size of at least
    n + max_shift cells keeps every shift the seed looks at free of wrap-around."""
    n = 2 * int(np.ceil(g.reach / g.cell)) + 2
    reach = int(np.ceil(g.max_shift / g.cell))
    size = n + reach + 1
    while not _smooth(size):  # FFT sizes of 2, 3 and 5 only are the fast ones
        size += 1
    return n, size


def _smooth(m: int) -> bool:
    for f in (2, 3, 5):
        while m % f == 0:
            m //= f
    return m == 1


@functools.lru_cache(maxsize=8)
def _shifts(g: BevGrid) -> tuple[np.ndarray, np.ndarray]:
    """(signed shift of each FFT bin in metres, the bins within max_shift)."""
    _, size = _grid_size(g)
    steps = np.fft.fftfreq(size, 1.0 / size) * g.cell
    return steps, np.flatnonzero(np.abs(steps) <= g.max_shift)


def bev_spectrum(xy: np.ndarray, g: BevGrid) -> np.ndarray:
    """The spectrum of a bird's-eye occupancy grid of ``xy`` (metres, centred)."""
    n, size = _grid_size(g)
    ij = np.floor(xy[:, :2] / g.cell).astype(np.int64) + n // 2
    ij = ij[((ij >= 0) & (ij < n)).all(axis=1)]
    grid = np.zeros((n, n), dtype=np.float32)
    grid[ij[:, 0], ij[:, 1]] = 1.0
    # each cell also counts half in its 4 neighbours: grids of 2 m voxel means are sparse
    out = grid.copy()
    out[1:] += 0.5 * grid[:-1]
    out[:-1] += 0.5 * grid[1:]
    out[:, 1:] += 0.5 * grid[:, :-1]
    out[:, :-1] += 0.5 * grid[:, 1:]
    return np.fft.rfft2(out, (size, size))  # single precision: an argmax needs no more


def seed_translation(query: np.ndarray, target: np.ndarray, g: BevGrid) -> np.ndarray:
    """The (x, y) shift, within ``max_shift``, that best overlays the query's grid (turned by
    the seed yaw) on the keyframe's: both ``bev_spectrum`` s."""
    _, size = _grid_size(g)
    corr = np.fft.irfft2(target * np.conj(query), (size, size))
    steps, near = _shifts(g)
    corr = corr[np.ix_(near, near)]
    i, j = np.unravel_index(int(np.argmax(corr)), corr.shape)
    return np.array([steps[near[i]], steps[near[j]]])
