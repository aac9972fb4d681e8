"""A small SE(3) pose-graph optimiser for the benchmarks (numpy and scipy.sparse): what a
loop edge's covariance buys a pose graph (``benchmarks/pose_graph.py``).

An edge (a, b, Z, Ω) says T_a⁻¹ · T_b = Z; its error is ``overlapmamba.core.posecov``'s,
e = Log(Z⁻¹ · T_a⁻¹ · T_b) (translation, then the rotation vector; perturbations on the
right), weighted by Ω, the inverse of the covariance the service answers for a closure:
GTSAM's ``BetweenFactor<Pose3>`` with the blocks swapped (``g2o``'s ``EDGE_SE3:QUAT`` with
``posecov.g2o_information`` agrees to first order: its error keeps the quaternion's vector
part, and the relative pose's translation as it is where this takes the SE(3) logarithm's:
``benchmarks/g2o_check.py`` measures the gap). Levenberg–Marquardt on the whole graph, one
vertex held fixed, with the Jacobians J_b = J and J_a = −J · Ad(T_b⁻¹ · T_a), J the inverse
of the right Jacobian at e (by central differences of Log, so the optimum is the exact one
even where an edge is metres off), solved as one sparse system a step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve


def _hat(v: np.ndarray) -> np.ndarray:
    """(n, 3) → (n, 3, 3) skew matrices."""
    z = np.zeros(len(v))
    return np.stack(
        [
            np.stack([z, -v[:, 2], v[:, 1]], -1),
            np.stack([v[:, 2], z, -v[:, 0]], -1),
            np.stack([-v[:, 1], v[:, 0], z], -1),
        ],
        1,
    )


def exp_se3(xi: np.ndarray) -> np.ndarray:
    """(n, 6) twists (translation, rotation vector) → (n, 4, 4) poses."""
    xi = np.atleast_2d(np.asarray(xi, dtype=np.float64))
    rho, phi = xi[:, :3], xi[:, 3:]
    theta = np.linalg.norm(phi, axis=1)[:, None, None]
    k = _hat(phi)
    k2 = k @ k
    small = theta < 1e-8
    t = np.where(small, 1.0, theta)
    a = np.where(small, 1.0, np.sin(t) / t)
    b = np.where(small, 0.5, (1 - np.cos(t)) / t**2)
    c = np.where(small, 1 / 6, (t - np.sin(t)) / t**3)
    eye = np.eye(3)
    out = np.tile(np.eye(4), (len(xi), 1, 1))
    out[:, :3, :3] = eye + a * k + b * k2
    out[:, :3, 3] = ((eye + b * k + c * k2) @ rho[:, :, None])[:, :, 0]
    return out


def log_se3(poses: np.ndarray) -> np.ndarray:
    """(n, 4, 4) poses → (n, 6) twists (translation, rotation vector; angles below π)."""
    r, t = poses[:, :3, :3], poses[:, :3, 3]
    axis = np.stack([r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]], -1)
    s = 0.5 * np.linalg.norm(axis, axis=1)
    c = 0.5 * (np.trace(r, axis1=1, axis2=2) - 1.0)
    theta = np.arctan2(s, c)
    small = theta < 1e-8
    scale = np.where(small, 0.5, theta / (2.0 * np.sin(np.where(small, 1.0, theta))))
    phi = scale[:, None] * axis
    k = _hat(phi)
    th = np.where(small, 1.0, theta)[:, None, None]
    half = 0.5 * th
    b = np.where(small[:, None, None], 1 / 12, (1.0 - half / np.tan(half)) / th**2)
    v_inv = np.eye(3) - 0.5 * k + b * (k @ k)
    rho = (v_inv @ t[:, :, None])[:, :, 0]
    return np.concatenate([rho, phi], 1)


def inverse(poses: np.ndarray) -> np.ndarray:
    """(n, 4, 4) rigid poses inverted."""
    out = np.tile(np.eye(4), (len(poses), 1, 1))
    rt = np.transpose(poses[:, :3, :3], (0, 2, 1))
    out[:, :3, :3] = rt
    out[:, :3, 3] = -(rt @ poses[:, :3, 3, None])[:, :, 0]
    return out


def adjoint(poses: np.ndarray) -> np.ndarray:
    """(n, 4, 4) → (n, 6, 6) adjoints for (translation, rotation) twists."""
    r, t = poses[:, :3, :3], poses[:, :3, 3]
    out = np.zeros((len(poses), 6, 6))
    out[:, :3, :3] = r
    out[:, 3:, 3:] = r
    out[:, :3, 3:] = _hat(t) @ r
    return out


@dataclass
class Edges:
    """m edges: T_a⁻¹ · T_b = Z with information Ω."""

    a: np.ndarray  # (m,) int
    b: np.ndarray  # (m,) int
    z: np.ndarray  # (m, 4, 4)
    info: np.ndarray  # (m, 6, 6)

    @staticmethod
    def join(*parts: Edges) -> Edges:
        return Edges(
            np.concatenate([p.a for p in parts]).astype(int),
            np.concatenate([p.b for p in parts]).astype(int),
            np.concatenate([p.z for p in parts]),
            np.concatenate([p.info for p in parts]),
        )


def errors_of(poses: np.ndarray, edges: Edges) -> np.ndarray:
    """(m, 4, 4) E = Z⁻¹ · T_a⁻¹ · T_b: the identity where an edge holds exactly."""
    return inverse(edges.z) @ inverse(poses[edges.a]) @ poses[edges.b]


def residuals(poses: np.ndarray, edges: Edges) -> np.ndarray:
    """(m, 6) errors e = Log(Z⁻¹ · T_a⁻¹ · T_b)."""
    return log_se3(errors_of(poses, edges))


def log_jacobian(e: np.ndarray, step: float = 1e-6) -> np.ndarray:
    """(m, 6, 6) d Log(E · Exp(ξ)) / dξ at ξ = 0 for each E (m, 4, 4): the inverse of the
    right Jacobian at Log E, by central differences (exact to the step's square; the
    identity at E = I)."""
    out = np.empty((len(e), 6, 6))
    for k in range(6):
        xi = np.zeros((1, 6))
        xi[0, k] = step
        plus = log_se3(e @ exp_se3(xi))
        minus = log_se3(e @ exp_se3(-xi))
        out[:, :, k] = (plus - minus) / (2 * step)
    return out


def cost(poses: np.ndarray, edges: Edges) -> float:
    """½ Σ eᵀ Ω e."""
    e = residuals(poses, edges)
    return 0.5 * float(np.einsum("mi,mij,mj->", e, edges.info, e))


@dataclass
class Solved:
    poses: np.ndarray
    iterations: int
    cost_start: float
    cost: float
    converged: bool


def optimise(
    poses: np.ndarray,
    edges: Edges,
    fixed: int = 0,
    iterations: int = 100,
    tolerance: float = 1e-9,
) -> Solved:
    """Levenberg–Marquardt from ``poses`` (n, 4, 4), vertex ``fixed`` held: the poses that
    minimise :func:`cost`. Stops when a step lowers the cost by less than ``tolerance`` of
    it, or after ``iterations`` steps."""
    n = len(poses)
    if len(edges.a) == 0:
        raise ValueError("a pose graph needs at least one edge")
    if min(edges.a.min(), edges.b.min()) < 0 or max(edges.a.max(), edges.b.max()) >= n:
        raise ValueError(f"an edge names a vertex outside 0 … {n - 1}")
    x = np.array(poses, dtype=np.float64)
    start = current = cost(x, edges)
    lam, done, steps = 1e-4, False, 0
    free = np.ones(n, bool)
    free[fixed] = False
    cols = np.repeat(np.arange(n) * 6, 6) + np.tile(np.arange(6), n)
    keep = cols[np.repeat(free, 6)]
    for steps in range(1, iterations + 1):
        err = errors_of(x, edges)
        e = log_se3(err)
        jb = log_jacobian(err)
        ja = -jb @ adjoint(inverse(x[edges.b]) @ x[edges.a])
        w_e = np.einsum("mij,mj->mi", edges.info, e)
        g = np.zeros((n, 6))
        np.add.at(g, edges.a, np.einsum("mji,mj->mi", ja, w_e))
        np.add.at(g, edges.b, np.einsum("mji,mj->mi", jb, w_e))
        ja_info = np.einsum("mki,mkj->mij", ja, edges.info)  # J_aᵀ Ω
        jb_info = np.einsum("mki,mkj->mij", jb, edges.info)  # J_bᵀ Ω
        ab = ja_info @ jb
        blocks = (
            (edges.a, edges.a, ja_info @ ja),
            (edges.a, edges.b, ab),
            (edges.b, edges.a, np.transpose(ab, (0, 2, 1))),
            (edges.b, edges.b, jb_info @ jb),
        )
        rows, colz, vals = [], [], []
        for u, v, m in blocks:
            r0 = u[:, None, None] * 6 + np.arange(6)[None, :, None]
            c0 = v[:, None, None] * 6 + np.arange(6)[None, None, :]
            rows.append(np.broadcast_to(r0, m.shape).ravel())
            colz.append(np.broadcast_to(c0, m.shape).ravel())
            vals.append(m.ravel())
        h = sp.csc_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(colz))),
            shape=(6 * n, 6 * n),
        )[keep][:, keep]
        rhs = -g.ravel()[keep]
        diag = h.diagonal()
        if not np.isfinite(rhs).all():
            return Solved(x, steps, start, current, False)
        while True:
            damped = h + sp.diags(lam * np.maximum(diag, 1e-12))
            dx = np.zeros(6 * n)
            dx[keep] = spsolve(damped.tocsc(), rhs)
            trial = x @ exp_se3(dx.reshape(n, 6))
            new = cost(trial, edges)
            if new <= current:
                break
            lam *= 10.0
            if lam > 1e12:  # no step lowers the cost: converged only if none could
                still = float(np.abs(rhs).max()) <= 1e-9 * max(1.0, current)
                return Solved(x, steps, start, current, still)
        gained = current - new
        x, current = trial, new
        lam = max(lam / 10.0, 1e-9)
        if gained <= tolerance * max(current, 1e-300):
            done = True
            break
    return Solved(x, steps, start, current, done)


def position_errors(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(n,) distances between the two trajectories' positions (the same frame: vertex 0
    held at its true pose, no alignment)."""
    return np.linalg.norm(estimate[:, :3, 3] - truth[:, :3, 3], axis=1)


def rotation_errors_deg(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(n,) angles (degrees) of each estimate's rotation against the truth's."""
    rel = np.transpose(estimate[:, :3, :3], (0, 2, 1)) @ truth[:, :3, :3]
    c = np.clip(0.5 * (np.trace(rel, axis1=1, axis2=2) - 1.0), -1.0, 1.0)
    return np.degrees(np.arccos(c))
