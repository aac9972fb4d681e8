"""Poses: KITTI text files, the camera→LiDAR frame change, and relative yaw.

Poses are (N, 4, 4) float64 homogeneous transforms from the scan frame to the world frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from overlapmamba.core.errors import DatasetError


def read_poses(path: str | Path) -> np.ndarray:
    """KITTI pose file: one 3×4 row-major matrix (12 numbers) per line → (N, 4, 4)."""
    path = Path(path)
    rows = []
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()  # a BOM is not data
    except OSError as err:
        raise DatasetError(f"cannot read pose file {path}: {err.strerror}") from err
    for lineno, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            values = [float(v) for v in line.split()]
        except ValueError as err:
            raise DatasetError(f"{path}:{lineno}: pose holds a non-number: {err}") from err
        if len(values) != 12:
            raise DatasetError(
                f"{path}:{lineno}: pose has {len(values)} numbers; expected 12 (3×4 row-major)"
            )
        rows.append(values)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    if rows:
        poses[:, :3, :] = np.asarray(rows, dtype=np.float64).reshape(-1, 3, 4)
    if not np.isfinite(poses).all():
        raise DatasetError(f"{path}: poses contain NaN or infinite values")
    return poses


def write_poses(path: str | Path, poses: np.ndarray) -> None:
    """Inverse of :func:`read_poses`."""
    flat = np.asarray(poses, dtype=np.float64)[:, :3, :].reshape(-1, 12)
    np.savetxt(path, flat, fmt="%.9e")


def read_calib(path: str | Path) -> dict[str, np.ndarray]:
    """KITTI ``calib.txt``: ``KEY: v1 v2 …`` per line. 12-number entries become 4×4."""
    path = Path(path)
    out: dict[str, np.ndarray] = {}
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()  # a BOM is not data
    except OSError as err:
        raise DatasetError(f"cannot read calibration file {path}: {err.strerror}") from err
    for lineno, line in enumerate(lines, 1):
        if ":" not in line:
            continue
        key, _, rest = line.partition(":")
        try:
            values = np.array([float(v) for v in rest.split()], dtype=np.float64)
        except ValueError as err:
            raise DatasetError(f"{path}:{lineno}: calibration holds a non-number") from err
        if not np.isfinite(values).all():
            raise DatasetError(f"{path}:{lineno}: calibration holds NaN or infinite values")
        if values.size == 12:
            m = np.eye(4)
            m[:3, :] = values.reshape(3, 4)
            out[key.strip()] = m
        else:
            out[key.strip()] = values
    return out


def camera_to_lidar(poses_cam: np.ndarray, tr_velo_to_cam: np.ndarray) -> np.ndarray:
    """KITTI ground truth is in the left camera frame; re-express it for the LiDAR.

    T_velo_i = Tr⁻¹ · P_0⁻¹ · P_i · Tr, so frame 0 is the identity and x points forward.
    """
    tr = np.asarray(tr_velo_to_cam, dtype=np.float64)
    for name, m in (("the calibration's Tr", tr), ("the first pose", poses_cam[0])):
        if abs(np.linalg.det(m[:3, :3])) < 1e-9:  # a rotation's is 1
            raise DatasetError(
                f"{name} is singular (its rotation's determinant is "
                f"{np.linalg.det(m[:3, :3]):.3g}; a rotation's is 1): it cannot be inverted"
            )
    first_inv = np.linalg.inv(poses_cam[0])
    return np.linalg.inv(tr) @ first_inv @ poses_cam @ tr


def relative_transform(query_pose: np.ndarray, ref_poses: np.ndarray) -> np.ndarray:
    """T_query←ref for each reference: maps reference-frame points into the query frame.

    query_pose: (4, 4); ref_poses: (K, 4, 4) or (4, 4) → same leading shape as ref_poses.
    """
    return np.linalg.inv(query_pose) @ ref_poses


def yaw_deg(transforms: np.ndarray) -> np.ndarray:
    """Rotation about z of (…, 4, 4) transforms, degrees in (−180, 180]."""
    t = np.asarray(transforms)
    return np.degrees(np.arctan2(t[..., 1, 0], t[..., 0, 0]))


# a loop closure whose relative pose is this close to the truth is right (metres, degrees):
# an edge a pose graph can take
POSE_RIGHT = (1.0, 2.0)


def pose_error(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """How far a (4, 4) transform is from the true one: (translation in metres, |yaw| in
    degrees) of truth⁻¹ · estimate."""
    err = np.linalg.inv(truth) @ estimate
    return float(np.linalg.norm(err[:3, 3])), float(abs(yaw_deg(err)))


def quaternion(rot: np.ndarray) -> np.ndarray:
    """3×3 rotation → (qx, qy, qz, qw), unit, qw ≥ 0 (Shepperd's method)."""
    m = np.asarray(rot, dtype=np.float64)
    t = np.trace(m)
    if t > 0:
        s = 2.0 * np.sqrt(t + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0, 0.0, 0.0, (m[k, j] - m[j, k]) / s]
        q[i] = s / 4
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
    out = np.asarray(q, dtype=np.float64)
    out /= np.linalg.norm(out)
    return out if out[3] >= 0 else -out


def from_quaternion(xyz: np.ndarray | list[float], q: np.ndarray | list[float]) -> np.ndarray:
    """(x, y, z) and a quaternion (qx, qy, qz, qw; normalised here) → a 4×4 pose."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / (np.linalg.norm(q) or 1.0)
    T = np.eye(4)
    T[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    T[:3, 3] = np.asarray(xyz, dtype=np.float64)
    return T


def translations(poses: np.ndarray) -> np.ndarray:
    """(N, 3) positions."""
    return np.asarray(poses)[:, :3, 3]


def rotation_z(deg: float) -> np.ndarray:
    """4×4 rotation by ``deg`` degrees about z (counter-clockwise seen from above)."""
    a = np.radians(deg)
    m = np.eye(4)
    m[0, 0] = m[1, 1] = np.cos(a)
    m[0, 1], m[1, 0] = -np.sin(a), np.sin(a)
    return m


def transform_points(xyz: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """Apply a 4×4 transform to (N, 3) points → (N, 3) float32."""
    t = np.asarray(transform, dtype=np.float64)
    return (np.asarray(xyz, dtype=np.float64) @ t[:3, :3].T + t[:3, 3]).astype(np.float32)
