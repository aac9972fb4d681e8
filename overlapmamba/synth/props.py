"""Street furniture and the primitives everything is built from: boxes, trees, bushes, poles
and signs, each placed on the terrain with a material and a per-instance albedo. The town
builder (:mod:`overlapmamba.synth.world`) decides where they go."""

from __future__ import annotations

import numpy as np

from overlapmamba.synth.geometry import BOX, CYLINDER, MAT, REFLECTIVITY, Mesh, instances, template
from overlapmamba.synth.terrain import Terrain


class PropBuilder:
    """Collects placed meshes (``parts``) and tree positions (``trees``); draws shapes and
    albedos from ``rng`` in the order they are placed."""

    def __init__(self, rng: np.random.Generator, terrain: Terrain) -> None:
        self.rng = rng
        self.terrain = terrain
        self.parts: list[Mesh] = []
        self.trees: list[np.ndarray] = []

    # ---- primitives -------------------------------------------------------------------
    def z(self, xy: np.ndarray) -> np.ndarray:
        return self.terrain.height(xy)

    def _albedo(self, mat: str, n: int, spread: float = 0.25) -> np.ndarray:
        base = REFLECTIVITY[MAT[mat]]
        return np.clip(base * self.rng.uniform(1 - spread, 1 + spread, n), 0.02, 1.0)

    def box(self, c, yaw, length, w, h, mat: str, z0: float | None = None) -> None:
        c = np.asarray(c, float)
        corners = self._corners(c, yaw, length, w)
        base = float(self.z(corners).min()) - 0.3 if z0 is None else z0
        self.parts.append(
            instances(
                BOX,
                c[None],
                [yaw],
                [[length, w, h + (0.3 if z0 is None else 0)]],
                [base],
                [MAT[mat]],
                self._albedo(mat, 1),
            )
        )

    @staticmethod
    def _corners(c, yaw, length, w) -> np.ndarray:
        cs, sn = np.cos(yaw), np.sin(yaw)
        loc = np.array([[-length, -w], [length, -w], [length, w], [-length, w]]) / 2
        return c + loc @ np.array([[cs, sn], [-sn, cs]])

    def tree(self, xy: np.ndarray, scale: float = 1.0) -> None:
        n = len(xy)
        if n == 0:
            return
        r = self.rng
        trunk_h = r.uniform(1.8, 3.5, n) * scale
        crown_d = r.uniform(3.0, 7.0, n) * scale
        crown_h = crown_d * r.uniform(0.8, 1.3, n)
        z0 = self.z(xy)
        trunk_r = r.uniform(0.25, 0.5, n) * scale
        self.parts.append(
            instances(
                CYLINDER,
                xy,
                r.uniform(0, 6.3, n),
                np.column_stack([trunk_r, trunk_r, trunk_h + 0.5]),
                z0 - 0.2,
                [MAT["bark"]],
                self._albedo("bark", n),
            )
        )
        self.parts.append(
            instances(
                template("ellipsoid"),
                xy,
                r.uniform(0, 6.3, n),
                np.column_stack([crown_d, crown_d * r.uniform(0.8, 1.2, n), crown_h]),
                z0 + trunk_h * 0.75,
                [MAT["foliage"]],
                self._albedo("foliage", n),
            )
        )
        self.trees.append(xy)

    def bush(self, xy: np.ndarray) -> None:
        n = len(xy)
        if n == 0:
            return
        r = self.rng
        d = r.uniform(1.0, 2.6, n)
        self.parts.append(
            instances(
                template("ellipsoid"),
                xy,
                r.uniform(0, 6.3, n),
                np.column_stack([d, d * r.uniform(0.7, 1.3, n), r.uniform(0.8, 1.7, n)]),
                self.z(xy) - 0.2,
                [MAT["foliage"]],
                self._albedo("foliage", n),
            )
        )

    def pole(self, xy: np.ndarray, yaw: np.ndarray) -> None:
        """Street lights with an arm reaching over the road (``yaw`` points at the road)."""
        n = len(xy)
        if n == 0:
            return
        r = self.rng
        h = r.uniform(6.0, 9.0, n)
        rad = r.uniform(0.18, 0.3, n)
        z0 = self.z(xy)
        self.parts.append(
            instances(
                CYLINDER,
                xy,
                0.0,
                np.column_stack([rad, rad, h]),
                z0 - 0.2,
                [MAT["pole"]],
                self._albedo("pole", n),
            )
        )
        arm = xy + np.column_stack([np.cos(yaw), np.sin(yaw)]) * 0.9
        self.parts.append(
            instances(
                BOX,
                arm,
                yaw,
                np.column_stack([np.full(n, 1.8), np.full(n, 0.25), np.full(n, 0.2)]),
                z0 + h - 0.4,
                [MAT["pole"]],
                self._albedo("pole", n),
            )
        )

    def sign(self, xy: np.ndarray, yaw: np.ndarray) -> None:
        n = len(xy)
        if n == 0:
            return
        z0 = self.z(xy)
        self.parts.append(
            instances(
                CYLINDER,
                xy,
                0.0,
                [[0.12, 0.12, 2.6]],
                z0 - 0.2,
                [MAT["pole"]],
                self._albedo("pole", n),
            )
        )
        self.parts.append(
            instances(
                BOX,
                xy,
                yaw,
                [[0.08, 0.7, 0.7]],
                z0 + 1.9,
                [MAT["sign"]],
                self._albedo("sign", n, 0.05),
            )
        )
