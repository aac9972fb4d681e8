"""Poses, calibration and the sequence readers, on real and written data."""

from __future__ import annotations

import numpy as np
import pytest

from overlapmamba.core.datasets import REGISTRY, detect_kind, open_sequence
from overlapmamba.core.errors import DatasetError
from overlapmamba.core.poses import (
    camera_to_lidar,
    read_calib,
    read_poses,
    relative_transform,
    rotation_z,
    write_poses,
    yaw_deg,
)


def test_poses_round_trip_and_reject_junk(tmp_path):
    poses = np.stack([rotation_z(a) for a in (0, 30, -100)])
    poses[:, :3, 3] = [[1, 2, 3], [4, 5, 6], [7, 8, 9]]
    write_poses(tmp_path / "poses.txt", poses)
    np.testing.assert_allclose(read_poses(tmp_path / "poses.txt"), poses, atol=1e-9)
    (tmp_path / "bad.txt").write_text("1 2 3\n")
    with pytest.raises(DatasetError, match="has 3 numbers; expected 12"):
        read_poses(tmp_path / "bad.txt")
    (tmp_path / "nan.txt").write_text(" ".join(["nan"] * 12) + "\n")
    with pytest.raises(DatasetError, match="NaN"):
        read_poses(tmp_path / "nan.txt")


def test_files_saved_with_a_byte_order_mark_are_read(tmp_path):
    """An editor on Windows saves poses.txt and calib.txt with a UTF-8 byte-order mark: the
    first line was read as junk ("non-number '\\ufeff1'", "no 12-number 'Tr:' entry")."""
    poses = np.stack([rotation_z(a) for a in (0, 30)])
    write_poses(tmp_path / "poses.txt", poses)
    text = (tmp_path / "poses.txt").read_text()
    (tmp_path / "poses.txt").write_text(text, encoding="utf-8-sig")
    np.testing.assert_allclose(read_poses(tmp_path / "poses.txt"), poses, atol=1e-9)
    tr = " ".join(["1", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1", "0"])
    (tmp_path / "calib.txt").write_text(f"Tr: {tr}\n", encoding="utf-8-sig")
    np.testing.assert_allclose(read_calib(tmp_path / "calib.txt")["Tr"], np.eye(4))


def test_relative_yaw():
    a, b = rotation_z(10.0), rotation_z(-35.0)
    assert yaw_deg(relative_transform(a, b[None]))[0] == pytest.approx(-45.0)


def test_camera_to_lidar_on_synthetic_calibration():
    # Camera frame: z forward, x right, y down. A LiDAR (x forward, y left, z up) drives forward.
    tr = np.array([[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1]], float)
    cam = np.stack([np.eye(4)] * 3)
    cam[:, 2, 3] = [0, 1, 2]  # forward along camera z
    lidar = camera_to_lidar(cam, tr)
    np.testing.assert_allclose(lidar[:, :3, 3], [[0, 0, 0], [1, 0, 0], [2, 0, 0]], atol=1e-12)


def test_kitti_reader_on_real_sequence(kitti_seq_dir):
    seq = open_sequence(kitti_seq_dir)
    assert detect_kind(kitti_seq_dir) == "kitti" and len(seq) == 101
    calib = read_calib(kitti_seq_dir / "calib.txt")
    assert calib["Tr"].shape == (4, 4) and calib["P0"].shape == (4, 4)
    t = seq.positions()
    # In the LiDAR frame the car drives forward along +x on a flat road (83 m, no revisit).
    assert np.allclose(seq.poses[0], np.eye(4), atol=1e-6)
    assert 75 < t[-1, 0] < 90 and abs(t[-1, 2]) < 3
    assert np.all(np.diff(t[:, 0]) > 0)
    assert len(seq.points(0)) > 100_000


def test_pcd_folder_reader_on_real_nuscenes(nuscenes_dir):
    seq = open_sequence(nuscenes_dir, sensor="hdl32")
    assert detect_kind(nuscenes_dir) == "pcd-folder" and len(seq) == 39
    # Natural order: 0, 1, 2, …, 10 — not 0, 1, 10, 11.
    assert [p.stem for p in seq.scan_paths[:12]] == [str(i) for i in range(12)]
    steps = np.linalg.norm(np.diff(seq.positions(), axis=0), axis=1)
    assert steps.max() < 10 and 80 < steps.sum() < 110


def test_pcd_folder_written(tmp_path):
    from pypcd4 import PointCloud as PcdCloud

    clouds = tmp_path / "clouds"
    clouds.mkdir()
    for i in (0, 1, 2, 10):
        PcdCloud.from_xyz_points(np.full((5, 3), i, np.float32)).save(clouds / f"{i}.pcd")
    write_poses(tmp_path / "poses.txt", np.stack([np.eye(4)] * 4))
    seq = open_sequence(tmp_path)
    assert [float(seq.points(i).xyz[0, 0]) for i in range(4)] == [0, 1, 2, 10]


def test_kitti_scans_named_without_zero_padding_keep_their_order(tmp_path):
    """``0.bin … 11.bin`` sorted as text put 10.bin and 11.bin third and fourth: each scan
    after them went out with another scan's pose and time, without a word. Ordered by the
    number in the name, as the PCD folder's are."""
    velodyne = tmp_path / "velodyne"
    velodyne.mkdir()
    for i in range(12):
        np.full((5, 4), i, np.float32).tofile(velodyne / f"{i}.bin")
    write_poses(tmp_path / "poses.txt", np.stack([np.eye(4)] * 12))
    seq = open_sequence(tmp_path)
    assert [float(seq.points(i).xyz[0, 0]) for i in range(12)] == list(range(12))


def test_bad_sequences_name_the_problem(tmp_path, synthetic_seq_dir):
    with pytest.raises(DatasetError, match="does not exist"):
        open_sequence(tmp_path / "nope")
    with pytest.raises(DatasetError, match="matches no known layout"):
        open_sequence(tmp_path)
    # what a ROS user gives by mistake is named as such, not "does not exist"
    cut = tmp_path / "cut"
    cut.mkdir()
    (cut / "cut_0.db3").write_bytes(b"")
    with pytest.raises(DatasetError, match="no metadata.yaml.*ros2 bag reindex"):
        open_sequence(cut)
    with pytest.raises(DatasetError, match="storage file: give its folder"):
        open_sequence(cut / "cut_0.db3")
    (tmp_path / "drive.bag.active").write_bytes(b"")
    with pytest.raises(DatasetError, match="still being written, or cut short"):
        open_sequence(tmp_path / "drive.bag.active")
    with pytest.raises(DatasetError, match="unknown sequence kind 'rosbag'"):
        open_sequence(synthetic_seq_dir, kind="rosbag")
    (tmp_path / "velodyne").mkdir()
    with pytest.raises(DatasetError, match="poses.txt is missing"):
        open_sequence(tmp_path)
    write_poses(tmp_path / "poses.txt", np.stack([np.eye(4)] * 2))
    np.zeros((3, 4), "<f4").tofile(tmp_path / "velodyne" / "000000.bin")
    with pytest.raises(DatasetError, match="1 scans but 2 poses"):
        open_sequence(tmp_path)
    # a calibration that would make every pose NaN, or that cannot be inverted: named
    write_poses(tmp_path / "poses.txt", np.stack([np.eye(4)]))
    (tmp_path / "calib.txt").write_text("Tr: nan 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(DatasetError, match=r"calib.txt:1: calibration holds NaN"):
        open_sequence(tmp_path)
    (tmp_path / "calib.txt").write_text("Tr: " + " ".join(["0"] * 12) + "\n")
    with pytest.raises(DatasetError, match="calib.txt, poses.txt.*Tr is singular"):
        open_sequence(tmp_path)
    (tmp_path / "calib.txt").write_text("Tr: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    (tmp_path / "poses.txt").write_text(" ".join(["0"] * 12) + "\n")
    with pytest.raises(DatasetError, match="the first pose is singular"):
        open_sequence(tmp_path)
    assert set(REGISTRY) == {"kitti", "pcd-folder"}


def test_a_folder_without_poses_is_a_drive_without_poses_for_the_client_only(tmp_path):
    """KITTI's test sequences (11–21) and raw drives have no poses.txt: the client could not
    send them at all, though a keyframe's pose is optional. ``open_drive`` opens them with
    no poses; whatever needs the poses (evaluation, ground truth) still refuses by name."""
    from pypcd4 import PointCloud as PcdCloud

    from overlapmamba.client._replay import open_drive
    from overlapmamba.core.datasets import open_recording

    kitti = tmp_path / "11"
    (kitti / "velodyne").mkdir(parents=True)
    for i in range(3):
        np.full((5, 4), i, np.float32).tofile(kitti / "velodyne" / f"{i:06d}.bin")
    pcd = tmp_path / "scene"
    (pcd / "clouds").mkdir(parents=True)
    for i in range(2):
        PcdCloud.from_xyz_points(np.full((5, 3), i, np.float32)).save(pcd / "clouds" / f"{i}.pcd")
    for folder, n in ((kitti, 3), (pcd, 2)):
        drive = open_drive(folder)
        assert len(drive) == n and drive.poses is None and drive.pose(0) is None
        assert drive.unposed == 0 and float(drive.scan(n - 1)[0, 0]) == n - 1
        with pytest.raises(DatasetError, match="poses.txt is missing"):
            open_sequence(folder)
        with pytest.raises(DatasetError, match="poses.txt is missing"):
            open_recording(folder, need_poses=True)
