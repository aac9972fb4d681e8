"""A spinning multi-beam LiDAR of the catalogue (:mod:`overlapmamba.core.sensors.catalogue`) on a
mounting (:mod:`overlapmamba.synth.mounting`), ray-cast with Embree (through embreex).

Per scan:
  1. each column fires at its own instant of the 0.1 s sweep, from the pose of that instant
     (the vehicle moves ≈1 m per sweep; KITTI's scans carry the same motion distortion);
  2. rays are intersected with the static town and with a small per-scan scene of the cars
     and pedestrians nearby; the nearer hit wins;
  3. rays that hit porous surfaces (foliage, chain-link fences) pass through with the
     material's probability and are cast again from behind the surface;
  4. a return is detected with a probability that falls with received energy
     (reflectivity · cos(incidence) / range²), and also drops out at random;
  5. range gets Gaussian noise; intensity follows reflectivity and incidence angle;
  6. points are expressed in the sensor frame at the scan's timestamp (mid-sweep, facing
     forward), in firing order.

Output: (N, 4) float32 x, y, z, intensity — KITTI's ``.bin`` record.

**Where the firings fall.** With ``phase`` 0 (every town made before generator 1.8.0: the
``locked`` firing phase of :class:`overlapmamba.synth.config.GenConfig`) the head fires at
the same azimuths every turn, so a model's column grid meets the firings in the same pattern
in every scan (the kitti-hdl64's 2,083 firings give its 900 columns two or three each, always
the same columns). A real head does not: its firings' spacing varies with the motor's speed
from turn to turn (KITTI 00's scans, one by one: ``benchmarks/firing_spacing.py``), so the
count of firings a turn varies too and the pattern between firings and columns drifts.
``phase`` φ ∈ [0, 1) (the ``drifting`` firing phase, drawn per scan) starts the scan's
firings φ of a spacing later: every firing's azimuth and instant move by φ / ``columns`` of
a turn.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from overlapmamba.core.sensors.catalogue import CATALOGUE
from overlapmamba.synth.geometry import TRANSMIT, Mesh
from overlapmamba.synth.mounting import MOUNTINGS, Mounting


@dataclass(frozen=True)
class LidarModel:
    """A catalogue sensor (:mod:`overlapmamba.core.sensors.catalogue`) as the simulator fires it."""

    name: str  # the catalogue name, also the profile its drives' ground truth uses
    elevations_deg: tuple[float, ...]
    columns: int  # firings per revolution
    rate_hz: float = 10.0
    max_range: float = 120.0
    min_range: float = 0.9
    range_sigma: float = 0.02  # m
    dropout: float = 0.02  # returns lost at random
    energy_scale: float = 0.006  # detection probability = 1 − exp(−energy / energy_scale)

    @property
    def beams(self) -> int:
        return len(self.elevations_deg)

    def sweep(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit ray directions (beams, columns, 3) in the sensor frame and each column's
        firing time (columns,) in seconds relative to the scan timestamp.

        The head spins clockwise seen from above, starting backwards (azimuth +180°), so it
        faces forward (azimuth 0) at mid-sweep — the scan's timestamp.
        """
        el = np.radians(np.asarray(self.elevations_deg))[:, None]
        frac = (np.arange(self.columns) + 0.5) / self.columns
        az = np.pi - 2 * np.pi * frac
        d = np.stack(
            [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) * np.ones_like(az)], -1
        )
        return d, (frac - 0.5) / self.rate_hz


def get_lidar(name: str) -> LidarModel:
    """The catalogue sensor ``name`` as the simulator fires it."""
    if name not in CATALOGUE:
        raise ValueError(f"unknown simulated sensor {name!r}; allowed: {', '.join(CATALOGUE)}")
    s = CATALOGUE[name]
    return LidarModel(
        name=s.name,
        elevations_deg=s.elevations_deg,
        columns=s.columns,
        rate_hz=s.rate_hz,
        max_range=s.max_range,
        min_range=s.min_range,
        range_sigma=s.range_sigma,
    )


class _Scene:
    def __init__(self, mesh: Mesh) -> None:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        self.mesh = mesh
        self.scene = rtcore_scene.EmbreeScene()
        TriangleMesh(self.scene, np.ascontiguousarray(mesh.tris, dtype=np.float32))

    def cast(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """→ distance (inf on a miss), face index (−1), unnormalised normal."""
        r = self.scene.run(o, d, output=1)
        face = r["primID"].astype(np.int64)
        miss = r["geomID"] == -1
        face[miss] = -1
        t = np.where(miss, np.inf, r["tfar"]).astype(np.float32)
        return t, face, r["Ng"]


class Scanner:
    """Casts scans of one LiDAR model on one mounting in one static world (build once per
    process). ``pose_at`` gives the sensor's poses (the mounting's tilt included)."""

    def __init__(self, static: Mesh, model: LidarModel, mounting: Mounting | None = None) -> None:
        self.model = model
        self.mounting = mounting or MOUNTINGS["car"]
        self.static = _Scene(static)
        self.dirs, self.col_time = model.sweep()
        self.dirs_by_column = np.ascontiguousarray(self.dirs.transpose(1, 0, 2))  # (C, H, 3)
        tilt = self.mounting.tilt()
        platform = self.dirs if tilt is None else self.dirs @ tilt.T
        # Firing order (column-major), like the ray arrays below.
        self.blocked = self.mounting.blocked(platform).T.reshape(-1)

    def _cast(self, dyn: _Scene | None, o: np.ndarray, d: np.ndarray):
        t, face, ng = self.static.cast(o, d)
        mat = np.full(len(t), 255, np.uint8)
        albedo = np.zeros(len(t), np.float32)
        hit = face >= 0
        mat[hit] = self.static.mesh.mat[face[hit]]
        albedo[hit] = self.static.mesh.albedo[face[hit]]
        if dyn is not None:
            t2, face2, ng2 = dyn.cast(o, d)
            nearer = t2 < t
            t = np.where(nearer, t2, t)
            ng = np.where(nearer[:, None], ng2, ng)
            mat[nearer] = dyn.mesh.mat[face2[nearer]]
            albedo[nearer] = dyn.mesh.albedo[face2[nearer]]
        return t, mat, albedo, ng

    def scan(
        self,
        pose_at,
        t_scan: float,
        dynamic: Mesh,
        rng: np.random.Generator,
        phase: float = 0.0,
    ) -> np.ndarray:
        """One sweep around timestamp ``t_scan``; ``pose_at(times) → (M, 4, 4)``. ``phase``
        in [0, 1): the firings start that fraction of a spacing later (the module notes)."""
        m = self.model
        H = m.beams
        if not 0.0 <= phase < 1.0:
            raise ValueError(f"phase must be in [0, 1) of a firing's spacing; got {phase}")
        col_time, dirs = self.col_time, self.dirs_by_column
        if phase:  # the head spins clockwise: later firings, smaller azimuths
            col_time = col_time + phase / (m.columns * m.rate_hz)
            dirs = dirs @ _turn_z(-2.0 * np.pi * phase / m.columns).T
        poses = pose_at(t_scan + col_time)  # (C, 4, 4) pose of each firing
        ref = pose_at(np.array([t_scan]))[0]
        # Firing order: column by column, all lasers of a column together. Each column's
        # directions turned by its own pose: one stacked matmul (30× an einsum, same bits).
        o = np.repeat(poses[:, :3, 3].astype(np.float32), H, axis=0)
        d = (dirs @ poses[:, :3, :3].transpose(0, 2, 1)).astype(np.float32)
        d = d.reshape(-1, 3)

        dyn = _Scene(dynamic) if len(dynamic) else None
        t, mat, albedo, ng = self._cast(dyn, o, d)

        # Porous surfaces: some rays go on and hit what lies behind.
        hit = np.isfinite(t)
        porous = hit & (rng.random(len(t)) < TRANSMIT[np.minimum(mat, len(TRANSMIT) - 1)])
        if porous.any():
            idx = np.nonzero(porous)[0]
            skip = t[idx] + 0.05
            o2 = np.ascontiguousarray(o[idx] + d[idx] * skip[:, None])
            t2, mat2, alb2, ng2 = self._cast(dyn, o2, np.ascontiguousarray(d[idx]))
            t[idx] = t2 + skip
            mat[idx], albedo[idx], ng[idx] = mat2, alb2, ng2

        hit = np.isfinite(t) & (t < m.max_range) & (t > m.min_range) & ~self.blocked
        idx = np.nonzero(hit)[0]
        r = t[idx].astype(np.float64)
        # Per coordinate (columns of the hits' normals and directions): the same sums in the
        # same order as a row-wise dot and norm, at a fraction of their cost.
        n = ng[idx].astype(np.float64).T
        u = d[idx].T
        dot = n[0] * u[0] + n[1] * u[1] + n[2] * u[2]
        norm = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
        cos_inc = np.abs(dot) / np.maximum(norm, 1e-12)
        rho = albedo[idx].astype(np.float64)
        energy = rho * cos_inc * np.minimum(1.0, (20.0 / r) ** 2)
        detected = rng.random(len(idx)) < (1.0 - np.exp(-energy / m.energy_scale))
        detected &= rng.random(len(idx)) >= m.dropout
        idx, r, rho, cos_inc = idx[detected], r[detected], rho[detected], cos_inc[detected]

        r = r + rng.normal(0.0, m.range_sigma, len(r))
        world = d[idx].astype(np.float64)  # o + d·r, in place: half the time, same bits
        world *= r[:, None]
        world += o[idx]
        inv = np.linalg.inv(ref)
        local = world @ inv[:3, :3].T + inv[:3, 3]
        # KITTI's intensities depend on incidence only weakly (its road reads ≈0.3 even at
        # grazing angles), so reflectivity dominates.
        intensity = rho * (0.9 + 0.1 * cos_inc) * (1.0 - 0.15 * np.minimum(r / 100.0, 1.0))
        intensity = np.clip(intensity + rng.normal(0, 0.03, len(r)), 0.0, 0.99)
        return np.column_stack([local, intensity]).astype("<f4")


def _turn_z(angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` radians about the sensor's z axis."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


__all__ = ["LidarModel", "Scanner", "get_lidar"]
