"""How sure a verified loop closure's relative pose is: its 6 × 6 covariance, the weight a
pose graph gives the edge.

**Convention** (the service's answers, the client, the pose-graph files): the error of a
relative pose ``T`` (4 × 4, T_keyframe←query) is the vector δ = (x, y, z, rx, ry, rz) with
T_true = T · Exp(δ): a perturbation on the right, in the **query's frame**, translation
first (metres), then the rotation vector (radians). That is the tangent space of GTSAM's
``Pose3`` with its two blocks swapped (GTSAM orders rotation first) and of g2o's
``EDGE_SE3:QUAT`` with the rotation halved (g2o's error keeps the quaternion's vector part,
half the rotation vector for small errors): :func:`g2o_information` converts.

**Where it comes from.** GICP's final Gauss-Newton Hessian ``H`` (small_gicp orders it
rotation, translation, for a perturbation on the right of T_target←source: the same
perturbation as δ) is the information the registration's correspondences carry about the
pose, up to a scale: GICP's point covariances are normalised shapes, not the sensor's noise
in metres. :func:`from_hessian` takes that scale (``covariance.scale``), which
``benchmarks/pose_covariance.py`` calibrates on the validation town against the true
relative poses and scores on the test towns. Where the geometry leaves a direction free (a
corridor) ``H`` is nearly singular there and the covariance large along it: what a pose
graph needs to slide the edge rather than bend the map.

numpy only: the service, the client and the benchmarks share it.
"""

from __future__ import annotations

import numpy as np

# rotation, translation (small_gicp) → translation, rotation (δ)
_SWAP = np.r_[3:6, 0:3]

# a Hessian whose smallest eigenvalue is below this share of its largest gives no covariance:
# some direction is not constrained at all (the inverse would be numerical noise)
MIN_CONDITION = 1e-12


def swap_blocks(m: np.ndarray) -> np.ndarray:
    """A 6 × 6 matrix over (rotation, translation) as one over (translation, rotation), or
    back (the swap is its own inverse)."""
    m = np.asarray(m, dtype=np.float64)
    return m[np.ix_(_SWAP, _SWAP)]


def from_hessian(hessian: np.ndarray, scale: float) -> np.ndarray | None:
    """GICP's final 6 × 6 Hessian (rotation first) → the covariance of δ (translation
    first, module docstring): ``scale`` · H⁻¹. None when ``H`` is not symmetric positive
    definite to :data:`MIN_CONDITION` (no finite covariance) or is not finite."""
    if not scale > 0:
        raise ValueError(f"covariance scale must be > 0, got {scale}")
    h = np.asarray(hessian, dtype=np.float64)
    if h.shape != (6, 6) or not np.isfinite(h).all():
        return None
    h = 0.5 * (h + h.T)
    w, v = np.linalg.eigh(h)
    if w[-1] <= 0 or w[0] <= MIN_CONDITION * w[-1]:
        return None
    cov = (v / w) @ v.T * scale
    return swap_blocks(0.5 * (cov + cov.T))


ESTIMATORS = ("hessian", "residual")
# χ² with 6 degrees of freedom at 0.95: a right covariance's 95 % ellipsoid is δᵀ Σ⁻¹ δ below it
CHI2_6_95 = 12.591587243743977


def covariance(
    hessian: np.ndarray | None, residual: float | None, estimator: str, scale: float
) -> np.ndarray | None:
    """A registration's pose covariance (δ's order) under ``estimator``: ``hessian``,
    ``scale`` · H⁻¹; ``residual``, ``scale`` · r · H⁻¹ with r its cost per inlier pair (least
    squares' σ̂² · (JᵀJ)⁻¹). None where it has no finite one (:func:`from_hessian`)."""
    if estimator not in ESTIMATORS:
        raise ValueError(f"covariance estimator {estimator!r} is not known; allowed: {ESTIMATORS}")
    if hessian is None:
        return None
    if estimator == "residual":
        if residual is None or not np.isfinite(residual) or residual <= 0:
            return None
        return from_hessian(np.asarray(hessian, dtype=np.float64) / residual, scale)
    return from_hessian(hessian, scale)


def log_so3(rot: np.ndarray) -> np.ndarray:
    """3 × 3 rotation → its rotation vector (radians), accurate for small and large angles
    (below π)."""
    r = np.asarray(rot, dtype=np.float64)
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])  # 2 sin θ · u
    s = 0.5 * np.linalg.norm(axis)
    c = 0.5 * (np.trace(r) - 1.0)
    theta = float(np.arctan2(s, c))
    if theta < 1e-8:
        return 0.5 * axis  # θ·u ≈ sin θ·u
    return theta / (2.0 * np.sin(theta)) * axis


def _left_jacobian_inv(phi: np.ndarray) -> np.ndarray:
    """SO(3)'s left Jacobian's inverse at the rotation vector ``phi`` (the map from a
    pose's translation to its tangent's)."""
    theta = float(np.linalg.norm(phi))
    k = np.array([[0, -phi[2], phi[1]], [phi[2], 0, -phi[0]], [-phi[1], phi[0], 0]])
    if theta < 1e-8:
        return np.eye(3) - 0.5 * k + k @ k / 12.0
    half = 0.5 * theta
    b = (1.0 - half / np.tan(half)) / theta**2
    return np.eye(3) - 0.5 * k + b * (k @ k)


def error(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """δ (module docstring) of ``estimate`` against ``truth``, both 4 × 4: the SE(3)
    logarithm of estimate⁻¹ · truth, as (translation, rotation)."""
    d = np.linalg.inv(np.asarray(estimate, dtype=np.float64)) @ np.asarray(truth, np.float64)
    phi = log_so3(d[:3, :3])
    rho = _left_jacobian_inv(phi) @ d[:3, 3]
    return np.concatenate([rho, phi])


def mahalanobis2(delta: np.ndarray, covariance: np.ndarray) -> float:
    """δᵀ Σ⁻¹ δ: χ² with 6 degrees of freedom when Σ is right."""
    d = np.asarray(delta, dtype=np.float64)
    return float(d @ np.linalg.solve(np.asarray(covariance, dtype=np.float64), d))


def g2o_information(covariance: np.ndarray) -> np.ndarray:
    """The covariance of δ → the information matrix of g2o's ``EDGE_SE3:QUAT`` (error:
    translation, then the quaternion's vector part, half the rotation vector):
    D⁻¹ Σ⁻¹ D⁻¹ with D = diag(1, 1, 1, ½, ½, ½)."""
    d_inv = np.diag([1.0, 1.0, 1.0, 2.0, 2.0, 2.0])
    info = d_inv @ np.linalg.inv(np.asarray(covariance, dtype=np.float64)) @ d_inv
    return 0.5 * (info + info.T)
