"""Registration of a query scan against a keyframe's compact geometry
(:mod:`overlapmamba.core.geometry`) with small_gicp, seeded by the descriptor's yaw: the pose
and fit that verification (:mod:`overlapmamba.service.verify`) judges.

    query points ─ prepare (once per query, while the encoder works): every ``stride``-th
                   point, voxel grid, normals and covariances, which grid points lie on
                   steep surfaces, GICP's thinned source (``thinned``)
    keyframe blob ─ decode (the grid its scan was prepared on: ``keyframe_geometry``), k-d
                   tree, covariances, bird's-eye spectrum — cached for the 64 latest
    seed         ─ rotation by −yaw (the descriptor's relative yaw), then the (x, y) shift
                   that best overlays the two bird's-eye grids of steep points (FFT
                   cross-correlation, ``seed_translation``): a revisit passes the place
                   metres away from where the keyframe was taken
    GICP from the seed
    → relative_pose T_keyframe←query (4 × 4, maps query points into the keyframe's frame),
      fitness (share of the query's steep grid points — walls, poles, trunks; the ground
      fits anywhere — with a keyframe point within ``radius`` after alignment; a query with
      fewer than ``min_points / 2`` steep points is refused), rmse (of those distances),
      iterations, converged

On the validation town, the translation seed cut the true loops that GICP failed to reach
from 25 % to 8 % of the candidates, and scoring steep points instead of all separated right
from wrong candidates better (``benchmarks/verify_threshold.py``).

A registration that does not converge within ``max_iterations`` stops there (bounded time);
a query or keyframe too sparse to register is refused with the reason, never an exception.
With a ``screen`` (:func:`register`), GICP runs only when the seed pose already leaves that
share of the query's scored points within its reach (``max_correspondence``).
**Cost and accuracy** (KITTI 00, turned odd frames against even ones,
``benchmarks/registration.py``; this 2-core machine, medians): ≈ 1,000 grid points a side
on the 2 m grid, ≈ 600 in GICP's source; ≈ 4 ms to prepare a query; per candidate, when
its keyframe is cached, ≈ 1.3 ms: GICP 0.7 (2 threads, 3–4 iterations), the seed 0.35,
the fitness search 0.17; errors 5 cm / 0.03°. A 1 m grid gave 1.6 cm / 0.02° at ≈ 10 ms
per candidate. The query is thinned to every 4th point before its grid is made: the
grid's cells are still filled, at a quarter of the work. GICP moves a thinned copy of the
query (``thinned``: −45 % of its time at the same pose error) on 2 threads (−20 to −35 %)
and stops at 5 mm / 0.2° steps (an iteration less than small_gicp's defaults, the same
error). The seed's FFT is single precision, 90 cells a side: the smallest free of
wrap-around within ``max_shift``.

**One thread under load.** GICP on 2 threads is the faster alone, but the service registers
while its other cores encode: an OpenMP region then waits for a thread the encoder holds,
and small_gicp keeps Python's lock while it waits, which stalls the event loop and every
other request's Python work. So the service registers on one thread (``verify.threads``):
with encoder lanes on 2 cores, a fleet got as many observations a second or more, and the
verify stage took less time a query (``python benchmarks/fleet_views.py``, the shipped file
against GICP on 2 threads: ``reports/client/fleet-lanes.json``). small_gicp holds the lock
for every call, not only while it waits: the service runs all of this module in a child
process by default (:mod:`overlapmamba.service.registrar`, ``verify.processes``).
"""

from __future__ import annotations

import dataclasses
import functools
import time
from dataclasses import dataclass, field

import numpy as np
import small_gicp

from overlapmamba.core.geometry import GeometryError, decode_geometry, pack_geometry
from overlapmamba.core.poses import rotation_z
from overlapmamba.service.seed import BevGrid, bev_spectrum, seed_translation
from overlapmamba.service.sensors import FieldOfView


@dataclass(frozen=True)
class RegistrationParams:
    voxel: float = 2.0  # m: the query's grid (the keyframe's comes with its blob)
    stride: int = 4  # every stride-th query point goes into the query's grid
    neighbours: int = 6  # points per covariance
    max_correspondence: float = 2.0  # m: pairs farther apart are ignored
    max_iterations: int = 30
    # GICP has converged when a step moves less than these: 5 mm and 0.2° (small_gicp's
    # defaults, 1 mm and 0.1°, cost an iteration more for the same pose error on KITTI 00)
    translation_eps: float = 5e-3
    rotation_eps_deg: float = 0.2
    radius: float = 1.0  # m: fitness counts query points with a neighbour this close
    min_points: int = 50  # grid points each side needs
    threads: int = 1  # GICP's (OpenMP; the service's verify.threads); preparing a side uses 1
    ground_stride: int = 3  # GICP's source: every steep grid point, every 3rd of the others
    bev_cell: float = 2.0  # m: the bird's-eye grids that seed the translation
    max_shift: float = 40.0  # m: the farthest translation the seed looks for
    bev_reach: float = 64.0  # m: the grids' half-width (structure farther out is left out)

    @property
    def bev(self) -> BevGrid:
        """The translation seed's grid (:mod:`overlapmamba.service.seed`)."""
        return BevGrid(self.bev_cell, self.max_shift, self.bev_reach)


@dataclass(frozen=True)
class Prepared:
    cloud: small_gicp.PointCloud | None  # the grid (what a keyframe keeps)
    size: int
    reason: str | None  # why the query cannot be registered, when it cannot
    steep: np.ndarray | None = None  # (size,) bool: grid points on steep surfaces (with cloud)
    source: small_gicp.PointCloud | None = None  # what GICP moves: ``thinned`` (with cloud)
    scored: np.ndarray | None = None  # (M, 3): the points fitness scores (with cloud)
    # the steep points' bird's-eye spectra, turned by a seed yaw (whole degrees): a query's
    # candidates are mostly keyframes of one pass, whose yaws round alike
    spectra: dict[int, np.ndarray] = field(default_factory=dict, compare=False, repr=False)

    def turned_spectrum(self, yaw_deg: float | None, p: RegistrationParams) -> np.ndarray | None:
        """``bev_spectrum`` of the steep points turned by −yaw (the seed's rotation) rounded
        to a degree (at 64 m half a degree moves a point 0.56 m, within one 2 m cell);
        None when fewer than 3 points are steep."""
        if self.cloud is None or self.steep is None or self.steep.sum() < 3:
            return None
        key = round(yaw_deg or 0.0) % 360
        if key not in self.spectra:
            pts = self.cloud.points()[self.steep, :3] @ rotation_z(-key)[:3, :3].T
            self.spectra[key] = bev_spectrum(pts, p.bev)
        return self.spectra[key]


@dataclass(frozen=True)
class Registration:
    relative_pose: np.ndarray | None  # (4, 4) T_keyframe←query
    fitness: float | None
    rmse: float | None
    iterations: int
    converged: bool
    reason: str | None  # why there is no pose, when there is none
    ms: float
    reach: float | None = None  # share within GICP's reach at the seed (``register``'s screen)
    # how well the geometry pins the translation: the smallest over the largest eigenvalue
    # of the translation block of GICP's final Hessian (:func:`constraint`); None where GICP
    # did not run (a screened seed)
    constraint: float | None = None
    # GICP's final 6 × 6 Hessian (rotation, translation) and its cost per inlier pair: the
    # pose's covariance up to a scale (overlapmamba.core.posecov); None where GICP did not run
    hessian: np.ndarray | None = field(default=None, compare=False, repr=False)
    residual: float | None = None


def constraint(hessian: np.ndarray) -> float:
    """How well a registration's geometry pins its translation in every direction: the
    smallest eigenvalue of the translation block of GICP's final 6 × 6 Hessian (small_gicp
    orders it rotation, translation) over its largest. Near 0: a direction along which the
    scans slide without cost (a corridor, a road cut, a tunnel), where fitness stays high
    at a wrong position."""
    w = np.linalg.eigvalsh(np.asarray(hessian, dtype=np.float64)[3:, 3:])
    return float(w[0] / w[-1]) if w[-1] > 0 else 0.0


# points farther than this (m) are no sensor's returns: left out of registration
FAR_M = 10_000.0


def prepare(xyz: np.ndarray, p: RegistrationParams) -> Prepared:
    """The query's side, once per query: its voxel grid with covariances."""
    pts = np.asarray(xyz[:: max(1, p.stride), :3], dtype=np.float64)
    with np.errstate(invalid="ignore"):  # the common case checks in one flat pass
        ok = np.isfinite(pts).all() and (len(pts) == 0 or float(np.abs(pts).max()) < FAR_M)
    if not ok:  # beyond any sensor's reach small_gicp's voxel keys overflow, one log line each
        with np.errstate(invalid="ignore"):
            pts = pts[np.isfinite(pts).all(axis=1) & (np.abs(pts).max(axis=1) < FAR_M)]
    cloud = small_gicp.voxelgrid_sampling(pts, p.voxel, 1)
    if cloud.size() < p.min_points:
        return Prepared(
            None,
            cloud.size(),
            f"the scan fills {cloud.size()} voxels of {p.voxel:g} m; registration needs at "
            f"least {p.min_points}",
        )
    tree = small_gicp.KdTree(cloud, num_threads=1)
    small_gicp.estimate_normals_covariances(cloud, tree, p.neighbours, 1)
    steep = structure(cloud)
    if steep.sum() < p.min_points // 2:
        # ground fits anywhere: scored on it, two unrelated scans of open ground "verified"
        # at any x, y and yaw where no ambiguity margin was set
        return Prepared(
            None,
            cloud.size(),
            f"the scan has {int(steep.sum())} of its {cloud.size()} voxels on steep surfaces "
            f"(walls, poles, trunks); a pose needs at least {p.min_points // 2}: open ground "
            "fits any",
        )
    grid = cloud.points()[:, :3]
    # ground fits anywhere: fitness scores the structure
    scored = grid[steep]
    return Prepared(cloud, cloud.size(), None, steep, thinned(cloud, steep, p), scored)


def thinned(
    cloud: small_gicp.PointCloud, steep: np.ndarray, p: RegistrationParams
) -> small_gicp.PointCloud:
    """GICP's source: every steep grid point and every ``ground_stride``-th of the others,
    with covariances of its own. The ground's few constraints (height, roll, pitch) need
    few points; the walls and poles carry the rest. On KITTI 00 a third of the ground cut
    GICP's time by ≈ 45 % at the same pose error (``benchmarks/registration.py``)."""
    if p.ground_stride <= 1:
        return cloud
    keep = steep.copy()
    keep[np.flatnonzero(~steep)[:: p.ground_stride]] = True
    if keep.sum() < p.min_points:  # a sparse scan keeps all it has
        return cloud
    source = small_gicp.PointCloud(cloud.points()[keep, :3])
    tree = small_gicp.KdTree(source, num_threads=1)
    small_gicp.estimate_normals_covariances(source, tree, p.neighbours, 1)
    return source


def keyframe_geometry(query: Prepared, p: RegistrationParams) -> bytes | None:
    """What a keyframe keeps of a scan: the grid its registration side was prepared on
    (``None`` when the scan was too sparse for one)."""
    if query.cloud is None:
        return None
    return pack_geometry(query.cloud.points()[:, :3], voxel=p.voxel)


def register(
    query: Prepared,
    geometry: bytes,
    yaw_deg: float | None,
    p: RegistrationParams,
    view: FieldOfView | None = None,
    screen: float | None = None,
) -> Registration:
    """Align the prepared query to one keyframe's geometry (see the module notes).
    ``view``: the keyframe's sensor's field of view, when it is another sensor than the
    query's: fitness then scores only the query's points inside it. ``screen``: GICP runs
    only when, at the seed pose, at least this share of the scored points have a keyframe
    point within its reach (``max_correspondence``; the registration's ``reach``), else the
    seed pose is the answer, with 0 iterations (:func:`rival_fitness`)."""
    t0 = time.perf_counter()

    def refused(reason: str) -> Registration:
        return Registration(None, None, None, 0, False, reason, (time.perf_counter() - t0) * 1e3)

    if query.cloud is None or query.source is None or query.scored is None:
        return refused(query.reason or "the query could not be prepared")
    try:
        target = _target(geometry, p)
    except GeometryError as err:
        return refused(f"the keyframe's geometry is unreadable: {err}")
    if target.cloud is None:
        return refused(
            f"the keyframe keeps {target.size} points; registration needs at least {p.min_points}"
        )
    init = rotation_z(-yaw_deg) if yaw_deg is not None else np.eye(4)
    turned = query.turned_spectrum(yaw_deg, p)
    if turned is not None:
        init[:2, 3] = seed_translation(turned, target.spectrum, p.bev)
    tree = target.tree
    assert tree is not None  # a target with a cloud has its tree
    reach = None
    if screen is not None:
        d2 = _distances(query, tree, init, p, view)
        if isinstance(d2, str):
            return refused(d2)
        reach = float((d2 <= p.max_correspondence**2).mean())
        if reach < screen:
            return _scored(init, d2, p, 0, False, reach, t0)
    res = small_gicp.align(
        target.cloud,
        query.source,
        tree,
        init,
        registration_type="GICP",
        max_correspondence_distance=p.max_correspondence,
        num_threads=p.threads,
        max_iterations=p.max_iterations,
        translation_epsilon=p.translation_eps,
        rotation_epsilon=np.deg2rad(p.rotation_eps_deg),
    )
    T = np.asarray(res.T_target_source, dtype=np.float64)
    d2 = _distances(query, tree, T, p, view)
    if isinstance(d2, str):
        return refused(d2)
    scored = _scored(T, d2, p, int(res.iterations), bool(res.converged), reach, t0)
    return dataclasses.replace(
        scored,
        constraint=constraint(res.H),
        hessian=np.array(res.H, dtype=np.float64),
        residual=float(res.error) / max(1, int(res.num_inliers)),
    )


def _distances(
    query: Prepared,
    tree: small_gicp.KdTree,
    T: np.ndarray,
    p: RegistrationParams,
    view: FieldOfView | None,
) -> np.ndarray | str:
    """Squared distances from the query's scored points, moved by ``T``, to their nearest
    keyframe points (only those inside ``view`` when given); a refusal's reason when too
    few are inside it."""
    assert query.scored is not None  # a prepared query with a cloud has its scored points
    moved = query.scored @ T[:3, :3].T + T[:3, 3]
    if view is not None:
        seen = view.inside(moved)
        if seen.sum() < p.min_points // 2:
            return (
                f"{int(seen.sum())} of the query's points lie in the keyframe sensor's field "
                f"of view; fitness needs at least {p.min_points // 2}"
            )
        moved = moved[seen]
    _, sq = tree.batch_nearest_neighbor_search(moved, 1)
    return np.asarray(sq, dtype=np.float64)


def _scored(
    T: np.ndarray,
    d2: np.ndarray,
    p: RegistrationParams,
    iterations: int,
    converged: bool,
    reach: float | None,
    t0: float,
) -> Registration:
    close = d2 <= p.radius**2
    rmse = float(np.sqrt(d2[close].mean())) if close.any() else None
    ms = (time.perf_counter() - t0) * 1e3
    return Registration(T, float(close.mean()), rmse, iterations, converged, None, ms, reach)


def structure(cloud: small_gicp.PointCloud) -> np.ndarray:
    """(N,) bool: grid points on steep surfaces (walls, poles, trunks), not ground or roofs:
    those whose neighbourhood spreads vertically — the covariance's z variance is at least
    a fifth of its trace (a horizontal patch has almost none; a wall about half; a pole
    nearly all). small_gicp regularises each covariance to a plane's, V·diag(ε, 1, 1)·Vᵀ
    with ε = 1e-3 along the normal n, so its z variance is 1 − (1 − ε)·n_z² and its trace
    2 + ε: the test reads the normals (``estimate_normals_covariances``) and needs no
    covariance matrices copied out (0.7 ms a cloud)."""
    nz2 = np.asarray(cloud.normals(), dtype=np.float64)[:, 2] ** 2
    eps = 1e-3
    return 1.0 - (1.0 - eps) * nz2 >= 0.2 * (2.0 + eps)


@dataclass(frozen=True)
class _Target:
    """A keyframe's side of registration, built once from its blob."""

    size: int
    cloud: small_gicp.PointCloud | None  # None: too few points
    tree: small_gicp.KdTree | None
    spectrum: np.ndarray  # its steep points' bird's-eye grid, as seed_translation takes it


@functools.lru_cache(maxsize=64)
def _target(geometry: bytes, p: RegistrationParams) -> _Target:
    """Decode, k-d tree, covariances, bird's-eye spectrum — kept for the 64 keyframes
    registered last (≈ 0.4 MB each): a robot's consecutive queries meet the same keyframes.
    Raises GeometryError for a blob that cannot be read."""
    pts, _ = decode_geometry(geometry)
    if len(pts) < p.min_points:
        return _Target(len(pts), None, None, np.zeros((0, 0), complex))
    cloud = small_gicp.PointCloud(pts)
    tree = small_gicp.KdTree(cloud, num_threads=1)
    small_gicp.estimate_normals_covariances(cloud, tree, p.neighbours, 1)
    return _Target(len(pts), cloud, tree, bev_spectrum(pts[structure(cloud)], p.bev))
