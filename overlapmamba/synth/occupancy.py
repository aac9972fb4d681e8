"""Where a town's builder may still place something: a raster of the ground at 0.5 m marking
the roads (with their kerb margin) and every footprint placed so far (:mod:`.world`)."""

from __future__ import annotations

import numpy as np


class Occupancy:
    """Occupancy at 0.5 m: roads (with kerb margin) and everything placed so far."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray, res: float = 0.5) -> None:
        self.lo, self.res = lo, res
        self.shape = tuple(np.ceil((hi - lo) / res).astype(int) + 1)
        self.road = np.zeros(self.shape, bool)
        self.occ = np.zeros(self.shape, bool)

    def idx(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ij = np.floor((np.asarray(xy) - self.lo) / self.res).astype(int)
        ij = np.clip(ij, 0, np.array(self.shape) - 1)
        return ij[..., 0], ij[..., 1]

    def rect(self, c: np.ndarray, yaw: float, length: float, width: float) -> tuple:
        u = np.arange(-length / 2, length / 2 + 1e-9, self.res / 1.5)
        v = np.arange(-width / 2, width / 2 + 1e-9, self.res / 1.5)
        uu, vv = np.meshgrid(u, v, indexing="ij")
        cs, sn = np.cos(yaw), np.sin(yaw)
        xy = np.stack([c[0] + cs * uu - sn * vv, c[1] + sn * uu + cs * vv], -1).reshape(-1, 2)
        return self.idx(xy)

    def free(self, c, yaw, length, width) -> bool:
        """The rectangle lies inside the raster, off roads and off everything placed."""
        i, j = self.rect(c, yaw, length, width)
        inside = (c - self.lo > length).all() and (
            self.lo + np.array(self.shape) * self.res - c > length
        ).all()
        return bool(inside and not self.occ[i, j].any() and not self.road[i, j].any())

    def mark(self, c, yaw, length, width) -> None:
        i, j = self.rect(c, yaw, length, width)
        self.occ[i, j] = True
