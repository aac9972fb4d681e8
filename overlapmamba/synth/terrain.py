"""Gentle terrain: a sum of a few long-wavelength plane waves.

Wavelengths of 200–700 m and a total amplitude of a few metres give slopes of at most a few
per cent, like the hills of a town. Everything stands on it: roads, buildings, the vehicle.
"""

from __future__ import annotations

import numpy as np

from overlapmamba.synth.geometry import REFLECTIVITY, Mesh


class Terrain:
    def __init__(self, rng: np.random.Generator, amplitude: float, waves: int = 6) -> None:
        ang = rng.uniform(0, 2 * np.pi, waves)
        wavelength = rng.uniform(200.0, 700.0, waves)
        k = 2 * np.pi / wavelength
        self._k = np.column_stack([np.cos(ang) * k, np.sin(ang) * k])  # (waves, 2)
        self._phase = rng.uniform(0, 2 * np.pi, waves)
        amp = rng.uniform(0.5, 1.0, waves)
        self._amp = amp / amp.sum() * amplitude

    def height(self, xy: np.ndarray) -> np.ndarray:
        """(…, 2) → (…,) metres."""
        xy = np.asarray(xy, np.float64)
        return np.sin(xy @ self._k.T + self._phase) @ self._amp

    def gradient(self, xy: np.ndarray) -> np.ndarray:
        """(…, 2) → (…, 2) dz/dx, dz/dy."""
        xy = np.asarray(xy, np.float64)
        return (np.cos(xy @ self._k.T + self._phase) * self._amp) @ self._k

    def mesh(self, lo: np.ndarray, hi: np.ndarray, cell: float, surface) -> Mesh:
        """Grid mesh over [lo, hi]; ``surface(xy (M, 2)) → material ids (M,)`` per cell."""
        xs = np.arange(lo[0], hi[0] + cell, cell)
        ys = np.arange(lo[1], hi[1] + cell, cell)
        gx, gy = np.meshgrid(xs, ys, indexing="ij")
        gz = self.height(np.stack([gx, gy], -1))
        v = np.stack([gx, gy, gz], -1)  # (nx, ny, 3)
        a, b, c, d = v[:-1, :-1], v[1:, :-1], v[1:, 1:], v[:-1, 1:]
        t1 = np.stack([a, b, c], -2).reshape(-1, 3, 3)
        t2 = np.stack([a, c, d], -2).reshape(-1, 3, 3)
        centers = ((a + c) / 2)[..., :2].reshape(-1, 2)
        mat = np.asarray(surface(centers), np.uint8)
        alb = REFLECTIVITY[mat]
        return Mesh(
            np.concatenate([t1, t2]).astype(np.float32),
            np.concatenate([mat, mat]),
            np.concatenate([alb, alb]),
        )
