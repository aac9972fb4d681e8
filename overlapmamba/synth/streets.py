"""The street network: a perturbed grid with oblique and curved streets, and its districts.

Nodes start on a grid with varied block sizes and are jittered, so intersections meet at
varied angles. Some grid edges are removed (never leaving a dead end), some cells gain a
diagonal street, and some streets bend (a quadratic Bézier). Every street belongs to the
district at its midpoint; districts are Voronoi cells of a few seeds whose type depends on
the distance from the town centre (dense core, suburban/industrial ring, open outskirts).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

DISTRICTS = ("urban", "suburban", "open", "industrial")

# Street half-width (m) range and cruise speed (m/s) range by district.
HALF_WIDTH = {
    "urban": (5.0, 7.0),
    "suburban": (4.5, 5.5),
    "open": (3.6, 4.2),
    "industrial": (5.0, 6.0),
}
CRUISE = {
    "urban": (7.0, 10.0),
    "suburban": (8.0, 11.0),
    "open": (11.0, 15.0),
    "industrial": (8.0, 12.0),
}


@dataclass
class Street:
    u: int
    v: int
    points: np.ndarray  # (P, 2) polyline from node u to node v, ≈2 m spacing
    half_width: float
    district: str
    cruise: float  # m/s

    @property
    def length(self) -> float:
        return float(np.linalg.norm(np.diff(self.points, axis=0), axis=1).sum())

    def oriented(self, start: int) -> np.ndarray:
        return self.points if start == self.u else self.points[::-1]


@dataclass
class StreetNetwork:
    nodes: np.ndarray  # (N, 2)
    streets: list[Street]
    district_seeds: np.ndarray  # (D, 2)
    district_types: list[str]
    adjacency: dict[int, list[tuple[int, int]]] = field(
        default_factory=dict
    )  # node → (nbr, street)

    def __post_init__(self) -> None:
        self.adjacency = {i: [] for i in range(len(self.nodes))}
        for k, s in enumerate(self.streets):
            self.adjacency[s.u].append((s.v, k))
            self.adjacency[s.v].append((s.u, k))

    def street_between(self, a: int, b: int) -> int:
        """Index of the street joining nodes a and b."""
        for nbr, k in self.adjacency[a]:
            if nbr == b:
                return k
        raise KeyError((a, b))

    def turn_deg(self, a: int, b: int, c: int) -> float:
        """Heading change (degrees) driving a → b → c, from the streets' end tangents."""
        inc = self.streets[self.street_between(a, b)].oriented(a)
        out = self.streets[self.street_between(b, c)].oriented(b)
        d1, d2 = inc[-1] - inc[-3], out[2] - out[0]
        return float(abs(np.degrees(np.arctan2(d1[0] * d2[1] - d1[1] * d2[0], d1 @ d2))))

    def district_at(self, xy: np.ndarray) -> np.ndarray:
        """(M, 2) → (M,) index into DISTRICTS."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        d2 = ((xy[:, None, :] - self.district_seeds[None]) ** 2).sum(-1)
        types = np.array([DISTRICTS.index(t) for t in self.district_types])
        return types[d2.argmin(1)]

    def bounds(self, margin: float) -> tuple[np.ndarray, np.ndarray]:
        pts = np.concatenate([s.points for s in self.streets])
        return pts.min(0) - margin, pts.max(0) + margin


def _bezier(a: np.ndarray, b: np.ndarray, bend: float, step: float = 2.0) -> np.ndarray:
    d = b - a
    length = float(np.linalg.norm(d))
    normal = np.array([-d[1], d[0]]) / max(length, 1e-9)
    ctrl = (a + b) / 2 + normal * bend
    n = max(2, int(np.ceil(length / step)) + 1)
    t = np.linspace(0, 1, n)[:, None]
    return (1 - t) ** 2 * a + 2 * (1 - t) * t * ctrl + t**2 * b


def _connected_without_dead_ends(n: int, edges: set[tuple[int, int]]) -> bool:
    deg = np.zeros(n, int)
    adj: dict[int, list[int]] = {i: [] for i in range(n)}
    for u, v in edges:
        deg[u] += 1
        deg[v] += 1
        adj[u].append(v)
        adj[v].append(u)
    if (deg < 2).any():
        return False
    seen, stack = {0}, [0]
    while stack:
        for w in adj[stack.pop()]:
            if w not in seen:
                seen.add(w)
                stack.append(w)
    return len(seen) == n


def build_streets(
    rng: np.random.Generator,
    nx: int,
    ny: int,
    block: tuple[float, float] = (70.0, 140.0),
    jitter: float = 9.0,
    remove_fraction: float = 0.12,
    diagonal_fraction: float = 0.15,
    curved_fraction: float = 0.3,
    n_districts: int | None = None,
) -> StreetNetwork:
    """A street network on an ``nx × ny`` node grid."""
    xs = np.concatenate([[0.0], np.cumsum(rng.uniform(*block, nx - 1))])
    ys = np.concatenate([[0.0], np.cumsum(rng.uniform(*block, ny - 1))])
    xs -= xs.mean()
    ys -= ys.mean()
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    nodes = np.column_stack([gx.ravel(), gy.ravel()]) + rng.uniform(-jitter, jitter, (nx * ny, 2))

    def nid(i: int, j: int) -> int:
        return i * ny + j

    edges: set[tuple[int, int]] = set()
    for i in range(nx):
        for j in range(ny):
            if i + 1 < nx:
                edges.add((nid(i, j), nid(i + 1, j)))
            if j + 1 < ny:
                edges.add((nid(i, j), nid(i, j + 1)))
    # Remove some streets, keeping the town connected and free of dead ends (no U-turns).
    to_remove = round(remove_fraction * len(edges))
    for e in rng.permutation(np.array(sorted(edges))).tolist():
        if to_remove <= 0:
            break
        trial = edges - {(e[0], e[1])}
        if _connected_without_dead_ends(nx * ny, trial):
            edges = trial
            to_remove -= 1
    # Oblique streets: at most one diagonal per grid cell.
    for i in range(nx - 1):
        for j in range(ny - 1):
            if rng.random() < diagonal_fraction:
                e = (
                    (nid(i, j), nid(i + 1, j + 1))
                    if rng.random() < 0.5
                    else (nid(i + 1, j), nid(i, j + 1))
                )
                edges.add((min(e), max(e)))

    extent = np.abs(nodes).max(0)
    n_districts = n_districts or max(4, (nx * ny) // 5)
    seeds = rng.uniform(-extent, extent, (n_districts, 2))
    radius = np.linalg.norm(seeds / extent, axis=1) / np.sqrt(2)
    types = []
    for r in radius:
        if r < 0.3:
            p = [0.75, 0.1, 0.0, 0.15]
        elif r < 0.6:
            p = [0.2, 0.45, 0.05, 0.3]
        else:
            p = [0.0, 0.35, 0.45, 0.2]
        types.append(DISTRICTS[rng.choice(4, p=p)])
    # Every district type exists in every town: the nearest seeds to fixed rings take the
    # missing types.
    for want in DISTRICTS:
        if want not in types:
            counts = {t: types.count(t) for t in types}
            k = max(range(len(types)), key=lambda i: (counts[types[i]], rng.random()))
            types[k] = want

    net_tmp = StreetNetwork(nodes, [], seeds, types)
    streets = []
    for u, v in sorted(edges):
        a, b = nodes[u], nodes[v]
        district = DISTRICTS[int(net_tmp.district_at(((a + b) / 2)[None])[0])]
        length = float(np.linalg.norm(b - a))
        p_curve = curved_fraction * (2.0 if district == "open" else 1.0)
        bend = rng.normal(0, 0.12 * length) if rng.random() < p_curve else 0.0
        bend = float(np.clip(bend, -0.25 * length, 0.25 * length))
        streets.append(
            Street(
                u,
                v,
                _bezier(a, b, bend),
                float(rng.uniform(*HALF_WIDTH[district])),
                district,
                float(rng.uniform(*CRUISE[district])),
            )
        )
    # A corner with only two streets must be drivable: if curved streets make it sharper
    # than 100°, straighten them (the grid angle stays, ≈90° ± jitter).
    net = StreetNetwork(nodes, streets, seeds, types)
    for node, nbrs in net.adjacency.items():
        if len(nbrs) == 2 and net.turn_deg(nbrs[0][0], node, nbrs[1][0]) > 100.0:
            for _, k in nbrs:
                st = streets[k]
                st.points = _bezier(nodes[st.u], nodes[st.v], 0.0)
    return StreetNetwork(nodes, streets, seeds, types)


def resample(points: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every ``step`` metres along a polyline, and their arc lengths."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.arange(0.0, s[-1] + 1e-9, step)
    return np.column_stack([np.interp(t, s, points[:, 0]), np.interp(t, s, points[:, 1])]), t


def frame_at(points: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position (M, 2) and unit tangent (M, 2) at arc lengths s along a polyline."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    pos = np.column_stack([np.interp(s, cum, points[:, 0]), np.interp(s, cum, points[:, 1])])
    k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    tan = (points[k + 1] - points[k]) / np.maximum(seg[k], 1e-9)[:, None]
    return pos, tan
