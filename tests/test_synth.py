"""Synthetic LiDAR worlds: geometry, driving, the sensor, and the generated sequences."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("embreex")

import itertools

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.overlap import LoopParams, loop_ground_truth, overlap_and_yaw
from overlapmamba.core.sensors import CATALOGUE, get_profile
from overlapmamba.synth.config import GenConfig
from overlapmamba.synth.dynamics import Dynamics
from overlapmamba.synth.generate import build_scene, firing_phase, generate, read_manifest
from overlapmamba.synth.geometry import MAT, Mesh
from overlapmamba.synth.lidar import Scanner, get_lidar
from overlapmamba.synth.mounting import MOUNTINGS, Mounting, get_mounting
from overlapmamba.synth.presets import DRAWN_PRESETS, PRESETS, drawn_town
from overlapmamba.synth.streets import DISTRICTS
from overlapmamba.synth.trajectory import DriveParams, plan_drive, plan_route
from overlapmamba.synth.truth import read_overlaps
from overlapmamba.synth.world import WorldParams, build_world

SMALL = {"nx": 3, "ny": 3, "block_min": 50.0, "block_max": 65.0}
TINY = PRESETS["tiny"]  # the session-wide ``tiny_seq`` fixture (conftest) is this preset


def _digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


# ---- world -----------------------------------------------------------------------------------
def test_town_has_every_district_repeated_types_and_is_deterministic():
    w = build_world(11, WorldParams())
    assert {s.district for s in w.network.streets} == set(DISTRICTS)
    kinds = {k for _, k in w.footprints}
    assert {"urban", "house", "hall"} <= kinds
    # Look-alike places: house types come from a small catalogue, so sizes repeat.
    sizes = [
        tuple(np.round(np.linalg.norm(np.diff(c[:3], axis=0), axis=1), 3))
        for c, k in w.footprints
        if k == "house"
    ]
    assert len(sizes) > 2 * len(set(sizes))
    assert np.isfinite(w.static.tris).all() and len(w.static) > 100_000
    assert {MAT["foliage"], MAT["kerb"], MAT["pole"], MAT["asphalt"]} <= set(
        np.unique(w.static.mat)
    )
    again = build_world(11, WorldParams())
    np.testing.assert_array_equal(again.static.tris, w.static.tris)
    other = build_world(12, WorldParams())
    assert len(other.static) != len(w.static) or not np.array_equal(
        other.static.tris, w.static.tris
    )


def test_intersections_meet_at_varied_angles():
    net = build_world(5, WorldParams()).network
    angles = []
    for node, nbrs in net.adjacency.items():
        dirs = []
        for _, k in nbrs:
            pts = net.streets[k].oriented(node)
            d = pts[3] - pts[0]
            dirs.append(np.degrees(np.arctan2(d[1], d[0])))
        dirs = np.sort(dirs)
        angles += list(np.diff(np.concatenate([dirs, dirs[:1] + 360])))
    angles = np.array(angles)
    assert angles.std() > 10  # not a perfect grid of 90° corners
    assert (angles < 70).any()  # oblique streets make acute corners


# ---- driving ---------------------------------------------------------------------------------
def test_routes_never_u_turn_and_revisit_both_ways():
    net = build_world(5, WorldParams()).network
    route, revisits = plan_route(net, np.random.default_rng(3), 15_000, DriveParams())
    for a, b, c in zip(route, route[1:], route[2:], strict=False):
        assert not (a == c and len(net.adjacency[b]) > 1), f"U-turn at node {b}"
    reversed_ = [r["reversed"] for r in revisits]
    assert len(revisits) >= 10
    assert np.mean(reversed_) >= 0.4
    assert not all(reversed_)
    assert max(r["age_m"] for r in revisits) > 1500  # some revisits are long after the first
    # Revisits do not chain: the drive explores between them, and reaches most of the town.
    gap = DriveParams().revisit_every[0]
    for a, b in itertools.pairwise(revisits):
        assert b["start_m"] >= a["end_m"] + gap
    driven = {frozenset(e) for e in itertools.pairwise(route)}
    assert len(driven) > 0.6 * len(net.streets)


@pytest.mark.parametrize(
    ("seed", "world", "drive"), [(5, SMALL, {}), (TINY.seed, TINY.world, TINY.drive)]
)
def test_drive_speed_heading_and_height_are_realistic(seed, world, drive):
    w = build_world(seed, WorldParams(**world))
    p = DriveParams(**{k: tuple(v) if isinstance(v, list) else v for k, v in drive.items()})
    d = plan_drive(w.network, w.terrain, np.random.default_rng([seed, 0xD21]), 600, p)
    assert p.v_min - 1e-6 <= d.speed.min() and d.speed.max() <= p.v_max + 1e-6
    step = np.linalg.norm(np.diff(d.poses[:, :3, 3], axis=0), axis=1)
    np.testing.assert_allclose(
        step, (d.speed[1:] + d.speed[:-1]) / 2 / p.rate_hz, rtol=0.1, atol=0.05
    )
    # Heading within each sweep too (firing instants 10 ms apart): no cusps at sharp turns.
    fine = d.pose_at(np.arange(d.times[0], d.times[-1], 0.01))
    yaw = np.unwrap(np.arctan2(fine[:, 1, 0], fine[:, 0, 0]))
    assert np.degrees(np.abs(np.diff(yaw))).max() < 2.0  # < 200°/s
    assert np.degrees(np.abs(np.diff(yaw))).sum() > 180  # but it does turn
    ground = w.terrain.height(d.poses[:, :2, 3])
    np.testing.assert_allclose(d.poses[:, 2, 3] - ground, p.mount_height, atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(d.poses[:, :3, :3]), 1.0, atol=1e-9)


def test_parked_cars_change_between_visits_not_between_scans():
    w = build_world(5, WorldParams(**SMALL))
    dyn = Dynamics(w, 5, 1000.0)
    c = w.parking[len(w.parking) // 2, :2]
    a, b = dyn.mesh_at(100.0, c, 60.0), dyn.mesh_at(100.1, c, 60.0)
    later = dyn.mesh_at(400.0, c, 60.0)
    parked = lambda m: m.tris[m.mat == MAT["car"]].reshape(-1, 9)  # noqa: E731
    static_a = {tuple(np.round(t, 2)) for t in parked(a)}
    assert len(static_a & {tuple(np.round(t, 2)) for t in parked(b)}) > 0.8 * len(static_a)
    assert len(static_a & {tuple(np.round(t, 2)) for t in parked(later)}) < 0.7 * len(static_a)


# ---- sensor ----------------------------------------------------------------------------------
def _plane(z: float, half: float = 300.0, mat: str = "asphalt") -> Mesh:
    a, b, c, d = [(-half, -half, z), (half, -half, z), (half, half, z), (-half, half, z)]
    tris = np.array([[a, b, c], [a, c, d]], np.float32)
    return Mesh(tris, np.full(2, MAT[mat], np.uint8), np.full(2, 0.3, np.float32))


def _still(pose: np.ndarray):
    return lambda t: np.repeat(pose[None], len(np.atleast_1d(t)), axis=0)


def test_scanner_sees_flat_ground_at_the_right_ranges():
    lidar = get_lidar("kitti-hdl64")
    height = MOUNTINGS["car"].height
    pose = np.eye(4)
    pose[2, 3] = height
    pts = Scanner(_plane(0.0), lidar).scan(
        _still(pose), 0.0, Mesh.empty(), np.random.default_rng(0)
    )
    assert pts.dtype == np.float32 and pts.shape[1] == 4
    assert np.abs(pts[:, 2] + height).max() < 0.2  # 2 cm noise along the ray
    horiz = np.linalg.norm(pts[:, :2], axis=1)
    # The ego car hides the nearest ground ahead and behind, not to the sides.
    ahead = np.abs(pts[:, 1]) < 0.5
    assert horiz[ahead].min() > 3.5
    assert horiz[~ahead].min() < 4.2
    assert pts[:, 3].min() > 0 and pts[:, 3].max() <= 0.99


def _firing_fraction(pts: np.ndarray, columns: int) -> np.ndarray:
    """Each point's azimuth in firings after the locked head's nearest one, in [−½, ½): the
    head fires at azimuth π − 2π(k + ½)/columns (clockwise)."""
    az = np.arctan2(pts[:, 1].astype(np.float64), pts[:, 0].astype(np.float64))
    k = ((np.pi - az) / (2 * np.pi) * columns - 0.5) % columns
    return (k + 0.5) % 1.0 - 0.5


def test_a_drifting_scan_fires_a_fraction_of_a_spacing_later():
    """phase 0 fires where every locked turn does; phase φ a fraction φ of a firing's
    spacing later at every firing, with every other draw (noise, dropout) the same."""
    lidar = get_lidar("kitti-hdl64")
    scanner = Scanner(_room(), lidar, Mounting("pole", 5.0))
    pose = np.eye(4)
    pose[2, 3] = 5.0
    scan = lambda phase: scanner.scan(  # noqa: E731
        _still(pose), 0.0, Mesh.empty(), np.random.default_rng(3), phase
    )
    locked, default = (
        scan(0.0),
        scanner.scan(_still(pose), 0.0, Mesh.empty(), np.random.default_rng(3)),
    )
    assert np.array_equal(locked, default)
    assert np.abs(_firing_fraction(locked, lidar.columns)).max() < 1e-3
    for phase in (0.25, 0.7):
        pts = scan(phase)
        late = _firing_fraction(pts, lidar.columns)
        want = (phase + 0.5) % 1.0 - 0.5
        assert np.abs(late - want).max() < 1e-3, phase
        assert abs(len(pts) - len(locked)) < 0.01 * len(locked)
    with pytest.raises(ValueError, match=r"phase must be in \[0, 1\)"):
        scan(1.0)


def test_a_drifting_town_differs_from_its_locked_twin_only_in_its_firings(tmp_path):
    """The same drive and draws, the firings moved; the locked config dumps as before the
    field existed (old manifests stay equal to their presets)."""
    cfg = GenConfig(seed=9, frames=4, world={"nx": 2, "ny": 2}, pair_table="none")
    assert "firing_phase" not in cfg.model_dump()
    drift = cfg.model_copy(update={"firing_phase": "drifting"})
    generate(tmp_path / "a", cfg, workers=1, progress=False)
    generate(tmp_path / "b", drift, workers=1, progress=False)
    assert read_manifest(tmp_path / "b")["config"]["firing_phase"] == "drifting"
    assert "firing_phase" not in read_manifest(tmp_path / "a")["config"]
    for k in range(4):
        a = np.fromfile(tmp_path / "a" / "velodyne" / f"{k:06d}.bin", np.float32).reshape(-1, 4)
        b = np.fromfile(tmp_path / "b" / "velodyne" / f"{k:06d}.bin", np.float32).reshape(-1, 4)
        assert abs(len(a) - len(b)) < 0.02 * len(a) and not np.array_equal(a[:100], b[:100])
    generate(tmp_path / "c", drift, workers=2, progress=False)  # drawn per scan, not per worker
    assert _digest(tmp_path / "c") == _digest(tmp_path / "b")
    phases = np.array([firing_phase(cfg.session_seed(), k) for k in range(200)])
    assert ((phases >= 0) & (phases < 1)).all() and np.histogram(phases, 4, (0, 1))[0].min() > 30
    assert "test-drift" in PRESETS and PRESETS["test-drift"].firing_phase == "drifting"
    locked = {"firing_phase": "locked", "preset": "test"}
    assert PRESETS["test-drift"].model_copy(update=locked) == PRESETS["test"]


def _room(half: float = 15.0, height: float = 40.0) -> Mesh:
    """A closed box around the sensor: every ray hits something within ≈ 50 m."""
    tris = []
    for x0, y0, x1, y1 in [(-1, -1, 1, -1), (1, -1, 1, 1), (1, 1, -1, 1), (-1, 1, -1, -1)]:
        a, b = (x0 * half, y0 * half, 0.0), (x1 * half, y1 * half, 0.0)
        c, d = (x1 * half, y1 * half, height), (x0 * half, y0 * half, height)
        tris += [[a, b, c], [a, c, d]]
    floor_ = _plane(0.0, half).tris.tolist()
    roof = _plane(height, half).tris.tolist()
    tris = np.array(tris + floor_ + roof, np.float32)
    return Mesh(
        tris, np.full(len(tris), MAT["facade"], np.uint8), np.full(len(tris), 0.8, np.float32)
    )


@pytest.mark.parametrize("name", sorted(CATALOGUE))
def test_every_catalogue_sensor_renders_its_own_beams(name):
    """Each ring of a rendered scan lies on its sensor's elevation table, every beam returns,
    and a turn holds at most beams × columns points: nearly all of them in a closed room."""
    sensor = CATALOGUE[name]
    scanner = Scanner(_room(), get_lidar(name), Mounting("pole", 5.0))  # nothing below it
    pose = np.eye(4)
    pose[2, 3] = 5.0  # high enough that the room's floor lies within every sensor's range
    pts = scanner.scan(_still(pose), 0.0, Mesh.empty(), np.random.default_rng(0))
    r = np.linalg.norm(pts[:, :3], axis=1)
    el = np.degrees(np.arcsin(pts[:, 2] / r))
    table = np.asarray(sensor.elevations_deg)
    off = np.abs(el[:, None] - table[None]).min(1)
    assert off.max() < 0.01, f"{name}: a point {off.max():.3f}° off its table"
    assert set(np.abs(el[:, None] - table[None]).argmin(1)) == set(range(sensor.beams))
    assert (r > sensor.min_range).all() and (r < sensor.max_range).all()
    rays = sensor.returns_per_turn - int(scanner.blocked.sum())
    assert len(pts) <= sensor.returns_per_turn and len(pts) > 0.9 * rays


def test_a_tilted_low_mount_keeps_the_table_and_its_poses_carry_the_tilt():
    cfg = GenConfig(seed=9, frames=6, sensor="xt32", mount="backpack", world={"nx": 2, "ny": 2})
    m = cfg.mounting()
    assert (m.height, m.pitch_deg) == (1.80, 5.0)
    _, drive, _ = build_scene(cfg)
    level = build_scene(cfg.model_copy(update={"mount_pitch_deg": 0.0}))[1]
    # the sensor's forward axis points 5° below the platform's
    fwd, flat = drive.poses[:, :3, 0], level.poses[:, :3, 0]
    angle = np.degrees(np.arccos(np.clip((fwd * flat).sum(1), -1, 1)))
    np.testing.assert_allclose(angle, 5.0, atol=1e-6)
    assert (fwd[:, 2] < flat[:, 2]).all()
    np.testing.assert_allclose(drive.poses[:, :3, 3], level.poses[:, :3, 3])
    # rendered in the tilted frame, the rings still lie on the table; the ground is tilted
    pose = np.eye(4)
    pose[:3, :3] = m.tilt()
    pose[2, 3] = m.height
    pts = Scanner(_plane(0.0), get_lidar("xt32"), m).scan(
        _still(pose), 0.0, Mesh.empty(), np.random.default_rng(0)
    )
    el = np.degrees(np.arcsin(pts[:, 2] / np.linalg.norm(pts[:, :3], axis=1)))
    assert np.abs(el[:, None] - np.asarray(CATALOGUE["xt32"].elevations_deg)).min(1).max() < 0.01
    ahead, behind = pts[pts[:, 0] > 5], pts[pts[:, 0] < -5]
    assert np.median(ahead[:, 2]) > np.median(behind[:, 2]) + 0.5  # ground rises ahead


def test_the_mountings_bodies_hide_the_ground_they_shadow():
    nearest: dict[str, float] = {}
    for name in ("car", "robot", "amr"):
        m = MOUNTINGS[name]
        pose = np.eye(4)
        pose[2, 3] = m.height
        pts = Scanner(_plane(0.0), get_lidar("os0-128"), m).scan(
            _still(pose), 0.0, Mesh.empty(), np.random.default_rng(0)
        )
        ahead = pts[(np.abs(pts[:, 1]) < 0.2) & (pts[:, 0] > 0)]
        nearest[name] = float(ahead[:, 0].min())
        # the front box's edge casts the shadow: the ground nearer than its line of sight
        _, x1, _, top = max(m.body, key=lambda box: box[1])
        shadow = m.height * x1 / -top
        assert shadow * 0.97 <= nearest[name] < shadow * 1.5, name
    with pytest.raises(ValueError, match="allowed: car, robot, amr, backpack"):
        get_mounting("drone")


def test_porous_surfaces_let_some_rays_through():
    lidar = get_lidar("hdl32")
    pose = np.eye(4)
    pose[2, 3] = MOUNTINGS["car"].height

    # A foliage wall 10 m ahead of a backstop wall at 20 m.
    def wall(x: float, mat: str) -> Mesh:
        a, b, c, d = [(x, -50, -5), (x, 50, -5), (x, 50, 20), (x, -50, 20)]
        tris = np.array([[a, b, c], [a, c, d]], np.float32)
        return Mesh(tris, np.full(2, MAT[mat], np.uint8), np.full(2, 0.4, np.float32))

    static = Mesh.concat([wall(10.0, "foliage"), wall(20.0, "facade")])
    pts = Scanner(static, lidar).scan(_still(pose), 0.0, Mesh.empty(), np.random.default_rng(1))
    # Rays (not a box of space) aimed at both walls: azimuth within ±8°, elevation −2…8°.
    az = np.degrees(np.arctan2(pts[:, 1], pts[:, 0]))
    el = np.degrees(np.arcsin(pts[:, 2] / np.linalg.norm(pts[:, :3], axis=1)))
    x = pts[(np.abs(az) < 8) & (el > -2) & (el < 8), 0]
    through = (np.abs(x - 20) < 0.3).mean()
    assert 0.2 < through < 0.5  # foliage passes 35 % of rays
    assert (np.abs(x - 10) < 0.3).mean() + through > 0.97


# ---- generated sequences ---------------------------------------------------------------------
def test_sequence_reads_as_kitti_with_ground_truth(tiny_seq):
    seq = open_sequence(tiny_seq)
    assert len(seq) == TINY.frames
    np.testing.assert_allclose(seq.poses[0], np.eye(4), atol=1e-9)
    scan = seq.points(10)
    assert scan.intensity is not None and 80_000 < len(scan) < 150_000  # HDL-64E, KITTI-like
    raw = np.fromfile(seq.scan_paths[10], dtype="<f4")
    assert raw.size % 4 == 0
    times = np.loadtxt(tiny_seq / "times.txt")
    np.testing.assert_allclose(np.diff(times), 0.1, atol=1e-6)
    man = read_manifest(tiny_seq)
    assert man["config"]["seed"] == TINY.seed and man["generator_version"]
    assert man["counts"]["frames"] == TINY.frames
    assert (tiny_seq / "map.png").stat().st_size > 10_000


def test_adjacent_scans_overlap_and_distant_scans_do_not(tiny_seq):
    table = read_overlaps(tiny_seq)
    adjacent = table["query"] - table["reference"] == 1
    assert table["overlap"][adjacent].min() > 0.7
    seq = open_sequence(tiny_seq)
    pos = seq.positions()
    q = 250
    dist = np.linalg.norm(pos - pos[q], axis=1)
    far = np.argsort(dist)[-60::10]  # six of the farthest scans in this small town
    assert dist[far].min() > 60
    ov, _ = overlap_and_yaw(
        seq.points(q).xyz,
        seq.poses[q],
        [seq.points(int(j)).xyz for j in far],
        seq.poses[far],
        get_profile(TINY.sensor),
    )
    assert ov.max() < 0.05


def test_loops_exist_in_both_directions_and_are_reused(tiny_seq, monkeypatch):
    man = read_manifest(tiny_seq)["counts"]["ground_truth"]
    assert man["same_direction_queries"] > 0 and man["reverse_direction_queries"] > 0
    seq = open_sequence(tiny_seq)
    # The shipped loop table is found by overlapmamba.core and used as is: no overlap is recomputed.
    import overlapmamba.core.overlap as overlap_mod

    monkeypatch.setattr(overlap_mod, "pair_overlaps", lambda *a, **k: pytest.fail("recomputed"))
    gt = loop_ground_truth(seq, get_profile(TINY.sensor), LoopParams(radius=12.0), progress=False)
    assert gt.is_loop.sum() == man["loop_pairs"]
    yaws = np.abs(gt.yaw_deg[gt.is_loop])
    assert (yaws > 150).any() and (yaws < 30).any()


def test_loop_only_pair_table_gives_the_same_loop_table_and_cannot_be_trained_on(
    tiny_seq, tmp_path
):
    """Held-out towns compute only the loop candidates (pairs more than loop_exclude frames
    apart): the loop table must be the very one that the full pair table gives. (Within 6 m
    instead of the preset's 12, a quarter of the work: the shipped table restricted to 6 m.)"""
    import shutil

    from overlapmamba.core.errors import DatasetError
    from overlapmamba.core.overlap import LoopGroundTruth
    from overlapmamba.synth.truth import compute_ground_truth
    from overlapmamba.train.batches import read_pair_table

    copy = tmp_path / "tiny"
    shutil.copytree(tiny_seq, copy)
    radius = 6.0
    cfg = TINY.model_copy(update={"pair_table": "loops", "gt_radius": radius})
    table, loops = compute_ground_truth(copy, cfg, workers=2, progress=False)
    full = read_overlaps(tiny_seq)
    assert (table["query"] - table["reference"] > TINY.loop_exclude).all()
    assert 0 < len(table["query"]) < len(full["query"]) / 4
    shipped = LoopGroundTruth.load(tiny_seq / "ground_truth" / "loops.npz")
    near = shipped.distance < radius
    for name in ("query", "reference", "overlap", "yaw_deg", "distance"):
        np.testing.assert_array_equal(getattr(loops, name), getattr(shipped, name)[near])
    same = {k: v for k, v in shipped.params.items() if k not in ("radius", "fingerprint")}
    assert {k: loops.params[k] for k in same} == same and loops.params["radius"] == radius
    assert loops.is_loop.sum() > 0
    with pytest.raises(DatasetError, match="pair_table='loops'.*needs pair_table='all'"):
        read_pair_table(copy)
    read_pair_table(tiny_seq)  # a training town's table is accepted


def test_same_seed_gives_byte_identical_output(tmp_path):
    cfg = GenConfig(seed=9, frames=6, sensor="hdl32", world={"nx": 2, "ny": 2}, gt_radius=10.0)
    generate(tmp_path / "a", cfg, workers=1, progress=False)
    generate(tmp_path / "b", cfg, workers=2, progress=False)
    a, b = _digest(tmp_path / "a"), _digest(tmp_path / "b")
    assert a == b and "map.png" in a and "ground_truth/overlaps.npz" in a
    generate(tmp_path / "c", cfg.model_copy(update={"seed": 10}), workers=1, progress=False)
    assert _digest(tmp_path / "c")["velodyne/000000.bin"] != a["velodyne/000000.bin"]


def test_generate_refuses_a_non_empty_folder_and_bad_config(tmp_path):
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "keep.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="not empty"):
        generate(tmp_path / "x", GenConfig(seed=1, frames=2), progress=False)
    assert (tmp_path / "x" / "keep.txt").read_text() == "mine"
    with pytest.raises(ValueError, match="allowed: hdl32, hdl64e, kitti-hdl64, os0-128"):
        GenConfig(seed=1, frames=2, sensor="ouster")
    with pytest.raises(ValueError, match="allowed: car, robot"):
        GenConfig(seed=1, frames=2, mount="drone")
    with pytest.raises(ValueError, match="allowed"):
        GenConfig(seed=1, frames=2, world={"towers": 3}).world_params()


def test_presets_are_fixed_distinct_towns_that_plan():
    rigs = {
        (
            *(c.seed, c.session, c.sensor, c.mount, c.mount_height),
            *(c.mount_pitch_deg, c.mount_roll_deg, c.firing_phase),
        )
        for c in PRESETS.values()
    }
    assert len(rigs) == len(PRESETS) and PRESETS["test"].split == "test"
    tests = [c for c in PRESETS.values() if c.split == "test"]
    evals = [c for c in PRESETS.values() if c.split != "train"]
    trains = [c for c in PRESETS.values() if c.split == "train"]
    assert not {c.seed for c in evals} & {c.seed for c in trains}  # no held-out town trained on
    assert {c.seed for c in tests}.isdisjoint({c.seed for c in evals if c.split == "val"})
    # every catalogue sensor has a validation and a test town: one drive, rendered by each
    for split in ("val", "test"):
        towns = [PRESETS[f"{split}-{name}"] for name in CATALOGUE]
        assert len({(c.seed, c.session, c.frames) for c in towns}) == 1
    planned = {}
    # two of the drawn towns plan here (the rest, and their level car renderings: same code)
    drawn = {*DRAWN_PRESETS[2:], *(f"{k}-car" for k in DRAWN_PRESETS)}
    for cfg in (c for k, c in PRESETS.items() if k not in drawn):  # a drive depends on the
        # town, the session and its length
        key = (cfg.seed, cfg.session, cfg.frames, json.dumps(cfg.world), json.dumps(cfg.drive))
        if key not in planned:
            planned[key] = len(build_scene(cfg)[1].poses)
        assert planned[key] == cfg.frames


def test_drawn_towns_are_fixed_and_cover_every_sensor_and_mounting():
    towns = [PRESETS[k] for k in DRAWN_PRESETS]
    assert [drawn_town(k) for k in range(len(towns))] == towns  # the index alone fixes a town
    assert {c.sensor for c in towns[: len(CATALOGUE)]} == set(CATALOGUE)
    assert [c.sensor for c in towns[:5]] == ["vlp16", "os0-128", "xt32", "os1-128", "hdl32"]
    assert {c.mount for c in towns} == set(MOUNTINGS)
    assert len({json.dumps(c.world, sort_keys=True) for c in towns}) > 1
    for c in towns:
        assert c.split == "train" and c.pair_table == "all" and c.frames == 1000
        low, high = {"car": (1.5, 2.2), "robot": (0.5, 1.0), "amr": (0.25, 0.5)}.get(
            c.mount, (1.5, 2.0)
        )
        assert low <= c.mount_height <= high and abs(c.mount_roll_deg) <= 3.0
        assert (
            (0 <= c.mount_pitch_deg <= 10)
            if c.mount == "backpack"
            else (abs(c.mount_pitch_deg) <= 3.0)
        )
        m = c.mounting()  # the drive's own height and tilt, as the generator uses them
        assert (m.height, m.pitch_deg) == (c.mount_height, c.mount_pitch_deg)
    for k, c in enumerate(towns[:6]):  # the mounting's ablation: the same drive, on a car
        car = PRESETS[f"train-x{k:02d}-car"]
        assert car == drawn_town(k, mounted=False) and car.mounting() == MOUNTINGS["car"]
        assert (car.seed, car.sensor, car.world, car.frames) == (c.seed, c.sensor, c.world, 1000)


@pytest.mark.real_data
def test_sim_report_compares_with_real_kitti(
    tiny_seq, kitti_seq_dir, kitti_reference_dir, tmp_path
):
    from typer.testing import CliRunner

    from overlapmamba.cli import app

    res = CliRunner().invoke(
        app,
        [
            "sim-report",
            "--synthetic",
            str(tiny_seq),
            "--real",
            str(kitti_seq_dir),
            "--reference",
            str(kitti_reference_dir),
            "--scans",
            "4",
            "--out",
            str(tmp_path / "r"),
        ],
    )
    assert res.exit_code == 0, res.output
    report = json.loads((tmp_path / "r" / "realism.json").read_text())
    stats = {r["statistic"] for r in report["rows"]}
    assert {
        "points per scan",
        "range histogram",
        "empty range-image pixels",
        "ground-return fraction",
        "intensity histogram",
    } <= stats
    assert report["compared_within_m"] <= 81
    assert (tmp_path / "r" / "realism.png").stat().st_size > 10_000
    # found in review: a --reference that is not there (a typo) read as "no intensity"
    args = ["sim-report", "--synthetic", str(tiny_seq), "--reference", str(tmp_path / "nope")]
    res = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "r2")])
    said = " ".join(res.output.replace("│", " ").split())
    assert res.exit_code == 2 and "does not exist" in said, said
    assert not (tmp_path / "r2").exists()


# ---- command line ----------------------------------------------------------------------------
def _plain(output: str) -> str:
    """CLI output without Rich's box drawing, whitespace collapsed."""
    return " ".join(output.replace("│", " ").replace("╭", " ").replace("╰", " ").split())


def test_gen_data_command_writes_a_sequence(tmp_path):
    from typer.testing import CliRunner

    from overlapmamba.cli import app

    out = tmp_path / "seq"
    args = ["gen-data", str(out), "--seed", "3", "--frames", "4", "--sensor", "hdl32"]
    res = CliRunner().invoke(
        app, [*args, "--nodes", "2", "--gt-radius", "5", "--workers", "1", "-q"]
    )
    assert res.exit_code == 0, res.output
    assert "Synthetic sequence" in res.output and "scans/s" in res.output
    assert len(open_sequence(out)) == 4
    assert read_manifest(out)["config"]["sensor"] == "hdl32"
    assert not (out / ".incomplete").exists() and not (out / ".manifest.json.tmp").exists()
    again = CliRunner().invoke(app, [*args, "-q"])
    assert again.exit_code == 2 and "is not empty" in _plain(again.output)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--preset", "test", "--seed", "1"], "--preset fixes seed"),
        (["--preset", "test", "--split", "train"], "town size and split"),  # was ignored
        (["--preset", "nope"], "allowed: train, train-b"),
        (["--frames", "10"], "give --seed and --frames"),
        (["--seed", "1", "--frames", "10", "--sensor", "mid360"], "allowed: hdl32, hdl64e"),
        (["--preset", "test", "--mount", "drone"], "allowed: car, robot"),
        (["--seed", "1", "--frames", "1"], "greater than or equal to 2"),
        (["--seed", "1", "--frames", "4", "--stall-timeout", "0"], "greater than or equal to 1"),
        (["--preset", "test", "--firing-phase", "random"], "'locked' or 'drifting'"),
    ],
)
def test_gen_data_refuses_bad_options(tmp_path, args, message):
    from typer.testing import CliRunner

    from overlapmamba.cli import app

    res = CliRunner().invoke(app, ["gen-data", str(tmp_path / "x"), *args])
    assert res.exit_code == 2
    assert message in _plain(res.output), res.output
    assert not (tmp_path / "x").exists()


def test_gen_data_session_0_is_the_first_drive_of_a_later_drives_preset(tmp_path, monkeypatch):
    """Found in review: `--preset val-s1 --session 0` (0 is falsy) kept the preset's session."""
    from typer.testing import CliRunner

    from overlapmamba.cli import app

    made = []

    def capture(out_dir, cfg, *args, **kwargs):  # type: ignore[no-untyped-def]
        made.append(cfg)
        raise OSError("stop here")  # the config is what is checked

    monkeypatch.setattr("overlapmamba.synth.generate.generate", capture)
    for extra, session in (([], 1), (["--session", "0"], 0), (["--session", "3"], 3)):
        CliRunner().invoke(app, ["gen-data", str(tmp_path / "x"), "--preset", "val-s1", *extra])
        assert made.pop().session == session, extra


def test_gen_data_reports_a_failed_worker_and_exits_1(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    import overlapmamba.synth.generate as gen
    from overlapmamba.cli import app
    from overlapmamba.core.errors import DatasetError
    from overlapmamba.synth.workers import WorkerError

    def dies(*args, **kwargs):
        raise WorkerError("a worker process died while running scan 2")
        yield  # a generator, like run_jobs

    monkeypatch.setattr(gen, "run_jobs", dies)
    out = tmp_path / "seq"
    args = ["gen-data", str(out), "--seed", "3", "--frames", "4", "--sensor", "hdl32", "-q"]
    res = CliRunner().invoke(app, [*args, "--nodes", "2", "--workers", "2"])
    assert res.exit_code == 1
    assert "died while running scan 2" in _plain(res.output)
    assert "is incomplete: delete it" in _plain(res.output)
    # what it left is never read as a sequence (its marker says it did not finish)
    with pytest.raises(DatasetError, match="never finished"):
        open_sequence(out)
    (tmp_path / "a-file").write_text("")
    res = CliRunner().invoke(app, ["gen-data", str(tmp_path / "a-file" / "seq"), *args[2:]])
    assert res.exit_code == 2 and "Not a directory" in _plain(res.output), res.output


def test_a_second_session_drives_the_same_town_with_other_cars_and_route():
    from overlapmamba.synth.generate import build_scene

    cfg = GenConfig(seed=9, frames=40, sensor="hdl32", world={"nx": 2, "ny": 2})
    w0, d0, dyn0 = build_scene(cfg)
    w1, d1, dyn1 = build_scene(cfg.model_copy(update={"session": 1}))
    np.testing.assert_array_equal(w0.static.tris, w1.static.tris)  # the same static town
    assert not np.allclose(d0.poses[:, :3, 3], d1.poses[:, :3, 3])  # another drive
    assert not np.array_equal(dyn0.park_on, dyn1.park_on)  # other parked cars
    again = build_scene(cfg.model_copy(update={"session": 1}))[1]
    np.testing.assert_array_equal(again.poses, d1.poses)  # a session is reproducible
    assert cfg.session_seed() == [9]  # session 0: the seed alone, as before sessions existed
    with pytest.raises(ValueError, match="less than or equal to 1000"):
        GenConfig(seed=9, frames=4, session=1001)


@pytest.mark.parametrize("first,second", [("test", "test-s1"), ("val", "val-s1")])
def test_a_second_session_keeps_to_the_first_sessions_streets(first, second):
    """The cross-session protocol needs every query of session 1 to have a place in session 0:
    session 1 re-drives session 0's streets (in its own order, both directions)."""
    from scipy.spatial import cKDTree

    from overlapmamba.synth.generate import build_scene
    from overlapmamba.synth.trajectory import driven_streets

    assert PRESETS[second].split == PRESETS[first].split  # a val session is selection data
    w0, d0, _ = build_scene(PRESETS[first])
    d1 = build_scene(PRESETS[second])[1]
    net = w0.network
    assert set(driven_streets(net, d1)) <= set(driven_streets(net, d0))
    tree = cKDTree(d0.poses[:, :2, 3])
    gap, near = tree.query(d1.poses[:, :2, 3])
    assert gap.max() < 5.0, gap.max()  # lanes are ≈3 m apart
    h0, h1 = (np.arctan2(d.poses[:, 1, 0], d.poses[:, 0, 0]) for d in (d0, d1))
    reverse = np.abs(np.angle(np.exp(1j * (h1 - h0[near])))) > np.pi / 2
    assert 0.1 < reverse.mean() < 0.9  # places met in both directions


def test_gen_data_session_option_is_recorded(tmp_path):
    from typer.testing import CliRunner

    from overlapmamba.cli import app

    out = tmp_path / "s1"
    args = ["gen-data", str(out), "--seed", "3", "--session", "2", "--frames", "3"]
    res = CliRunner().invoke(
        app, [*args, "--sensor", "hdl32", "--nodes", "2", "--no-ground-truth", "-q"]
    )
    assert res.exit_code == 0, res.output
    assert read_manifest(out)["config"]["session"] == 2 and "3 / 2 / hdl32" in res.output
    assert "firing_phase" not in read_manifest(out)["config"]  # locked, as before
    drift = ["gen-data", str(tmp_path / "d"), *args[2:], "--firing-phase", "drifting"]
    res = CliRunner().invoke(app, [*drift, "--nodes", "2", "--no-ground-truth", "-q"])
    assert res.exit_code == 0, res.output
    assert read_manifest(tmp_path / "d")["config"]["firing_phase"] == "drifting"
