"""A procedural town: streets, terrain, buildings and street furniture, as one static mesh.

Placement walks along both sides of every street and fills lots according to the street's
district; a 0.5 m occupancy raster keeps buildings off roads and off each other. Building
and house *types* come from small per-town catalogues, so similar-looking places exist (as
in real towns) while their arrangement keeps every place distinguishable.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
from pydantic import ConfigDict
from scipy import ndimage

from overlapmamba.core.configs import Config
from overlapmamba.synth.geometry import (
    BOX,
    MAT,
    Mesh,
    instances,
    ribbon,
    template,
)
from overlapmamba.synth.occupancy import Occupancy
from overlapmamba.synth.props import PropBuilder
from overlapmamba.synth.streets import (
    DISTRICTS,
    Street,
    StreetNetwork,
    build_streets,
    frame_at,
    resample,
)
from overlapmamba.synth.terrain import Terrain


class WorldParams(Config):
    model_config = ConfigDict(frozen=True)
    config_name: ClassVar[str] = "WorldParams"

    """Size and shape of a town. Defaults give ≈6–7 km of street (the train preset: 6.7 km).
    Parked cars, traffic and pedestrians are set by DynamicsParams."""

    nx: int = 6  # street-grid nodes along x
    ny: int = 6
    block_min: float = 70.0  # block edge lengths (m)
    block_max: float = 140.0
    terrain_amplitude: float = 4.0  # metres, summed over the terrain waves
    terrain_cell: float = 2.5


@dataclass
class World:
    params: WorldParams
    terrain: Terrain
    network: StreetNetwork
    static: Mesh
    parking: np.ndarray  # (S, 3): x, y, yaw of parking slots
    parking_district: np.ndarray  # (S,) index into DISTRICTS
    lo: np.ndarray
    hi: np.ndarray
    footprints: list[tuple[np.ndarray, str]] = field(default_factory=list)  # (4, 2) corners, kind
    trees: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    surface: np.ndarray | None = None  # coarse material raster for the map picture
    surface_res: float = 2.0

    @property
    def street_length(self) -> float:
        return sum(s.length for s in self.network.streets)


# District → (setback range, gap range between lots, catalogue, footprint kind, how much
# closer to an intersection lots may start). Urban lots are terraced: no gap.
_LOTS = {
    "urban": ((2.5, 4.5), (0.0, 0.0), "urban_types", "urban", -6.0),
    "suburban": ((6.0, 10.0), (3.0, 10.0), "house_types", "house", 0.0),
    "industrial": ((9.0, 18.0), (8.0, 20.0), "hall_types", "hall", 0.0),
}


class _Builder(PropBuilder):
    def __init__(self, rng: np.random.Generator, params: WorldParams) -> None:
        self.p = params
        self.net = build_streets(rng, params.nx, params.ny, (params.block_min, params.block_max))
        super().__init__(rng, Terrain(rng, params.terrain_amplitude))
        self.lo, self.hi = self.net.bounds(margin=140.0)
        self.raster = Occupancy(self.lo, self.hi)
        self.footprints: list[tuple[np.ndarray, str]] = []
        self.parking: list[tuple[float, float, float, int]] = []
        # Per-town catalogues: repeated types make look-alike places.
        r = rng
        self.house_types = [
            dict(
                l=r.uniform(8, 13),
                w=r.uniform(7, 10),
                h=r.uniform(5.5, 8.5),
                gable=r.random() < 0.7,
            )
            for _ in range(5)
        ]
        self.urban_types = [
            dict(l=r.uniform(8, 22), w=r.uniform(12, 20), h=r.uniform(9, 24), top=r.random() < 0.4)
            for _ in range(8)
        ]
        self.hall_types = [
            dict(l=r.uniform(25, 70), w=r.uniform(20, 45), h=r.uniform(7, 13)) for _ in range(5)
        ]

    # ---- layout -----------------------------------------------------------------------
    def rasterise_roads(self) -> None:
        """Road mask: cells closer to a centreline than its half-width plus a kerb margin."""
        R = self.raster
        centre = np.zeros(R.shape, bool)
        hw = np.zeros(R.shape, np.float32)
        for s in self.net.streets:
            pts, _ = resample(s.points, R.res / 2)
            i, j = R.idx(pts)
            centre[i, j] = True
            hw[i, j] = np.maximum(hw[i, j], s.half_width)
        dist, (ii, jj) = ndimage.distance_transform_edt(~centre, return_indices=True)
        self.road_dist = dist * R.res
        self.road_hw = hw[ii, jj]
        R.road = self.road_dist < self.road_hw + 0.8

    def street_side(self, s: Street, side: int) -> None:
        """Fill one side of a street (side = +1 left of u→v, −1 right)."""
        r, d = self.rng, s.district
        L = s.length
        hw = s.half_width
        junction = hw + 10.0  # keep lot frontages out of intersections

        def frame(at: np.ndarray, offset: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            pos, tan = frame_at(s.points, at)
            nrm = np.column_stack([-tan[:, 1], tan[:, 0]]) * side
            return pos + nrm * offset, tan, nrm

        # Parking slots along the kerb.
        if d != "open" and r.random() < {"urban": 0.75, "suburban": 0.45, "industrial": 0.35}[d]:
            at = np.arange(junction + 2, L - junction - 2, r.uniform(5.6, 6.6))
            if len(at):
                pos, tan, _ = frame(at, hw - 1.1)
                yaw = np.arctan2(tan[:, 1], tan[:, 0])
                for (x, y), a in zip(pos, yaw, strict=True):
                    self.parking.append((x, y, a, DISTRICTS.index(d)))

        # Buildings.
        if d in _LOTS:
            setback, gap, catalogue, kind, junction_shift = _LOTS[d]
            self._lots(
                s,
                side,
                frame,
                setback,
                gap,
                getattr(self, catalogue),
                kind,
                junction + junction_shift,
            )
        elif r.random() < 0.25:  # a lone barn on the open road
            self._lots(
                s,
                side,
                frame,
                setback=(12.0, 25.0),
                gap=(60.0, 150.0),
                catalogue=self.hall_types[:2],
                kind="hall",
                junction=junction,
            )

        # Street lights.
        pitch = {"urban": (24, 34), "suburban": (30, 45), "industrial": (35, 50), "open": (45, 70)}[
            d
        ]
        if d != "open" or side == 1:
            at = np.arange(r.uniform(5, 20), L, r.uniform(*pitch))
            pos, tan, nrm = frame(at, hw + 0.7)
            ok = self._clear(pos, 0.5)
            self.pole(pos[ok], np.arctan2(-nrm[ok, 1], -nrm[ok, 0]))

        # Street trees, yard trees, bushes.
        if d == "urban" and r.random() < 0.5:
            at = np.arange(r.uniform(3, 10), L, r.uniform(8, 14))
            pos, _, _ = frame(at, hw + 1.8)
            self.tree(pos[self._clear(pos, 0.8)], 0.8)
        elif d == "open":
            n = int(L / r.uniform(8, 30))
            pos, _, nrm = frame(r.uniform(0, L, n), 0.0)
            pos = pos + nrm * (hw + r.uniform(4, 30, n))[:, None]
            ok = self._clear(pos, 2.5)
            self.tree(pos[ok])
            n = int(L / r.uniform(10, 25))
            pos, _, nrm = frame(r.uniform(0, L, n), 0.0)
            pos = pos + nrm * (hw + r.uniform(2, 15, n))[:, None]
            self.bush(pos[self._clear(pos, 1.5)])
            if r.random() < 0.4:  # guard rail on posts
                at = np.arange(junction, L - junction, 1.0)
                if len(at) > 2:
                    pos, _, _ = frame(at, 0.0)
                    z = self.z(pos)
                    self._ribbon_mesh(
                        ribbon(pos, side * (hw + 0.6), 0.08, z + 0.55, 0.32), "guardrail"
                    )
                    posts, _, _ = frame(at[::4], hw + 0.6)
                    self.parts.append(
                        instances(
                            BOX,
                            posts,
                            0.0,
                            [[0.12, 0.12, 0.9]],
                            self.z(posts) - 0.1,
                            [MAT["metal"]],
                            self._albedo("metal", len(posts)),
                        )
                    )
        elif d == "industrial" and r.random() < 0.7:  # site fence with gates
            at = np.arange(junction, L - junction, 1.0)
            gates = r.uniform(0, L, 2)
            at = at[np.abs(at[:, None] - gates[None]).min(1) > 4]
            if len(at) > 2:
                pos, _, _ = frame(at, 0.0)
                for run in np.split(pos, np.nonzero(np.diff(at) > 1.5)[0] + 1):
                    if len(run) > 2:
                        self._ribbon_mesh(
                            ribbon(run, side * (hw + 4.0), 0.05, self.z(run) - 0.1, 2.1), "fence"
                        )

        # Kerb.
        at = np.arange(hw + 3.0, L - hw - 3.0, 1.0)
        if len(at) > 2:
            pos, _, _ = frame(at, 0.0)
            self._ribbon_mesh(ribbon(pos, side * (hw + 0.15), 0.3, self.z(pos) - 0.1, 0.25), "kerb")

    def _clear(self, pos: np.ndarray, radius: float) -> np.ndarray:
        """Points at least ``radius`` off every road and not on anything placed."""
        i, j = self.raster.idx(pos)
        ok = (self.road_dist[i, j] > self.road_hw[i, j] + radius) & ~self.raster.occ[i, j]
        return ok

    def _ribbon_mesh(self, tris: np.ndarray, mat: str) -> None:
        if len(tris):
            self.parts.append(
                Mesh(
                    tris.astype(np.float32),
                    np.full(len(tris), MAT[mat], np.uint8),
                    self._albedo(mat, 1).repeat(len(tris)).astype(np.float32),
                )
            )

    def _lots(
        self, s: Street, side: int, frame, setback, gap, catalogue, kind: str, junction: float
    ) -> None:
        r = self.rng
        at = junction + r.uniform(0, 4)
        while at < s.length - junction:
            t = catalogue[r.integers(len(catalogue))]
            length, depth, _height = t["l"], t["w"], t["h"]
            back = r.uniform(*setback)
            if kind == "urban" and r.random() < 0.25:
                back += r.uniform(1.0, 3.0)  # recess in the facade line
            mid = np.array([at + length / 2])
            pos, tan, _nrm = frame(mid, s.half_width + back + depth / 2)
            c, yaw = pos[0], float(np.arctan2(tan[0, 1], tan[0, 0]))
            # Terraced lots (no gap) may touch their neighbours; detached ones keep clear.
            clearance = 0.4 if gap[1] > 0 else -0.4
            if kind == "urban" and r.random() < 0.12:
                # A courtyard wall instead of a facade: the street front stays closed.
                wall_at = s.half_width + back + 0.2
                wall_mid = frame(mid, wall_at)[0][0]
                if self.raster.free(wall_mid, yaw, length, 0.6):
                    stations = np.arange(at, at + length + 0.5, 1.0)
                    pts, _, _ = frame(stations, wall_at)
                    self._ribbon_mesh(
                        ribbon(pts, 0.0, 0.35, self.z(pts) - 0.1, r.uniform(2.2, 3.2)), "facade"
                    )
                    self.raster.mark(wall_mid, yaw, length, 0.6)
                at += length
                continue
            if self.raster.free(c, yaw, length + clearance, depth + clearance):
                self.raster.mark(c, yaw, length, depth)
                self.footprints.append((self._corners(c, yaw, length, depth), kind))
                self._building(c, yaw, t, kind)
                if kind == "house":
                    self._yard(s, frame, at, length, back)
            at += length + r.uniform(*gap)

    def _building(self, c, yaw, t: dict, kind: str) -> None:
        r = self.rng
        length, depth, height = t["l"], t["w"], t["h"]
        corners = self._corners(c, yaw, length, depth)
        base = float(self.z(corners).min()) - 0.3
        if kind == "house" and t["gable"]:
            self.parts.append(
                instances(
                    template("gable_house"),
                    c[None],
                    [yaw],
                    [[length, depth, height + 0.3]],
                    [base],
                    [MAT["facade"], MAT["roof"]],
                    self._albedo("facade", 1)[:, None].repeat(2, 1),
                )
            )
        else:
            mat = "metal" if kind == "hall" else "facade"
            self.box(c, yaw, length, depth, height, mat)
            if kind == "urban" and t["top"]:  # a set-back top storey
                self.box(
                    c + r.uniform(-1, 1, 2),
                    yaw,
                    length * 0.7,
                    depth * 0.6,
                    3.0,
                    "facade",
                    z0=base + 0.3 + height,
                )

    def _yard(self, s: Street, frame, at: float, length: float, back: float) -> None:
        r = self.rng
        if r.random() < 0.6:  # hedge, fence or low garden wall along the front
            stations = np.arange(at, at + length, 1.0)
            if len(stations) > 2:
                pos, _, _ = frame(stations, s.half_width + back - 1.5)
                mat, width, h = [("foliage", 0.6, 1.1), ("fence", 0.05, 1.0), ("facade", 0.3, 0.9)][
                    int(r.integers(3))
                ]
                self._ribbon_mesh(ribbon(pos, 0.0, width, self.z(pos) - 0.1, h), mat)
        n = r.integers(0, 3)
        if n:
            pos, _, _nrm = frame(
                at + r.uniform(0, length, n), s.half_width + r.uniform(2.5, back - 1.0, n)
            )
            if r.random() < 0.5:
                self.bush(pos)
            else:
                self.tree(pos, 0.8)

    def junctions(self) -> None:
        """Signs at intersection corners and dashed centre lines."""
        r = self.rng
        for node, nbrs in self.net.adjacency.items():
            if len(nbrs) < 3 or r.random() < 0.3:
                continue
            c = self.net.nodes[node]
            for _, k in nbrs[: r.integers(1, 3)]:
                s = self.net.streets[k]
                pts = s.oriented(node)
                d = pts[min(6, len(pts) - 1)] - c
                d /= np.linalg.norm(d)
                nrm = np.array([d[1], -d[0]])
                p = c + d * (s.half_width + 4) + nrm * (s.half_width + 1.2)
                if self._clear(p[None], 0.3)[0]:
                    self.sign(p[None], np.array([np.arctan2(d[1], d[0])]))
        for s in self.net.streets:
            if s.half_width < 4.0:
                continue
            at = np.arange(s.half_width + 6, s.length - s.half_width - 6, 9.0)
            if len(at):
                pos, tan = frame_at(s.points, at)
                self.parts.append(
                    instances(
                        BOX,
                        pos,
                        np.arctan2(tan[:, 1], tan[:, 0]),
                        [[3.0, 0.15, 0.035]],
                        self.z(pos) - 0.02,
                        [MAT["marking"]],
                        self._albedo("marking", len(pos), 0.1),
                    )
                )

    def ground(self) -> Mesh:
        R = self.raster

        def surface(xy: np.ndarray) -> np.ndarray:
            i, j = R.idx(xy)
            d, hw = self.road_dist[i, j], self.road_hw[i, j]
            district = self.net.district_at(xy)
            soft = np.isin(district, [DISTRICTS.index("suburban"), DISTRICTS.index("open")])
            out = np.where(soft, MAT["grass"], MAT["pavement"])
            out = np.where(d < hw + 4.0, MAT["pavement"], out)
            return np.where(d < hw, MAT["asphalt"], out).astype(np.uint8)

        self.surface_fn = surface
        return self.terrain.mesh(self.lo, self.hi, self.p.terrain_cell, surface)


def build_world(seed: int, params: WorldParams | None = None) -> World:
    """The static town for ``seed``: the same seed always gives the same world."""
    params = params or WorldParams()
    rng = np.random.default_rng([seed, 0x5EED])
    b = _Builder(rng, params)
    b.rasterise_roads()
    for s in b.net.streets:
        for side in (1, -1):
            b.street_side(s, side)
    b.junctions()
    ground = b.ground()
    static = Mesh.concat([ground, *b.parts])
    parking = np.array([p[:3] for p in b.parking], np.float64).reshape(-1, 3)
    # Coarse surface raster for the map picture.
    res = 2.0
    xs = np.arange(b.lo[0], b.hi[0], res) + res / 2
    ys = np.arange(b.lo[1], b.hi[1], res) + res / 2
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    surface = b.surface_fn(np.column_stack([gx.ravel(), gy.ravel()])).reshape(gx.shape)
    return World(
        params=params,
        terrain=b.terrain,
        network=b.net,
        static=static,
        parking=parking,
        parking_district=np.array([p[3] for p in b.parking], np.int64),
        lo=b.lo,
        hi=b.hi,
        footprints=b.footprints,
        trees=np.concatenate(b.trees) if b.trees else np.zeros((0, 2)),
        surface=surface,
        surface_res=res,
    )
