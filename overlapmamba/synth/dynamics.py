"""What changes between visits: parked cars, traffic and pedestrians, as a function of time.

* Parked cars: every parking slot changes state in windows of ``park_window`` seconds with
  its own phase. In each window the slot is empty or holds a car of some type and colour at
  some position along the slot, so a place revisited minutes later has cars that appeared,
  left or moved, while consecutive scans see the same ones.
* Traffic: cars drive random routes along the right-hand lanes at their own speeds.
* Pedestrians: walk up and down the pavements.

Everything is precomputed from the seed, so ``mesh_at(t, …)`` is a pure function of time.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
from pydantic import ConfigDict

from overlapmamba.core.configs import Config
from overlapmamba.synth.geometry import MAT, REFLECTIVITY, Mesh, instances, template
from overlapmamba.synth.streets import DISTRICTS, frame_at
from overlapmamba.synth.world import World

# length, width, height (m)
_PARKED, _TRAFFIC, _PEDESTRIAN = 0, 1, 2  # kinds of dynamic object
CAR_TYPES = np.array(
    [[4.5, 1.8, 1.5], [4.0, 1.75, 1.5], [4.8, 1.95, 1.75], [5.2, 2.0, 2.1], [8.5, 2.5, 3.3]]
)


class DynamicsParams(Config):
    model_config = ConfigDict(frozen=True)
    config_name: ClassVar[str] = "DynamicsParams"

    park_window: float = 60.0  # s; a slot may change state once per window
    park_fill: float = 0.6  # probability a slot holds a car in a window
    traffic_per_km: float = 3.0
    pedestrians_per_km: float = 5.0
    # Moving objects whose footprint would overlap the ego car (its footprint in the sensor
    # frame: x from −2.7 to 2.3 m, |y| < 1 m) plus this margin — the car moves ≈1 m per
    # sweep — are left out. Parked cars never overlap the lane and must not pop out as the
    # car passes them.
    keep_clear: float = 0.8


class Dynamics:
    def __init__(
        self,
        world: World,
        seed: int | Sequence[int],
        duration: float,
        params: DynamicsParams | None = None,
    ):
        """``seed``: an int or a list of ints (a session's entropy, ``GenConfig.session_seed``)."""
        self.p = p = params or DynamicsParams()
        self.world = world
        rng = np.random.default_rng([*np.atleast_1d(seed).tolist(), 0xD1A])
        S = len(world.parking)
        windows = int(duration / p.park_window) + 3
        self.park_phase = rng.uniform(0, p.park_window, S)
        self.park_on = rng.random((windows, S)) < p.park_fill
        industrial = world.parking_district == DISTRICTS.index("industrial")
        types = rng.choice(4, (windows, S), p=[0.45, 0.25, 0.2, 0.1])
        trucks = rng.random((windows, S)) < 0.3
        self.park_type = np.where(industrial[None] & trucks, 4, types)
        self.park_shift = rng.uniform(-0.8, 0.8, (windows, S))  # along the slot
        self.park_albedo = _car_albedo(rng, (windows, S))

        km = world.street_length / 1000.0
        self.traffic = [self._route(rng) for _ in range(round(p.traffic_per_km * km))]
        self.traffic_speed = rng.uniform(6.0, 12.0, len(self.traffic))
        self.traffic_type = rng.choice(4, len(self.traffic), p=[0.45, 0.25, 0.2, 0.1])
        self.traffic_albedo = _car_albedo(rng, len(self.traffic))
        self.traffic_s0 = np.array([rng.uniform(0, r[2][-1]) for r in self.traffic])

        n_ped = round(p.pedestrians_per_km * km)
        streets = world.network.streets
        self.ped_street = rng.integers(0, len(streets), n_ped)
        self.ped_offset = np.array(
            [
                (streets[k].half_width + rng.uniform(1.0, 2.5)) * rng.choice([-1, 1])
                for k in self.ped_street
            ]
        )
        self.ped_speed = rng.uniform(1.0, 1.6, n_ped)
        self.ped_s0 = rng.uniform(0, 1, n_ped)
        self.ped_size = np.column_stack(
            [
                rng.uniform(0.4, 0.6, n_ped),
                rng.uniform(0.3, 0.45, n_ped),
                rng.uniform(1.55, 1.9, n_ped),
            ]
        )

    def _route(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A random no-U-turn loop of streets in the right-hand lane: points, yaw, arc length."""
        net = self.world.network
        cur = int(rng.integers(len(net.nodes)))
        prev = None
        parts = []
        for _ in range(40):
            opts = [o for o in net.adjacency[cur] if o[0] != prev] or net.adjacency[cur]
            nxt, k = opts[int(rng.integers(len(opts)))]
            parts.append(net.streets[k].oriented(cur)[:-1])
            prev, cur = cur, nxt
        pts = np.concatenate(parts)
        tan = np.gradient(pts, axis=0)
        tan /= np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-9)
        pts = pts + np.column_stack([tan[:, 1], -tan[:, 0]]) * 1.6
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
        return pts, np.arctan2(tan[:, 1], tan[:, 0]), s

    def mesh_at(self, t: float, center: np.ndarray, radius: float, heading: float = 0.0) -> Mesh:
        """Every dynamic object near the ego car at ``center`` (x, y), facing ``heading``
        (radians), at time ``t``."""
        p, w = self.p, self.world
        xy: list[Any] = []
        yaw: list[Any] = []
        size: list[Any] = []
        alb: list[Any] = []
        kind: list[Any] = []

        # Parked cars.
        win = ((t + self.park_phase) // p.park_window).astype(int)
        win = np.minimum(win, len(self.park_on) - 1)
        cols = np.arange(len(w.parking))
        on = self.park_on[win, cols]
        if len(w.parking):
            a = w.parking[:, 2]
            shift = self.park_shift[win, cols]
            pxy = w.parking[:, :2] + np.column_stack([np.cos(a), np.sin(a)]) * shift[:, None]
            sel = on & (np.linalg.norm(pxy - center, axis=1) < radius)
            xy.append(pxy[sel])
            yaw.append(a[sel])
            size.append(CAR_TYPES[self.park_type[win, cols][sel]])
            alb.append(self.park_albedo[win, cols][sel])
            kind.append(np.full(sel.sum(), _PARKED))

        # Traffic.
        for i, (pts, tyaw, s) in enumerate(self.traffic):
            at = (self.traffic_s0[i] + self.traffic_speed[i] * t) % s[-1]
            j = int(np.searchsorted(s, at))
            j = min(j, len(pts) - 1)
            if np.linalg.norm(pts[j] - center) < radius:
                xy.append(pts[j][None])
                yaw.append([tyaw[j]])
                size.append(CAR_TYPES[[self.traffic_type[i]]])
                alb.append([self.traffic_albedo[i]])
                kind.append([_TRAFFIC])

        # Pedestrians walk to the end of their street and back.
        streets = w.network.streets
        for i, k in enumerate(self.ped_street):
            st = streets[k]
            L = st.length
            phase = (self.ped_s0[i] + self.ped_speed[i] * t / (2 * L)) % 1.0
            at = L * (2 * phase if phase < 0.5 else 2 - 2 * phase)
            pos, tan = frame_at(st.points, np.array([at]))
            pos = pos + np.column_stack([-tan[:, 1], tan[:, 0]]) * self.ped_offset[i]
            if np.linalg.norm(pos[0] - center) < radius:
                xy.append(pos)
                yaw.append([np.arctan2(tan[0, 1], tan[0, 0])])
                size.append(self.ped_size[[i]])
                alb.append([REFLECTIVITY[MAT["person"]]])
                kind.append([_PEDESTRIAN])

        if not xy:
            return Mesh.empty()
        xy_a = np.concatenate(xy).reshape(-1, 2)
        kind_all = np.concatenate(kind)
        moving = kind_all != _PARKED
        size_all = np.concatenate(size).reshape(-1, 3)
        rel = xy_a - center
        c, s = np.cos(heading), np.sin(heading)
        ahead, left = rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c
        # Conservative: the object's half diagonal stands in for its orientation.
        reach = np.linalg.norm(size_all[:, :2], axis=1) / 2 + p.keep_clear
        overlaps = (ahead > -2.7 - reach) & (ahead < 2.3 + reach) & (np.abs(left) < 1.0 + reach)
        keep = ~(moving & overlaps)
        yaw_a = np.concatenate(yaw)[keep]
        size_a = size_all[keep]
        alb_a = np.concatenate(alb)[keep]
        kind_a = kind_all[keep]
        xy_a = xy_a[keep]
        z0 = w.terrain.height(xy_a) - 0.05
        cars, peds = kind_a != _PEDESTRIAN, kind_a == _PEDESTRIAN
        return Mesh.concat(
            [
                instances(
                    template("car"),
                    xy_a[cars],
                    yaw_a[cars],
                    size_a[cars],
                    z0[cars],
                    [MAT["car"], MAT["car"]],
                    np.column_stack([alb_a[cars], alb_a[cars] * 0.5]),
                ),
                instances(
                    template("person"),
                    xy_a[peds],
                    yaw_a[peds],
                    size_a[peds],
                    z0[peds],
                    [MAT["person"], MAT["person"]],
                    alb_a[peds],
                ),
            ]
        )


def _car_albedo(rng: np.random.Generator, shape) -> np.ndarray:
    """Paint: many dark and grey cars (weak returns), some white or bright ones."""
    base = rng.choice([0.08, 0.18, 0.32, 0.55], size=shape, p=[0.3, 0.3, 0.25, 0.15])
    return np.clip(base * rng.uniform(0.8, 1.2, shape), 0.03, 0.9)
