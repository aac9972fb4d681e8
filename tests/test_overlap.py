"""Overlap ground truth (OverlapNet's definition) and the loop table."""

from __future__ import annotations

import numpy as np
import pytest

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.overlap import (
    LoopGroundTruth,
    LoopParams,
    candidate_pairs,
    loop_ground_truth,
    overlap_and_yaw,
    pair_overlaps,
)
from overlapmamba.core.poses import rotation_z, transform_points
from overlapmamba.core.projection import project
from overlapmamba.core.sensors import get_profile

KITTI = get_profile("kitti-hdl64")


def overlap_reference(q_xyz, q_pose, r_xyz, r_pose, profile, tau=1.0):
    """One pair, spelled out step by step."""
    rel = np.linalg.inv(q_pose) @ r_pose
    ref = project(transform_points(r_xyz, rel), profile)
    cur = project(q_xyz, profile)
    empty = np.float32(profile.empty_value)
    both = (ref != empty) & (cur != empty)
    return (both & (np.abs(ref - cur) < tau)).sum() / (cur != empty).sum()


def test_self_overlap_is_one_and_yaw_is_recovered(synthetic_seq_dir):
    seq = open_sequence(synthetic_seq_dir)
    xyz = seq.points(3).xyz
    turned = transform_points(xyz, rotation_z(-40.0))  # same place, sensor turned by +40°
    pose_turned = seq.poses[3] @ rotation_z(40.0)
    ov, yaw = overlap_and_yaw(
        xyz, seq.poses[3], [xyz, turned], np.stack([seq.poses[3], pose_turned]), KITTI
    )
    assert ov[0] == pytest.approx(1.0)
    assert ov[1] > 0.97  # float rounding moves a few points across pixel boundaries
    assert yaw.tolist() == pytest.approx([0.0, 40.0], abs=1e-4)


def overlaps_against(seq, query: int, refs) -> tuple[np.ndarray, np.ndarray]:
    refs = np.asarray(refs)
    return overlap_and_yaw(
        seq.points(query).xyz,
        seq.poses[query],
        [seq.points(int(j)).xyz for j in refs],
        seq.poses[refs],
        KITTI,
    )


def test_vectorised_overlap_matches_pairwise_reference(kitti_seq_dir):
    seq = open_sequence(kitti_seq_dir)
    refs = [40, 45, 49, 50, 60, 90]
    ov, _ = overlaps_against(seq, 50, refs)
    expected = [
        overlap_reference(seq.points(50).xyz, seq.poses[50], seq.points(j).xyz, seq.poses[j], KITTI)
        for j in refs
    ]
    np.testing.assert_allclose(ov, expected, atol=1e-6)


def test_overlap_falls_with_distance_on_real_kitti(kitti_seq_dir):
    seq = open_sequence(kitti_seq_dir)
    ov, yaw = overlaps_against(seq, 50, [49, 51, 30, 0])
    assert ov[0] > 0.7 and ov[1] > 0.7  # adjacent frames, ≈1 m apart
    assert ov[0] > ov[2] > ov[3]
    assert ov[3] < 0.05  # 45 m apart
    assert np.abs(yaw).max() < 10  # a straight drive


def test_candidate_pairs_respect_radius_and_gap():
    pos = np.array([[0, 0, 0], [1, 0, 0], [50, 0, 0], [0.5, 0, 0]], float)
    assert sorted(map(tuple, candidate_pairs(pos, radius=2.0, min_gap=2))) == [(3, 0), (3, 1)]
    assert len(candidate_pairs(pos, radius=2.0)) == 3 * 3 + 1  # incl. i == j


def test_loop_table_finds_the_revisit_and_is_cached(synthetic_seq_dir, tmp_path):
    seq = open_sequence(synthetic_seq_dir)  # 24 frames per lap, 2 laps
    loops = LoopParams(exclude_recent_frames=12, radius=10.0, min_overlap=0.3)
    cache = tmp_path / "gt.npz"
    gt = loop_ground_truth(seq, KITTI, loops, cache=cache, progress=False)
    assert cache.is_file()
    has = gt.has_loop()
    # Frame 23 ends the first lap 6.7 m before frame 0: a genuine loop closure.
    assert not has[:23].any(), "the first lap cannot close a loop before it ends"
    assert has[24:].mean() > 0.9, "nearly every second-lap frame revisits the first lap"
    pos = gt.positives()
    for i in range(24, 48):
        if len(pos[i]):
            assert (i - 24) in pos[i] or ((i - 24) - 1) in pos[i] or ((i - 24) + 1) in pos[i]
    assert (gt.query - gt.reference > 12).all() and (gt.distance < 10).all()
    # Cached: the same object back, bit for bit; other parameters recompute.
    again = loop_ground_truth(seq, KITTI, loops, cache=cache, progress=False)
    np.testing.assert_array_equal(again.overlap, gt.overlap)
    assert LoopGroundTruth.load(cache).params["fingerprint"] == gt.params["fingerprint"]
    other = loop_ground_truth(
        seq, KITTI, loops.model_copy(update={"radius": 5.0}), cache=cache, progress=False
    )
    assert len(other.query) < len(gt.query)


def test_corrupt_cache_is_recomputed(synthetic_seq_dir, tmp_path):
    seq = open_sequence(synthetic_seq_dir)
    cache = tmp_path / "gt.npz"
    cache.write_bytes(b"not a zip file")
    loops = LoopParams(exclude_recent_frames=12, radius=10.0)
    gt = loop_ground_truth(seq, KITTI, loops, cache=cache, progress=False)
    assert len(gt.query) > 0 and LoopGroundTruth.load(cache).n_frames == len(seq)


def test_pair_overlaps_groups_by_query(synthetic_seq_dir):
    seq = open_sequence(synthetic_seq_dir)
    pairs = np.array([[5, 4], [2, 3], [5, 6], [2, 2]])
    ov, _ = pair_overlaps(seq, pairs, KITTI, progress=False)
    assert ov[3] == pytest.approx(1.0)
    single, _ = overlap_and_yaw(
        seq.points(5).xyz, seq.poses[5], [seq.points(6).xyz], seq.poses[[6]], KITTI
    )
    assert ov[2] == pytest.approx(single[0])


def test_pair_overlaps_of_no_pairs_is_empty(synthetic_seq_dir):
    # Regression: a drive that never comes back has no candidate pairs; this used to raise.
    from overlapmamba.core.overlap import pair_overlaps

    seq = open_sequence(synthetic_seq_dir)
    ov, yaw = pair_overlaps(seq, np.zeros((0, 2), np.int64), get_profile("kitti-hdl64"))
    assert ov.shape == yaw.shape == (0,)


def test_a_scan_rewritten_in_place_makes_its_caches_again(synthetic_seq_dir, tmp_path, monkeypatch):
    """The caches' keys read no scan (poses, names and sizes): a scan rewritten in place at
    its size (de-skewed, filtered, simulated again) kept its stale loop table and range
    images. Each records the scans' sampled content beside its key, and is made again when
    that differs."""
    import shutil

    from overlapmamba.train.rangecache import range_images

    monkeypatch.setenv("OVERLAPMAMBA_CACHE", str(tmp_path / "cache"))
    folder = tmp_path / "seq"
    shutil.copytree(synthetic_seq_dir, folder)
    loops = LoopParams(exclude_recent_frames=12, radius=10.0, min_overlap=0.3)
    seq = open_sequence(folder)
    before = loop_ground_truth(seq, KITTI, loops, progress=False)
    images = np.array(range_images(seq, KITTI, progress=False))
    scan = seq.scan_paths[30]
    xyzi = np.fromfile(scan, np.float32).reshape(-1, 4)
    xyzi[:, 0] += 20.0  # moved 20 m: another scene, the same size
    xyzi.tofile(scan)
    seq = open_sequence(folder)
    after = loop_ground_truth(seq, KITTI, loops, progress=False)
    assert after.params["fingerprint"] == before.params["fingerprint"]  # the key is blind
    assert after.params["content"] != before.params["content"]
    mine = (after.query == 30) | (after.reference == 30)
    was = (before.query == 30) | (before.reference == 30)
    assert not np.array_equal(after.overlap[mine], before.overlap[was])
    again = np.array(range_images(seq, KITTI, progress=False))
    assert not np.array_equal(again[30], images[30]) and np.array_equal(again[0], images[0])


def test_a_named_table_file_that_is_something_else_is_refused_not_overwritten(
    synthetic_seq_dir, tmp_path
):
    """Found in review: ``ground-truth --out notes.txt`` replaced the user's file with a loop
    table (an unreadable file was taken for a stale cache). A file that is not a table, by
    content and name, is refused and left as it was; a folder is named as one."""
    from overlapmamba.core.errors import DatasetError

    seq = open_sequence(synthetic_seq_dir)
    empty = tmp_path / "empty.txt"
    empty.write_text("")  # numpy's EOFError, not one of the errors first caught
    with pytest.raises(DatasetError, match="exists and is not a loop table"):
        loop_ground_truth(seq, KITTI, LoopParams(), cache=empty, progress=False)
    notes = tmp_path / "notes.txt"
    notes.write_text("my notes")
    loops = LoopParams(exclude_recent_frames=12, radius=10.0)
    with pytest.raises(DatasetError, match="exists and is not a loop table"):
        loop_ground_truth(seq, KITTI, loops, cache=notes, progress=False)
    assert notes.read_text() == "my notes"
    with pytest.raises(DatasetError, match="is a folder"):
        loop_ground_truth(seq, KITTI, loops, cache=tmp_path, progress=False)
    gt = loop_ground_truth(seq, KITTI, loops, cache=tmp_path / "table.bin", progress=False)
    again = loop_ground_truth(seq, KITTI, loops, cache=tmp_path / "table.bin", progress=False)
    assert np.array_equal(gt.query, again.query)  # a table under another name is one
    with pytest.raises(IsADirectoryError):  # a save that fails leaves no half table beside
        gt.save(tmp_path)
    assert not list(tmp_path.parent.glob(f".{tmp_path.name}.tmp*"))
