"""Write a synthetic sequence in the KITTI odometry layout, with ground truth and a manifest.

    OUT/
      velodyne/000000.bin …   float32 N×4 (x, y, z, intensity), sensor frame
      poses.txt               3×4 sensor→world per scan, relative to the first scan (as KITTI)
      calib.txt               identity Tr (the poses are already in the LiDAR frame)
      times.txt               scan timestamps (s)
      ground_truth/
        overlaps.npz          overlap and yaw of every pair (i > j) closer than gt_radius
                              (pair_table "loops": only pairs more than loop_exclude apart)
        loops.npz             the loop table (overlapmamba.core.overlap.LoopGroundTruth)
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

import numpy as np
from tqdm.auto import tqdm

from overlapmamba.core.poses import write_poses
from overlapmamba.core.sensors import get_profile
from overlapmamba.synth.config import GenConfig
from overlapmamba.synth.dynamics import Dynamics
from overlapmamba.synth.lidar import Scanner, get_lidar
from overlapmamba.synth.mounting import Mounting
from overlapmamba.synth.trajectory import Drive, driven_streets, plan_drive
from overlapmamba.synth.truth import compute_ground_truth, revisit_frames
from overlapmamba.synth.workers import DEFAULT_STALL_TIMEOUT_S, run_jobs
from overlapmamba.synth.world import World, build_world

# 1.4.0: sessions (session 0 is byte-identical to 1.3.1); 1.5.0: a later session keeps to
# the streets of the first (session 0 unchanged); 1.6.0: the sensor catalogue and mountings
# (kitti-hdl64 on the car byte-identical to 1.5.0; hdl32 now as its manual gives it);
# 1.7.0: overlap tables in float32 (scans byte-identical to 1.6.0; each overlap within
# 5e-5 of 1.6.0's, none across 0.3: benchmarks/overlap_tables.py); 1.8.0: the drifting
# firing phase (``firing_phase``; locked towns byte-identical to 1.7.0)
GENERATOR_VERSION = "1.8.0"
DYNAMIC_RADIUS = 110.0  # m: cars and people farther than this are not cast against


# ---- scan simulation in worker processes ---------------------------------------------------
_W: dict = {}


def _init_worker(
    world: World,
    drive: Drive,
    dynamics: Dynamics,
    sensor: str,
    mounting: Mounting,
    seed: list[int],
    out: str,
    drifting: bool = False,
):
    _W.update(
        scanner=Scanner(world.static, get_lidar(sensor), mounting),
        drive=drive,
        dyn=dynamics,
        seed=seed,
        out=Path(out),
        drifting=drifting,
    )


def firing_phase(seed: list[int], k: int) -> float:
    """Scan ``k``'s firing phase in a drifting town: from a stream of its own, so that the
    town's every other draw (noise, dropout, traffic) is the locked town's."""
    return float(np.random.default_rng([*seed, 2, k]).random())


def _simulate(k: int) -> tuple[int, int]:
    drive: Drive = _W["drive"]
    t = float(drive.times[k])
    heading = float(np.arctan2(drive.poses[k, 1, 0], drive.poses[k, 0, 0]))
    mesh = _W["dyn"].mesh_at(t, drive.poses[k, :2, 3], DYNAMIC_RADIUS, heading)
    phase = firing_phase(_W["seed"], k) if _W["drifting"] else 0.0
    rng = np.random.default_rng([*_W["seed"], 1, k])
    pts = _W["scanner"].scan(drive.pose_at, t, mesh, rng, phase)
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
    drifting = cfg.firing_phase == "drifting"
    args = (
        world,
        drive,
        dynamics,
        cfg.sensor,
        cfg.mounting(),
        cfg.session_seed(),
        str(out),
        drifting,
    )
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


# ---- statistics and manifest --------------------------------------------------------------------
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


# the marker of a sequence folder gen-data is still writing (or was killed writing)
INCOMPLETE = ".incomplete"


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
        if (out / INCOMPLETE).exists():  # a run that was stopped or failed
            raise FileExistsError(
                f"{out} is an incomplete run's folder (stopped, or failed): delete it, or "
                "choose a new folder for the sequence"
            )
        raise FileExistsError(f"{out} is not empty; choose a new folder for the sequence")
    out.mkdir(parents=True, exist_ok=True)
    # until the manifest is whole, the folder says it is not (a run killed between the scans
    # and the manifest leaves a folder every reader would otherwise take for a sequence)
    (out / INCOMPLETE).write_text("gen-data under way; if no run is, delete this folder\n")
    t0 = time.perf_counter()
    world, drive, dynamics = build_scene(cfg)
    t_world = time.perf_counter() - t0

    counts = simulate_scans(out, world, drive, dynamics, cfg, workers, progress, stall_timeout_s)
    t_sim = time.perf_counter() - t0 - t_world

    write_layout(out, drive)

    table = loops = None
    if ground_truth and cfg.pair_table != "none":
        table, loops = compute_ground_truth(out, cfg, workers, progress, stall_timeout_s)
    t_gt = time.perf_counter() - t0 - t_world - t_sim

    same = rev = None
    if loops is not None:
        same, rev, _ = revisit_frames(loops)
    from overlapmamba.synth.mapview import draw_map

    pos_world = drive.poses[:, :2, 3]
    draw_map(
        world,
        out / "map.png",
        pos_world,
        same,
        rev,
        title=f"seed {cfg.seed}"
        + (f" session {cfg.session}" if cfg.session else "")
        + f" · {cfg.frames} scans · {cfg.sensor} on a {cfg.mount}"
        + (f" · preset {cfg.preset}" if cfg.preset else ""),
    )

    manifest = {
        "generator": "overlapmamba synthetic LiDAR world",
        "generator_version": GENERATOR_VERSION,
        "config": cfg.model_dump(),
        "resolved": {
            "world": cfg.world_params().to_dict(),
            "drive": cfg.drive_params().to_dict(),
            "dynamics": cfg.dynamics_params().to_dict(),
            "lidar": dataclasses.asdict(get_lidar(cfg.sensor)),
            "mounting": dataclasses.asdict(cfg.mounting()),
            "profile": get_profile(cfg.sensor).model_dump(),
        },
        "world_from_sequence": drive.poses[0].tolist(),
        "counts": _stats(world, drive, counts, table, loops, cfg),
        "data_sha256": data_fingerprint(out),
    }
    tmp = out / ".manifest.json.tmp"
    tmp.write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")
    os.replace(tmp, out / "manifest.json")
    (out / INCOMPLETE).unlink()
    manifest["timing_s"] = {
        "world": t_world,
        "simulate": t_sim,
        "ground_truth": t_gt,
        "scans_per_s": cfg.frames / max(t_sim, 1e-9),
    }
    return manifest


def read_manifest(root: str | Path) -> dict:
    return json.loads((Path(root) / "manifest.json").read_text())
