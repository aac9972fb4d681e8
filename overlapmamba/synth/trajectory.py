"""Driving: a route along the streets with planned revisits, then a smooth 10 Hz trajectory.

Route planning explores the least-driven streets and, every few hundred metres, returns to a
stretch driven earlier: in the same or the opposite direction (the opposite share is kept at
``reverse_share``), some of them long after the first visit. Paths never U-turn: shortest
paths run over (node, arrived-from) states.

Each leg is moved into the right-hand lane (so opposite-direction visits are a lane apart,
≈3 m), the corners are then rounded into realistic turns, a slow lateral wander is added,
and the path is driven
with a speed profile limited by cruise speed, lateral acceleration in turns and
acceleration/braking. The vehicle sits on the terrain and pitches and rolls with it.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field
from itertools import pairwise
from typing import ClassVar

import numpy as np
from pydantic import ConfigDict
from scipy import ndimage

from overlapmamba.core.configs import Config
from overlapmamba.synth.mounting import tilt_matrix
from overlapmamba.synth.streets import StreetNetwork
from overlapmamba.synth.terrain import Terrain


class DriveParams(Config):
    model_config = ConfigDict(frozen=True)
    config_name: ClassVar[str] = "DriveParams"

    rate_hz: float = 10.0  # scans per second
    mount_height: float = 1.73  # sensor above the road (KITTI)
    mount_pitch_deg: float = 0.0  # the sensor's tilt (overlapmamba.synth.mounting)
    mount_roll_deg: float = 0.0
    v_min: float = 5.0  # m/s
    v_max: float = 15.0
    a_lat: float = 2.5  # m/s², limits speed in turns
    a_acc: float = 1.2
    a_dec: float = 2.0
    lane_offset: float = 1.45  # lane centre right of the street centreline (m)
    lane_wander: float = 0.25  # std of the slow lateral wander within the lane (m)
    turn_smoothing: float = 7.0  # Gaussian σ (m) that rounds the route's corners
    max_turn_deg: float = 110.0  # sharper turns (into acute intersections) are not planned
    revisit_every: tuple[float, float] = (200.0, 450.0)  # metres of exploring between revisits
    revisit_min_age: float = 250.0  # a revisited stretch was driven at least this long ago (m)
    old_age: float = 1500.0  # "old" revisits (> ~1000 frames later) are at least this old (m)
    old_share: float = 0.4
    reverse_share: float = 0.5


@dataclass
class Drive:
    """poses: (N, 4, 4) sensor→world at frame times; dense: the continuous trajectory
    (time, x, y, yaw) at 0.5 m spacing, for poses at any instant inside a sweep."""

    poses: np.ndarray
    times: np.ndarray  # (N,) s
    speed: np.ndarray  # (N,) m/s
    dense_t: np.ndarray
    dense_xy: np.ndarray
    dense_yaw: np.ndarray
    terrain: Terrain
    mount_height: float
    route: list[int] = field(default_factory=list)
    revisits: list[dict] = field(default_factory=list)
    mount_tilt: np.ndarray | None = None  # (3, 3) platform ← sensor; None: level

    def pose_at(self, t: np.ndarray) -> np.ndarray:
        """(M,) times → (M, 4, 4) sensor→world poses (the mounting's tilt included)."""
        t = np.asarray(t, np.float64)
        x = np.interp(t, self.dense_t, self.dense_xy[:, 0])
        y = np.interp(t, self.dense_t, self.dense_xy[:, 1])
        yaw = np.interp(t, self.dense_t, self.dense_yaw)
        poses = vehicle_pose(np.column_stack([x, y]), yaw, self.terrain, self.mount_height)
        if self.mount_tilt is not None:
            poses[:, :3, :3] = poses[:, :3, :3] @ self.mount_tilt
        return poses


def driven_streets(net: StreetNetwork, drive: Drive) -> np.ndarray:
    """Indices of the streets the drive's scans lie on: the route's legs up to the distance
    driven by the last scan (the route is planned a little longer than it is driven)."""
    xy = drive.poses[:, :2, 3]
    driven = float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum())
    legs = [net.street_between(a, b) for a, b in pairwise(drive.route)]
    start = np.concatenate([[0.0], np.cumsum([net.streets[k].length for k in legs])])[:-1]
    return np.unique([k for k, s0 in zip(legs, start, strict=True) if s0 < driven])


def vehicle_pose(xy: np.ndarray, yaw: np.ndarray, terrain: Terrain, mount: float) -> np.ndarray:
    """Sensor poses on the terrain: yaw from the path, pitch and roll from the slope."""
    g = terrain.gradient(xy)
    c, s = np.cos(yaw), np.sin(yaw)
    pitch = -np.arctan(g[:, 0] * c + g[:, 1] * s)  # nose up when climbing
    roll = np.arctan(-g[:, 0] * s + g[:, 1] * c)  # left side up when the ground rises left
    cp, sp, cr, sr = np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    R = np.zeros((len(xy), 3, 3))
    # R = Rz(yaw) · Ry(pitch) · Rx(roll)
    R[:, 0] = np.column_stack([c * cp, c * sp * sr - s * cr, c * sp * cr + s * sr])
    R[:, 1] = np.column_stack([s * cp, s * sp * sr + c * cr, s * sp * cr - c * sr])
    R[:, 2] = np.column_stack([-sp, cp * sr, cp * cr])
    T = np.tile(np.eye(4), (len(xy), 1, 1))
    T[:, :3, :3] = R
    T[:, :2, 3] = xy
    T[:, 2, 3] = terrain.height(xy) + mount
    return T


def _can_turn(net: StreetNetwork, prev: int | None, cur: int, nxt: int, max_turn: float) -> bool:
    return prev is None or (nxt != prev and net.turn_deg(prev, cur, nxt) <= max_turn)


def _shortest(
    net: StreetNetwork,
    cur: int,
    prev: int | None,
    goal: int,
    not_from: int,
    max_turn: float = 180.0,
    detour: np.ndarray | None = None,
) -> list[int] | None:
    """Nodes after ``cur`` up to ``goal`` without U-turns, not arriving at goal from
    ``not_from`` (so the stretch that follows does not start with a U-turn either).
    ``detour``: per-street factors on the length (streets to avoid cost more)."""
    if cur == goal and prev != not_from and _can_turn(net, prev, cur, not_from, max_turn):
        return []
    start = (cur, prev)
    dist = {start: 0.0}
    back: dict[tuple, tuple] = {}
    heap = [(0.0, cur, -1 if prev is None else prev)]
    while heap:
        d, node, came = heapq.heappop(heap)
        state = (node, None if came == -1 else came)
        if d > dist.get(state, np.inf):
            continue
        if (
            node == goal
            and came != not_from
            and state != start
            and _can_turn(net, None if came == -1 else came, node, not_from, max_turn)
        ):
            path = [node]
            while back.get(state) and back[state] != start:
                state = back[state]
                path.append(state[0])
            return path[::-1]
        for nbr, k in net.adjacency[node]:
            if nbr == came or not _can_turn(net, None if came == -1 else came, node, nbr, max_turn):
                continue
            nxt = (nbr, node)
            nd = d + net.streets[k].length * (1.0 if detour is None else detour[k])
            if nd < dist.get(nxt, np.inf):
                dist[nxt] = nd
                back[nxt] = state
                heapq.heappush(heap, (nd, nbr, node))
    return None


def _path_length(net: StreetNetwork, nodes: list[int]) -> float:
    return sum(net.streets[net.street_between(a, b)].length for a, b in pairwise(nodes))


def _toward_undriven(
    net: StreetNetwork,
    visits: np.ndarray,
    cur: int,
    prev: int | None,
    max_turn: float,
    detour: np.ndarray | None = None,
) -> list[int]:
    """Nodes leading to and through the nearest street never driven (empty if none is)."""
    undriven = np.nonzero(visits == 0)[0]
    if not len(undriven):
        return []
    here = net.nodes[cur]
    mids = np.array([net.streets[k].points[len(net.streets[k].points) // 2] for k in undriven])
    for k in undriven[np.argsort(np.linalg.norm(mids - here, axis=1))][:5]:
        st = net.streets[k]
        a, b = (
            (st.u, st.v)
            if np.linalg.norm(net.nodes[st.u] - here) <= np.linalg.norm(net.nodes[st.v] - here)
            else (st.v, st.u)
        )
        path = _shortest(net, cur, prev, a, b, max_turn, detour)
        if path is not None:
            return [*path, b]
    return []


def plan_route(
    net: StreetNetwork,
    rng: np.random.Generator,
    length: float,
    p: DriveParams,
    streets: np.ndarray | None = None,
):
    """Node sequence of about ``length`` metres, and the planned revisits.

    ``streets``: street indices to keep to (a later session re-driving the streets of the
    first, in its own order and directions); the others count as driven from the start, so
    exploring never picks them and takes them only where the network forces a detour."""
    degree = {n: len(v) for n, v in net.adjacency.items()}
    visits = np.zeros(len(net.streets))
    detour = None
    if streets is None:
        nodes = list(degree)
    else:
        visits[:] = 100.0  # as if driven 100 times: the last choice of a random turn
        visits[streets] = 0.0
        detour = np.full(len(net.streets), 20.0)  # paths leave the streets only if they must
        detour[streets] = 1.0
        nodes = sorted({n for k in streets for n in (net.streets[k].u, net.streets[k].v)})
    starts = [n for n in nodes if degree[n] >= 3] or nodes
    cur, prev = int(rng.choice(starts)), None
    route = [cur]
    legs: list[tuple[int, int, float]] = []  # (from, to, metres driven before this leg)
    driven = 0.0
    next_revisit = rng.uniform(*p.revisit_every)
    revisits: list[dict] = []
    n_reversed = 0

    def drive_to(nxt: int) -> None:
        nonlocal cur, prev, driven
        k = net.street_between(cur, nxt)
        legs.append((cur, nxt, driven))
        visits[k] += 1
        driven += net.streets[k].length
        prev, cur = cur, nxt
        route.append(nxt)

    while driven < length:
        if streets is not None and visits[streets].min() > 0:
            visits[streets] -= visits[streets].min()  # a lap done: the least driven are fresh
        if driven >= next_revisit:
            ages = np.array([driven - leg[2] for leg in legs[:-2]])
            old = np.nonzero(ages >= p.old_age)[0]
            ok = np.nonzero(ages >= p.revisit_min_age)[0]
            pool = old if len(old) and rng.random() < p.old_share else ok
            if len(pool):
                # Of a few candidate stretches, drive to the one with the cheapest path back:
                # the detour costs driving that could explore.
                reverse = n_reversed < p.reverse_share * (len(revisits) + 1)
                best = None
                for i in rng.choice(pool, size=min(6, len(pool)), replace=False):
                    n_legs = int(rng.integers(2, 4))
                    stretch = [legs[i][0]] + [leg[1] for leg in legs[i : i + n_legs]]
                    if reverse:
                        stretch = stretch[::-1]
                    path = _shortest(net, cur, prev, stretch[0], stretch[1], p.max_turn_deg, detour)
                    if path is not None:
                        cost = _path_length(net, [cur, *path])
                        if best is None or cost < best[0]:
                            best = (cost, int(i), stretch, path)
                if best is None:  # nothing reachable from here: try after the next street
                    next_revisit = driven
                else:
                    _, i, stretch, path = best
                    for nxt in path:
                        drive_to(nxt)
                    start = driven
                    for nxt in stretch[1:]:
                        drive_to(nxt)
                    revisits.append(
                        {
                            "age_m": float(ages[i]),
                            "reversed": bool(reverse),
                            "legs": len(stretch) - 1,
                            "start_m": start,
                            "end_m": driven,
                        }
                    )
                    n_reversed += int(reverse)
                    # Explore again before the next revisit: counted from where this one ended.
                    next_revisit = driven + rng.uniform(*p.revisit_every)
                    continue
        options = [
            (n, k) for n, k in net.adjacency[cur] if _can_turn(net, prev, cur, n, p.max_turn_deg)
        ] or [(n, k) for n, k in net.adjacency[cur] if n != prev]
        fresh = [o for o in options if visits[o[1]] == 0]
        if fresh:
            drive_to(fresh[int(rng.integers(len(fresh)))][0])
            continue
        frontier = _toward_undriven(net, visits, cur, prev, p.max_turn_deg, detour)
        if frontier:
            for nxt in frontier:
                drive_to(nxt)
            continue
        w = np.array([1.0 / (1.0 + visits[k]) ** 2 for _, k in options])
        drive_to(options[int(rng.choice(len(options), p=w / w.sum()))][0])
    return route, revisits


def plan_drive(
    net: StreetNetwork,
    terrain: Terrain,
    rng: np.random.Generator,
    frames: int,
    p: DriveParams,
    streets: np.ndarray | None = None,
) -> Drive:
    """``frames`` scans' drive; ``streets``: keep to these (see ``plan_route``)."""
    duration = (frames + 1) / p.rate_hz
    route, revisits = plan_route(net, rng, duration * p.v_max * 1.05 + 50.0, p, streets)

    # The route in the right-hand lane, leg by leg, with each sample's cruise speed. Legs are
    # offset *before* the corners are rounded: offsetting a rounded acute turn towards its
    # inside would fold the path into a cusp where the offset exceeds the turn's radius.
    pts, cruise = [], []
    for a, b in pairwise(route):
        st = net.streets[net.street_between(a, b)]
        poly = st.oriented(a)
        d = np.diff(poly, axis=0)
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
        right = np.column_stack([d[:, 1], -d[:, 0]])
        pts.append(poly[:-1] + right * p.lane_offset)
        cruise.append(np.full(len(poly) - 1, st.cruise))
    lane = np.concatenate(pts)
    cruise_raw = np.concatenate(cruise)
    step = 0.5
    seg = np.linalg.norm(np.diff(lane, axis=0), axis=1)
    s_raw = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.arange(0.0, s_raw[-1], step)
    xy = np.column_stack([np.interp(s, s_raw, lane[:, 0]), np.interp(s, s_raw, lane[:, 1])])
    v_cruise = np.interp(s, s_raw, cruise_raw)

    # Round the corners, then wander slowly within the lane.
    xy = ndimage.gaussian_filter1d(xy, p.turn_smoothing / step, axis=0, mode="nearest")
    tan = np.gradient(xy, axis=0)
    tan /= np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-9)
    right = np.column_stack([tan[:, 1], -tan[:, 0]])
    wander = ndimage.gaussian_filter1d(rng.normal(0, 1, len(s)), 30.0 / step, mode="wrap")
    wander *= p.lane_wander / max(wander.std(), 1e-9)
    xy = xy + right * np.clip(wander, -2 * p.lane_wander, 2 * p.lane_wander)[:, None]

    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    yaw = np.unwrap(np.arctan2(np.gradient(xy[:, 1]), np.gradient(xy[:, 0])))
    kappa = np.abs(np.gradient(yaw) / np.maximum(np.gradient(s), 1e-6))
    v = np.minimum(
        ndimage.gaussian_filter1d(v_cruise, 20.0 / step), np.sqrt(p.a_lat / np.maximum(kappa, 1e-6))
    )
    v = np.clip(v, p.v_min, p.v_max)
    ds = np.diff(s)
    for i in range(1, len(v)):  # accelerate
        v[i] = min(v[i], np.sqrt(v[i - 1] ** 2 + 2 * p.a_acc * ds[i - 1]))
    for i in range(len(v) - 2, -1, -1):  # brake
        v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * p.a_dec * ds[i]))
    t = np.concatenate([[0.0], np.cumsum(ds / ((v[1:] + v[:-1]) / 2))])

    # Start half a sweep in, so the first scan's sweep lies on the path too.
    times = 0.5 / p.rate_hz + np.arange(frames) / p.rate_hz
    if t[-1] < times[-1] + 1.0 / p.rate_hz:
        raise RuntimeError("planned route too short for the requested frames")  # cannot happen
    drive = Drive(
        poses=np.zeros((0, 4, 4)),
        times=times,
        speed=np.interp(times, t, v),
        dense_t=t,
        dense_xy=xy,
        dense_yaw=yaw,
        terrain=terrain,
        mount_height=p.mount_height,
        route=route,
        revisits=revisits,
        mount_tilt=tilt_matrix(p.mount_pitch_deg, p.mount_roll_deg),
    )
    drive.poses = drive.pose_at(times)
    return drive
