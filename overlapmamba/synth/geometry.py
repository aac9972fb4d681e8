"""Triangle soups for the synthetic world: unit templates instanced by numpy.

A :class:`Mesh` is what the ray caster consumes:

    tris:   (F, 3, 3) float32   triangle corners, world metres
    mat:    (F,) uint8          material id (see MATERIALS)
    albedo: (F,) float32        per-face reflectivity in [0, 1]

Templates are unit-sized with their base at z = 0, so one vectorised call places thousands
of buildings, trees or cars: scale → rotate about z → translate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

# name → (id, base reflectivity, probability that a ray passes through a hit face)
# Foliage and chain-link fences are porous to a LiDAR: some rays hit, some reach what is behind.
MATERIALS: dict[str, tuple[int, float, float]] = {
    "asphalt": (0, 0.33, 0.0),
    "grass": (1, 0.36, 0.0),
    "pavement": (2, 0.33, 0.0),
    "facade": (3, 0.30, 0.0),
    "roof": (4, 0.24, 0.0),
    "metal": (5, 0.42, 0.0),
    "foliage": (6, 0.34, 0.35),
    "bark": (7, 0.24, 0.0),
    "pole": (8, 0.40, 0.0),
    "car": (9, 0.30, 0.0),
    "fence": (10, 0.32, 0.55),
    "kerb": (11, 0.36, 0.0),
    "person": (12, 0.22, 0.0),
    "guardrail": (13, 0.60, 0.0),
    "marking": (14, 0.70, 0.0),
    "sign": (15, 0.95, 0.0),
}
MAT = {name: v[0] for name, v in MATERIALS.items()}
REFLECTIVITY = np.array([v[1] for v in sorted(MATERIALS.values())], dtype=np.float32)
TRANSMIT = np.array([v[2] for v in sorted(MATERIALS.values())], dtype=np.float32)


@dataclass
class Mesh:
    tris: np.ndarray
    mat: np.ndarray
    albedo: np.ndarray

    @staticmethod
    def empty() -> Mesh:
        return Mesh(np.zeros((0, 3, 3), np.float32), np.zeros(0, np.uint8), np.zeros(0, np.float32))

    @staticmethod
    def concat(meshes: list[Mesh]) -> Mesh:
        meshes = [m for m in meshes if len(m.tris)]
        if not meshes:
            return Mesh.empty()
        return Mesh(
            np.concatenate([m.tris for m in meshes]).astype(np.float32, copy=False),
            np.concatenate([m.mat for m in meshes]),
            np.concatenate([m.albedo for m in meshes]),
        )

    def __len__(self) -> int:
        return len(self.tris)


@dataclass(frozen=True)
class Template:
    """Unit shape: tris (F, 3, 3) within [-0.5, 0.5]² × [0, 1]; part (F,) index into the
    instance's material list, so one template can carry e.g. walls and a roof."""

    tris: np.ndarray
    part: np.ndarray


def _box_tris() -> np.ndarray:
    c = np.array(
        [[x, y, z] for z in (0.0, 1.0) for y in (-0.5, 0.5) for x in (-0.5, 0.5)], np.float64
    )
    # Outward-facing quads as corner indices (counter-clockwise seen from outside).
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    tris = []
    for a, b, cc, d in quads:
        tris += [(a, b, cc), (a, cc, d)]
    return c[np.array(tris)]


def _cylinder_tris(sides: int = 8) -> np.ndarray:
    a = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    ring = np.column_stack([0.5 * np.cos(a), 0.5 * np.sin(a)])
    tris = []
    for i in range(sides):
        p, q = ring[i], ring[(i + 1) % sides]
        lo_p, lo_q, hi_p, hi_q = [*p, 0], [*q, 0], [*p, 1], [*q, 1]
        tris += [(lo_p, lo_q, hi_q), (lo_p, hi_q, hi_p), ([0, 0, 1], hi_p, hi_q)]
    return np.array(tris, np.float64)


def _ellipsoid_tris() -> np.ndarray:
    """Icosphere (80 faces) squeezed into the unit template box."""
    import trimesh  # only at world-build time

    s = trimesh.creation.icosphere(subdivisions=1, radius=0.5)
    tris = np.array(s.triangles, np.float64)
    tris[..., 2] += 0.5
    return tris


def _gable_roof_tris() -> np.ndarray:
    """A prism: ridge along x at z = 1, eaves at z = 0 along y = ±0.5."""
    a, b = (-0.5, -0.5, 0.0), (0.5, -0.5, 0.0)
    c, d = (0.5, 0.5, 0.0), (-0.5, 0.5, 0.0)
    r0, r1 = (-0.5, 0.0, 1.0), (0.5, 0.0, 1.0)
    return np.array(
        [(a, b, r1), (a, r1, r0), (c, d, r0), (c, r0, r1), (a, r0, d), (b, c, r1)], np.float64
    )


def _stack(parts: list[tuple[np.ndarray, tuple[float, float, float, float, float, float]]]):
    """Combine unit shapes placed at (cx, cy, z0, sx, sy, sz) inside the unit template."""
    tris, part = [], []
    for k, (shape, (cx, cy, z0, sx, sy, sz)) in enumerate(parts):
        t = shape * np.array([sx, sy, sz]) + np.array([cx, cy, z0])
        tris.append(t)
        part.append(np.full(len(t), k, np.int64))
    return Template(np.concatenate(tris), np.concatenate(part))


BOX = Template(_box_tris(), np.zeros(12, np.int64))
CYLINDER = Template(_cylinder_tris(), np.zeros(24, np.int64))
_templates: dict[str, Template] = {}


def template(name: str) -> Template:
    """Lazily built composite templates (parts index the material list given at placement)."""
    if name not in _templates:
        box, roof = _box_tris(), _gable_roof_tris()
        if name == "ellipsoid":
            t = _ellipsoid_tris()
            _templates[name] = Template(t, np.zeros(len(t), np.int64))
        elif name == "gable_house":  # walls (part 0) to 70 % of the height, roof (part 1)
            _templates[name] = _stack([(box, (0, 0, 0, 1, 1, 0.7)), (roof, (0, 0, 0.7, 1, 1, 0.3))])
        elif name == "car":  # body (0) and cabin (1); x is the driving direction
            _templates[name] = _stack(
                [(box, (0, 0, 0.18, 1, 1, 0.5)), (box, (-0.06, 0, 0.68, 0.55, 0.9, 0.32))]
            )
        elif name == "person":  # legs+torso (0), head (1)
            _templates[name] = _stack(
                [(box, (0, 0, 0, 1, 1, 0.86)), (box, (0, 0, 0.86, 0.5, 0.6, 0.14))]
            )
        else:
            raise KeyError(name)
    return _templates[name]


def instances(
    tpl: Template,
    center: ArrayLike,
    yaw: ArrayLike,
    size: ArrayLike,
    z0: ArrayLike,
    materials: list[int] | np.ndarray,
    albedo: ArrayLike,
) -> Mesh:
    """K placed copies of a template.

    center: (K, 2); yaw: (K,) radians; size: (K, 3) length, width, height; z0: (K,) base
    height; materials: per template part, or (K, parts) per instance; albedo: (K,) or
    (K, parts) reflectivity.
    """
    center = np.asarray(center, np.float64).reshape(-1, 2)
    K = len(center)
    if K == 0:
        return Mesh.empty()
    size = np.broadcast_to(np.asarray(size, np.float64), (K, 3))
    yaw = np.broadcast_to(np.asarray(yaw, np.float64), (K,))
    z0 = np.broadcast_to(np.asarray(z0, np.float64), (K,))
    t = tpl.tris[None] * size[:, None, None, :]  # (K, F, 3, 3)
    c, s = np.cos(yaw)[:, None, None], np.sin(yaw)[:, None, None]
    x, y = t[..., 0], t[..., 1]
    out = np.empty_like(t)
    out[..., 0] = c * x - s * y + center[:, 0, None, None]
    out[..., 1] = s * x + c * y + center[:, 1, None, None]
    out[..., 2] = t[..., 2] + z0[:, None, None]
    F = len(tpl.tris)
    mats = np.asarray(materials)
    mats = np.broadcast_to(mats if mats.ndim == 2 else mats[None], (K, mats.shape[-1]))
    alb = np.asarray(albedo, np.float64)
    alb = np.broadcast_to(alb if alb.ndim == 2 else alb[:, None], (K, mats.shape[1]))
    return Mesh(
        out.reshape(K * F, 3, 3).astype(np.float32),
        mats[:, tpl.part].reshape(K * F).astype(np.uint8),
        alb[:, tpl.part].reshape(K * F).astype(np.float32),
    )


def ribbon(
    polyline: np.ndarray, offset: float, width: float, z_low: np.ndarray, height: float
) -> np.ndarray:
    """A wall-like strip (kerb, guard rail, fence, hedge) following a 2-D polyline.

    polyline: (P, 2); the strip's centre runs ``offset`` metres to the left of it; z_low:
    (P,) base heights. Returns (F, 3, 3) float64: a box segment per polyline step.
    """
    p = np.asarray(polyline, np.float64)
    if len(p) < 2:
        return np.zeros((0, 3, 3))
    d = np.gradient(p, axis=0)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    n = np.column_stack([-d[:, 1], d[:, 0]])
    mid = p + n * offset
    lo, hi = mid - n * width / 2, mid + n * width / 2
    z0, z1 = np.asarray(z_low, np.float64), np.asarray(z_low, np.float64) + height
    # Corners per station: (lo, z0) (hi, z0) (hi, z1) (lo, z1)
    ring = np.stack(
        [
            np.column_stack([lo, z0]),
            np.column_stack([hi, z0]),
            np.column_stack([hi, z1]),
            np.column_stack([lo, z1]),
        ],
        axis=1,
    )  # (P, 4, 3)
    a, b = ring[:-1], ring[1:]
    tris = []
    for i in range(4):
        j = (i + 1) % 4
        tris += [np.stack([a[:, i], a[:, j], b[:, j]], 1), np.stack([a[:, i], b[:, j], b[:, i]], 1)]
    return np.concatenate(tris)
