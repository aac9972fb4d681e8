"""Geometric verification of a place match: register the query scan against a keyframe's
compact geometry (:mod:`lidar_core.geometry`) with small_gicp, seeded by the descriptor's yaw.

    query points ─ prepare (once per query): every ``stride``-th point, voxel grid,
                   covariances
    keyframe blob ─ decode (its own voxel grid), k-d tree, covariances
    GICP from T₀ = rotation by −yaw (the descriptor's relative yaw; the place is the same,
                   so the translation starts at 0)
    → relative_pose T_keyframe←query (4 × 4, maps query points into the keyframe's frame),
      fitness (share of the query's grid points with a keyframe point within ``radius``
      after alignment), rmse (of those distances), iterations, converged

A registration that does not converge within ``max_iterations`` stops there (bounded time);
a query or keyframe too sparse to register is refused with the reason, never an exception.
:func:`verify_candidates` is the query's stage: it prepares the query once, registers each
candidate that has geometry, and judges each result against the calibrated thresholds
(``verify.min_fitness``, ``verify.max_rmse_m``: ``benchmarks/verify_threshold.py``).

**Resolution.** Both sides register on a 2 m grid by default: on KITTI 00 (turned odd frames
against even ones, ``benchmarks/registration.py``) that is ≈ 1,100 points a side, 4.9 ms to
prepare a query and 3.8 ms per candidate on this 2-core machine (medians), with errors of
4.7 cm / 0.03° (median); a 1 m grid gave 1.6 cm / 0.02° at ≈ 10 ms per candidate. The query is
thinned to every 4th point before its grid is made: the grid's cells are still filled, at a
quarter of the work.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import small_gicp

from lidar_core.geometry import GeometryError, decode_geometry
from lidar_core.poses import rotation_z
from service.settings import VerifySettings

NO_GEOMETRY = "the keyframe keeps no geometry (inserted as a descriptor, or its map keeps none)"


@dataclass(frozen=True)
class RegistrationParams:
    voxel: float = 2.0  # m: the query's grid (the keyframe's comes with its blob)
    stride: int = 4  # every stride-th query point goes into the query's grid
    neighbours: int = 6  # points per covariance
    max_correspondence: float = 2.0  # m: pairs farther apart are ignored
    max_iterations: int = 30
    radius: float = 1.0  # m: fitness counts query points with a neighbour this close
    min_points: int = 50  # grid points each side needs
    threads: int = 1


@dataclass(frozen=True)
class Prepared:
    cloud: small_gicp.PointCloud | None
    size: int
    reason: str | None  # why the query cannot be registered, when it cannot


@dataclass(frozen=True)
class Registration:
    relative_pose: np.ndarray | None  # (4, 4) T_keyframe←query
    fitness: float | None
    rmse: float | None
    iterations: int
    converged: bool
    reason: str | None  # why there is no pose, when there is none
    ms: float


def prepare(xyz: np.ndarray, p: RegistrationParams) -> Prepared:
    """The query's side, once per query: its voxel grid with covariances."""
    pts = np.asarray(xyz, dtype=np.float64)[:: max(1, p.stride), :3]
    pts = pts[np.isfinite(pts).all(axis=1)]
    cloud = small_gicp.voxelgrid_sampling(pts, p.voxel, p.threads)
    if cloud.size() < p.min_points:
        return Prepared(
            None,
            cloud.size(),
            f"the scan fills {cloud.size()} voxels of {p.voxel:g} m; registration needs at "
            f"least {p.min_points}",
        )
    tree = small_gicp.KdTree(cloud, num_threads=p.threads)
    small_gicp.estimate_covariances(cloud, tree, p.neighbours, p.threads)
    return Prepared(cloud, cloud.size(), None)


def register(
    query: Prepared, geometry: bytes, yaw_deg: float | None, p: RegistrationParams
) -> Registration:
    """Align the prepared query to one keyframe's geometry (see the module notes)."""
    t0 = time.perf_counter()

    def refused(reason: str) -> Registration:
        return Registration(None, None, None, 0, False, reason, (time.perf_counter() - t0) * 1e3)

    if query.cloud is None:
        return refused(query.reason or "the query could not be prepared")
    try:
        pts, _ = decode_geometry(geometry)
    except GeometryError as err:
        return refused(f"the keyframe's geometry is unreadable: {err}")
    if len(pts) < p.min_points:
        return refused(
            f"the keyframe keeps {len(pts)} points; registration needs at least {p.min_points}"
        )
    target = small_gicp.PointCloud(pts)
    tree = small_gicp.KdTree(target, num_threads=p.threads)
    small_gicp.estimate_covariances(target, tree, p.neighbours, p.threads)
    init = rotation_z(-yaw_deg) if yaw_deg is not None else np.eye(4)
    res = small_gicp.align(
        target,
        query.cloud,
        tree,
        init,
        registration_type="GICP",
        max_correspondence_distance=p.max_correspondence,
        num_threads=p.threads,
        max_iterations=p.max_iterations,
    )
    T = np.asarray(res.T_target_source, dtype=np.float64)
    src = query.cloud.points()[:, :3]
    moved = src @ T[:3, :3].T + T[:3, 3]
    _, sq = tree.batch_nearest_neighbor_search(moved, p.threads)
    d2 = np.asarray(sq, dtype=np.float64)
    close = d2 <= p.radius**2
    fitness = float(close.mean())
    rmse = float(np.sqrt(d2[close].mean())) if close.any() else None
    return Registration(
        T,
        fitness,
        rmse,
        int(res.iterations),
        bool(res.converged),
        None,
        (time.perf_counter() - t0) * 1e3,
    )


@dataclass(frozen=True)
class Verdict:
    """One candidate's verification, as an answer carries it."""

    verified: bool | None  # None: the keyframe has no geometry to register against
    fitness: float | None
    rmse: float | None
    reason: str | None  # why it is not verified, when it is not
    relative_pose: np.ndarray | None  # (4, 4) T_keyframe←query, when registration ran
    ms: float

    def public(self) -> dict[str, object]:
        return {
            "verified": self.verified,
            "fitness": self.fitness,
            "rmse": self.rmse,
            "reason": self.reason,
        }


def params_of(v: VerifySettings) -> RegistrationParams:
    return RegistrationParams(voxel=v.voxel_m, radius=v.radius_m, max_iterations=v.max_iterations)


def judge(reg: Registration, v: VerifySettings) -> Verdict:
    if reg.relative_pose is None or reg.fitness is None:
        return Verdict(False, None, None, reg.reason, None, reg.ms)
    reason = None
    if reg.fitness < v.min_fitness:
        reason = f"fitness {reg.fitness:.3f} is below {v.min_fitness}"
    elif reg.rmse is None or reg.rmse > v.max_rmse_m:
        reason = f"rmse {reg.rmse} m is above {v.max_rmse_m}"
    return Verdict(reason is None, reg.fitness, reg.rmse, reason, reg.relative_pose, reg.ms)


def verify_candidates(
    xyz: np.ndarray, candidates: list[tuple[bytes | None, float | None]], v: VerifySettings
) -> list[Verdict]:
    """The query's points and its candidates (geometry blob or None, the descriptor's
    relative yaw) → one verdict per candidate, in order. The query is prepared only when
    some candidate has geometry."""
    p = params_of(v)
    if all(blob is None for blob, _ in candidates):
        return [Verdict(None, None, None, NO_GEOMETRY, None, 0.0) for _ in candidates]
    query = prepare(xyz, p)
    out = []
    for blob, yaw_deg in candidates:
        if blob is None:
            out.append(Verdict(None, None, None, NO_GEOMETRY, None, 0.0))
        else:
            out.append(judge(register(query, blob, yaw_deg, p), v))
    return out
