"""Write a synthetic sequence in the KITTI odometry layout, with ground truth and a manifest.

    OUT/
      velodyne/000000.bin …   float32 N×4 (x, y, z, intensity), sensor frame
      poses.txt               3×4 sensor→world per scan, relative to the first scan (as KITTI)
      calib.txt               identity Tr (the poses are already in the LiDAR frame)
      times.txt               scan timestamps (s)
      ground_truth/
        overlaps.npz          overlap and yaw of every pair (i > j) closer than gt_radius
                              (pair_table "loops": only pairs more than loop_exclude apart)
        loops.npz             the loop table (lidar_core.overlap.LoopGroundTruth)
      manifest.json           seed, generator version, parameters, counts, loop statistics
      map.png                 top-down world with the coloured drive and its revisits

Scans are simulated in worker processes; each scan draws its noise from (seed, frame), so
the output is byte-identical for a seed whatever the number of workers.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator
from tqdm.auto import tqdm

from lidar_core.datasets import open_sequence
from lidar_core.overlap import (
    LoopGroundTruth,
    candidate_pairs,
    loop_params,
    loop_table_from_pairs,
    pair_overlaps,
)
from lidar_core.poses import write_poses
from lidar_core.sensors import get_profile
from lidar_synth.dynamics import Dynamics, DynamicsParams
from lidar_synth.lidar import LIDAR_MODELS, Scanner, get_lidar
from lidar_synth.trajectory import Drive, DriveParams, driven_streets, plan_drive
from lidar_synth.workers import DEFAULT_STALL_TIMEOUT_S, run_jobs
from lidar_synth.world import World, WorldParams, build_world

# 1.4.0: sessions (session 0 is byte-identical to 1.3.1); 1.5.0: a later session keeps to
# the streets of the first (session 0 unchanged)
GENERATOR_VERSION = "1.5.0"
DYNAMIC_RADIUS = 110.0  # m: cars and people farther than this are not cast against


class GenConfig(BaseModel):
    """Everything that determines a generated sequence."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    seed: int = Field(ge=0, le=2**31 - 1)
    frames: int = Field(ge=2, le=100_000)
    session: int = Field(
        default=0,
        ge=0,
        le=1000,
        description="0: the town's first drive; k > 0: another drive through the same static "
        "town (same seed) along the streets the first drive of as many frames took, in its own "
        "order and directions, with its own parked cars, traffic, people and scan noise",
    )
    sensor: str = "kitti-hdl64"
    preset: str | None = None
    split: str = Field(default="train", description="train, val or test; test is never trained on")
    world: dict = Field(default_factory=dict, description="WorldParams overrides")
    drive: dict = Field(default_factory=dict, description="DriveParams overrides")
    dynamics: dict = Field(default_factory=dict, description="DynamicsParams overrides")
    gt_radius: float = Field(default=30.0, gt=0, le=200)
    loop_exclude: int = Field(default=100, ge=0)
    loop_min_overlap: float = Field(default=0.3, ge=0, le=1)
    pair_table: Literal["all", "loops"] = Field(
        default="all",
        description="all: every pair within gt_radius (what training samples positives and "
        "near misses from); loops: only pairs more than loop_exclude frames apart, the loop "
        "table's candidates, enough for validation and test towns at a fraction of the work",
    )

    @field_validator("sensor")
    @classmethod
    def _known_sensor(cls, v: str) -> str:
        if v not in LIDAR_MODELS:
            raise ValueError(f"unknown sensor {v!r}; allowed: {', '.join(LIDAR_MODELS)}")
        return v

    @field_validator("split")
    @classmethod
    def _known_split(cls, v: str) -> str:
        if v not in ("train", "val", "test"):
            raise ValueError(f"unknown split {v!r}; allowed: train, val, test")
        return v

    def session_seed(self) -> list[int]:
        """Entropy of everything that changes between sessions (session 0: the seed alone,
        so first sessions stay byte-identical to those of earlier generator versions)."""
        return [self.seed] if self.session == 0 else [self.seed, 0x5E55, self.session]

    def world_params(self) -> WorldParams:
        return _build(WorldParams, self.world)

    def drive_params(self) -> DriveParams:
        lidar = get_lidar(self.sensor)
        base = {"rate_hz": lidar.rate_hz, "mount_height": lidar.mount_height}
        return _build(DriveParams, {**base, **self.drive})

    def dynamics_params(self) -> DynamicsParams:
        return _build(DynamicsParams, self.dynamics)


def _build(cls, overrides: dict):
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(overrides) - names
    if unknown:
        raise ValueError(
            f"unknown {cls.__name__} fields {sorted(unknown)}; allowed: {sorted(names)}"
        )
    fixed = {k: tuple(v) if isinstance(v, list) else v for k, v in overrides.items()}
    return cls(**fixed)


# ---- scan simulation in worker processes ---------------------------------------------------
_W: dict = {}


def _init_worker(
    world: World, drive: Drive, dynamics: Dynamics, sensor: str, seed: list[int], out: str
):
    _W.update(
        scanner=Scanner(world.static, get_lidar(sensor)),
        drive=drive,
        dyn=dynamics,
        seed=seed,
        out=Path(out),
    )


def _simulate(k: int) -> tuple[int, int]:
    drive: Drive = _W["drive"]
    t = float(drive.times[k])
    heading = float(np.arctan2(drive.poses[k, 1, 0], drive.poses[k, 0, 0]))
    mesh = _W["dyn"].mesh_at(t, drive.poses[k, :2, 3], DYNAMIC_RADIUS, heading)
    pts = _W["scanner"].scan(drive.pose_at, t, mesh, np.random.default_rng([*_W["seed"], 1, k]))
    path = _W["out"] / "velodyne" / f"{k:06d}.bin"
    tmp = path.with_suffix(".tmp")
    pts.tofile(tmp)
    os.replace(tmp, path)
    return k, len(pts)


def simulate_scans(
    out: Path,
    world: World,
    drive: Drive,
    dynamics: Dynamics,
    cfg: GenConfig,
    workers: int,
    progress: bool,
    stall_timeout_s: float = DEFAULT_STALL_TIMEOUT_S,
) -> np.ndarray:
    (out / "velodyne").mkdir(parents=True, exist_ok=True)
    counts = np.zeros(cfg.frames, np.int64)
    args = (world, drive, dynamics, cfg.sensor, cfg.session_seed(), str(out))
    bar = tqdm(total=cfg.frames, desc="simulate", unit="scan", disable=not progress)
    if workers <= 1:
        _init_worker(*args)
        done: Iterable[tuple[int, int]] = map(_simulate, range(cfg.frames))
    else:
        done = (
            res
            for _, res in run_jobs(
                _simulate,
                range(cfg.frames),
                workers=workers,
                initializer=_init_worker,
                initargs=args,
                stall_timeout_s=stall_timeout_s,
                what="scan",
            )
        )
    for k, n in done:
        counts[k] = n
        bar.update()
    bar.close()
    return counts


# ---- ground truth -----------------------------------------------------------------------------
def _overlap_chunk(args) -> tuple[np.ndarray, np.ndarray]:
    root, sensor, pairs = args
    seq = open_sequence(root, kind="kitti", sensor=sensor)
    return pair_overlaps(seq, pairs, get_profile(sensor), progress=False)


def compute_ground_truth(
    out: Path,
    cfg: GenConfig,
    workers: int,
    progress: bool,
    stall_timeout_s: float = DEFAULT_STALL_TIMEOUT_S,
) -> tuple[dict, LoopGroundTruth]:
    """Overlap/yaw of every pair closer than ``gt_radius`` (query later than reference), with
    lidar_core's overlap code; the loop table is the subset the loop protocol asks for.

    With ``pair_table="loops"`` only the loop table's candidates are computed (pairs more than
    ``loop_exclude`` frames apart): the same loop table, without the neighbouring frames that
    only training samples from."""
    seq = open_sequence(out, kind="kitti", sensor=cfg.sensor)
    profile = get_profile(cfg.sensor)
    min_gap = 1 if cfg.pair_table == "all" else cfg.loop_exclude + 1
    pairs = candidate_pairs(seq.positions(), radius=cfg.gt_radius, min_gap=min_gap)
    pairs = pairs[np.argsort(pairs[:, 0], kind="stable")]
    # Chunks of ≈25 whole queries, so each chunk projects its queries once.
    queries = np.unique(pairs[:, 0])
    firsts = [q[0] for q in np.array_split(queries, max(1, len(queries) // 25)) if len(q)]
    chunks = np.split(pairs, np.searchsorted(pairs[:, 0], firsts[1:]))
    jobs = [(str(out), cfg.sensor, c) for c in chunks]
    bar = tqdm(total=len(pairs), desc="overlap ground truth", unit="pair", disable=not progress)
    results: list = [None] * len(jobs)
    if workers <= 1:
        done: Iterable[tuple[int, Any]] = enumerate(map(_overlap_chunk, jobs))
    else:
        done = run_jobs(
            _overlap_chunk, jobs, workers=workers, stall_timeout_s=stall_timeout_s, what="chunk"
        )
    for i, res in done:
        results[i] = res
        bar.update(len(jobs[i][2]))
    bar.close()
    overlap = np.concatenate([r[0] for r in results]).astype(np.float32)
    yaw = np.concatenate([r[1] for r in results]).astype(np.float32)
    pos = seq.positions()
    dist = np.linalg.norm(pos[pairs[:, 0]] - pos[pairs[:, 1]], axis=1).astype(np.float32)
    gt_dir = out / "ground_truth"
    gt_dir.mkdir(exist_ok=True)
    table = {
        "query": pairs[:, 0],
        "reference": pairs[:, 1],
        "overlap": overlap,
        "yaw_deg": yaw,
        "distance": dist,
    }
    tmp = gt_dir / "overlaps.tmp.npz"
    np.savez_compressed(
        tmp,
        **table,
        radius=cfg.gt_radius,
        pair_table=cfg.pair_table,
        profile=json.dumps(profile.model_dump()),
    )
    os.replace(tmp, gt_dir / "overlaps.npz")
    params = loop_params(
        seq,
        profile,
        exclude_recent=cfg.loop_exclude,
        radius=min(30.0, cfg.gt_radius),
        min_overlap=cfg.loop_min_overlap,
    )
    loops = loop_table_from_pairs(seq, params, pairs[:, 0], pairs[:, 1], overlap, yaw)
    loops.save(gt_dir / "loops.npz")
    return table, loops


def read_overlaps(root: str | Path) -> dict[str, np.ndarray]:
    """The pair table written by :func:`compute_ground_truth`."""
    with np.load(Path(root) / "ground_truth" / "overlaps.npz", allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


# ---- statistics and manifest --------------------------------------------------------------------
def revisit_frames(loops: LoopGroundTruth) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frames that revisit a place, split by direction (best-overlap reference's |yaw| > 90°),
    and each such frame's gap to that reference in frames."""
    frames, refs, yaw = loops.best_loops()
    rev = np.abs(yaw) > 90
    return frames[~rev], frames[rev], frames - refs


def _stats(world: World, drive: Drive, counts: np.ndarray, table, loops, cfg: GenConfig) -> dict:
    kinds: dict[str, int] = {}
    for _, kind in world.footprints:
        kinds[kind] = kinds.get(kind, 0) + 1
    districts: dict[str, int] = {}
    for s in world.network.streets:
        districts[s.district] = districts.get(s.district, 0) + 1
    step = np.linalg.norm(np.diff(drive.poses[:, :3, 3], axis=0), axis=1)
    stats = {
        "frames": cfg.frames,
        "points_per_scan": {
            "mean": float(counts.mean()),
            "min": int(counts.min()),
            "max": int(counts.max()),
        },
        "world": {
            "static_triangles": len(world.static),
            "streets": len(world.network.streets),
            "street_km": round(world.street_length / 1000, 3),
            "streets_by_district": districts,
            "buildings": kinds,
            "trees": len(world.trees),
            "parking_slots": len(world.parking),
        },
        "drive": {
            "length_m": round(float(step.sum()), 1),
            "speed_mps": {
                "min": round(float(drive.speed.min()), 2),
                "mean": round(float(drive.speed.mean()), 2),
                "max": round(float(drive.speed.max()), 2),
            },
            # Planned revisits the drive completed within its scans.
            "planned_revisits": len(
                driven := [r for r in drive.revisits if r["end_m"] <= step.sum()]
            ),
            "planned_reversed": sum(r["reversed"] for r in driven),
        },
    }
    if loops is not None:
        same, rev, gaps = revisit_frames(loops)
        n = len(same) + len(rev)
        stats["ground_truth"] = {
            "pair_table": cfg.pair_table,
            "pairs_within_radius": len(table["query"]),
            "adjacent_overlap_mean": float(
                table["overlap"][table["query"] - table["reference"] == 1].mean()
            )
            if (table["query"] - table["reference"] == 1).any()
            else None,
            "loop_pairs": int(loops.is_loop.sum()),
            "queries_with_loop": n,
            "same_direction_queries": len(same),
            "reverse_direction_queries": len(rev),
            "reverse_fraction": round(len(rev) / n, 3) if n else 0.0,
            "max_revisit_gap_frames": int(gaps.max()) if n else 0,
            "queries_with_gap_over_1000": int((gaps > 1000).sum()),
        }
    return stats


def data_fingerprint(out: Path) -> str:
    """sha256 over poses and every scan: identifies the data a model was trained on."""
    h = hashlib.sha256()
    h.update((out / "poses.txt").read_bytes())
    for p in sorted((out / "velodyne").glob("*.bin")):
        with p.open("rb") as f:
            h.update(f.read())
    return h.hexdigest()


def write_layout(out: Path, drive: Drive) -> None:
    """poses.txt relative to the first scan (as KITTI), identity calib.txt, times.txt."""
    write_poses(out / "poses.txt", np.linalg.inv(drive.poses[0]) @ drive.poses)
    ident = " ".join(f"{v:.12e}" for v in np.eye(4)[:3].ravel())
    (out / "calib.txt").write_text("".join(f"P{i}: {ident}\n" for i in range(4)) + f"Tr: {ident}\n")
    np.savetxt(out / "times.txt", drive.times, fmt="%.6e")


def build_scene(cfg: GenConfig) -> tuple[World, Drive, Dynamics]:
    """The town, the drive through it and its moving parts: everything but the scans."""
    world = build_world(cfg.seed, cfg.world_params())  # the same for every session
    session = cfg.session_seed()
    net, terrain, params = world.network, world.terrain, cfg.drive_params()
    streets = None
    if cfg.session:  # later sessions re-drive the first one's streets, in their own order
        first = plan_drive(
            net, terrain, np.random.default_rng([cfg.seed, 0xD21]), cfg.frames, params
        )
        streets = driven_streets(net, first)
    rng = np.random.default_rng([*session, 0xD21])
    drive = plan_drive(net, terrain, rng, cfg.frames, params, streets)
    dynamics = Dynamics(world, session, float(drive.times[-1]) + 1.0, cfg.dynamics_params())
    return world, drive, dynamics


def generate(
    out: str | Path,
    cfg: GenConfig,
    *,
    workers: int = 2,
    ground_truth: bool = True,
    progress: bool = True,
    stall_timeout_s: float = DEFAULT_STALL_TIMEOUT_S,
) -> dict:
    """Generate one sequence into ``out`` (must be empty or absent); return the manifest.

    Scans and ground truth are computed in ``workers`` processes (see ``synth.workers``); a
    worker that dies, or no progress for ``stall_timeout_s``, raises ``WorkerError``."""
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(f"{out} is not empty; choose a new folder for the sequence")
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    world, drive, dynamics = build_scene(cfg)
    t_world = time.perf_counter() - t0

    counts = simulate_scans(out, world, drive, dynamics, cfg, workers, progress, stall_timeout_s)
    t_sim = time.perf_counter() - t0 - t_world

    write_layout(out, drive)

    table = loops = None
    if ground_truth:
        table, loops = compute_ground_truth(out, cfg, workers, progress, stall_timeout_s)
    t_gt = time.perf_counter() - t0 - t_world - t_sim

    same = rev = None
    if loops is not None:
        same, rev, _ = revisit_frames(loops)
    from lidar_synth.mapview import draw_map

    pos_world = drive.poses[:, :2, 3]
    draw_map(
        world,
        out / "map.png",
        pos_world,
        same,
        rev,
        title=f"seed {cfg.seed}"
        + (f" session {cfg.session}" if cfg.session else "")
        + f" · {cfg.frames} scans · {cfg.sensor}"
        + (f" · preset {cfg.preset}" if cfg.preset else ""),
    )

    manifest = {
        "generator": "overlapmamba synthetic LiDAR world",
        "generator_version": GENERATOR_VERSION,
        "config": cfg.model_dump(),
        "resolved": {
            "world": dataclasses.asdict(cfg.world_params()),
            "drive": dataclasses.asdict(cfg.drive_params()),
            "dynamics": dataclasses.asdict(cfg.dynamics_params()),
            "lidar": dataclasses.asdict(get_lidar(cfg.sensor)),
            "profile": get_profile(cfg.sensor).model_dump(),
        },
        "world_from_sequence": drive.poses[0].tolist(),
        "counts": _stats(world, drive, counts, table, loops, cfg),
        "data_sha256": data_fingerprint(out),
    }
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")
    manifest["timing_s"] = {
        "world": t_world,
        "simulate": t_sim,
        "ground_truth": t_gt,
        "scans_per_s": cfg.frames / max(t_sim, 1e-9),
    }
    return manifest


def read_manifest(root: str | Path) -> dict:
    return json.loads((Path(root) / "manifest.json").read_text())
