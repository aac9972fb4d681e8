"""ROS recordings as drives: a rosbag2 (SQLite), a rosbag2 (MCAP), a bare MCAP file and a
ROS 1 bag, written by rosbags from real KITTI scans, read back to exactly those points,
times and poses; through the CLI they give the same keyframes as the .bin files."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from overlapmamba.core.errors import DatasetError

pytest.importorskip("rosbags")
from ros_messages import MOUNT, write_recordings

from overlapmamba.client._replay import open_drive
from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.datasets.bags import open_bag

FRAMES = (0, 1, 2, 40)


@pytest.fixture(scope="module")
def live_url(tmp_path_factory):
    from service_kit import server

    with server(tmp_path_factory.mktemp("bag-server") / "data") as (url, _):
        yield url


@pytest.fixture(scope="module")
def recordings(kitti_seq_dir, tmp_path_factory):
    seq = open_sequence(kitti_seq_dir)
    clouds = [seq.points(i).as_xyzi()[:20000] for i in FRAMES]
    poses = seq.poses[list(FRAMES)]
    return write_recordings(tmp_path_factory.mktemp("bags"), clouds, poses), clouds, poses


def test_every_recording_reads_back_the_same_scans_times_and_poses(recordings):
    paths, clouds, poses = recordings
    for name, path in paths.items():
        bag = open_bag(path, odometry="/odom")
        assert len(bag) == len(FRAMES) and bag.topic == "/points", name
        np.testing.assert_allclose(bag.times, 1.0 + 0.1 * np.arange(len(FRAMES)), atol=1e-9)
        for i in (3, 0, 2):  # random access
            np.testing.assert_array_equal(bag.points(i).as_xyzi(), clouds[i])
        assert bag.poses is not None
        np.testing.assert_allclose(
            bag.poses, poses, atol=1e-5
        )  # KITTI R is not exactly orthonormal
        fresh = open_bag(path)  # robots of a fleet read one drive from several threads
        with ThreadPoolExecutor(4) as pool:
            got = [c.as_xyzi() for c in pool.map(fresh.points, [3, 1, 2, 0] * 2)]
        for i, g in zip([3, 1, 2, 0] * 2, got, strict=True):
            np.testing.assert_array_equal(g, clouds[i])
        drive = open_drive(path, odometry="/odom")
        assert drive.pose(1) is not None and drive.loop_radius is None
        # /tf: map → odom → base_link (interpolated at the scans' stamps) → velodyne (static)
        np.testing.assert_allclose(open_bag(path, tf="map").poses, poses, atol=1e-5)
        base = open_bag(path, tf="/map:base_link").poses  # a named child; ROS 1's "/" too
        np.testing.assert_allclose(base, poses @ np.linalg.inv(MOUNT), atol=1e-5)


def test_a_recording_is_opened_once_for_every_scan_read(recordings, monkeypatch):
    """Each scan read past the prefetched ones reopened the recording: a ROS 1 bag's index
    read again, a file-compressed rosbag2 inflated again whole, once per 8 scans (per scan
    with --every 8), per robot. One reader is kept and shared."""
    from overlapmamba.core.datasets import bags

    opened: list[object] = []
    real = bags._reader

    def counting(path):  # type: ignore[no-untyped-def]
        opened.append(path)
        return real(path)

    monkeypatch.setattr(bags, "_reader", counting)
    paths, clouds, _ = recordings
    for name, path in paths.items():
        opened.clear()
        bag = open_bag(path)
        first = len(opened)  # the index
        for _ in range(3):
            for i in (3, 0, 2, 1):
                bag._cache.clear()  # every read goes to the file
                np.testing.assert_array_equal(bag.xyzi(i), clouds[i])
        assert len(opened) - first == 1, (name, len(opened))
        bag.close()


def test_a_split_ros1_recording_is_read_as_one_drive(recordings, tmp_path):
    """``rosbag record --split`` writes drive_0.bag, drive_1.bag, …, with the latched
    /tf_static in the first part only: no part could be given on its own with --tf (its
    frames unconnected), nor all of them. Their folder is one drive, read in order."""
    from ros_messages import write_recordings

    paths, clouds, poses = recordings
    split = tmp_path / "split"
    split.mkdir()
    first = write_recordings(tmp_path / "a", clouds[:2], poses[:2])["ros1.bag"]
    rest = write_recordings(tmp_path / "b", clouds[2:], poses[2:], start_s=1.2, static=False)
    first.rename(split / "drive_2.bag")  # named so that text order would read them backwards
    rest["ros1.bag"].rename(split / "drive_10.bag")
    whole = open_bag(paths["ros1.bag"], tf="map")
    bag = open_bag(split, tf="map")
    assert len(bag) == 4 and bag.name == "split"
    np.testing.assert_array_equal(bag.stamps_ns, whole.stamps_ns)
    np.testing.assert_allclose(bag.poses, whole.poses, atol=1e-9)
    for i in range(4):
        np.testing.assert_array_equal(bag.xyzi(i), clouds[i])
    with pytest.raises(DatasetError, match="frame 'velodyne' is in no transform"):
        open_bag(split / "drive_10.bag", tf="map")  # a later part alone lacks /tf_static


def test_recordings_that_cannot_be_read_say_why(recordings, tmp_path):
    paths, _, _ = recordings
    bag = paths["rosbag2-sqlite"]
    with pytest.raises(DatasetError, match="no PointCloud2 topic '/lidar'; it has /points"):
        open_bag(bag, topic="/lidar")
    with pytest.raises(DatasetError, match="no nav_msgs/Odometry topic '/points'"):
        open_bag(bag, odometry="/points")
    with pytest.raises(DatasetError, match=r"no transform 'odom' → 'base_link' within 0.01 s"):
        open_bag(bag, tf="map", max_pose_gap_s=0.01)  # sent 20 ms either side of each scan
    with pytest.raises(DatasetError, match="frame 'earth' is in no transform; frames: base_link"):
        open_bag(bag, tf="earth")
    with pytest.raises(DatasetError, match="odometry topic or from /tf, not both"):
        open_bag(bag, odometry="/odom", tf="map")
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"#ROSBAG V2.0\n" + bytes(100))
    with pytest.raises(DatasetError, match="cannot be read"):
        open_bag(junk)
    with pytest.raises(DatasetError, match="cannot be read"):
        open_bag(tmp_path)  # a folder of .bag files is a split recording: this one's junk
    (tmp_path / "none").mkdir()
    with pytest.raises(DatasetError, match="not a ROS recording"):
        open_bag(tmp_path / "none")
    kitti = tmp_path / "kitti"  # a sequence folder with a stray bag in it stays a sequence
    (kitti / "velodyne").mkdir(parents=True)
    (kitti / "stray.bag").write_bytes(b"")
    from overlapmamba.core.datasets.bags import is_bag

    assert not is_bag(kitti) and is_bag(tmp_path)
    assert open_drive(bag).poses is None  # no odometry named: no poses
    from ros_messages import STORE
    from rosbags.rosbag2 import Writer

    odometry_only = tmp_path / "odometry_only"
    with Writer(odometry_only, version=8) as w:
        w.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=STORE)
    with pytest.raises(DatasetError, match="no sensor_msgs/PointCloud2 topic.*/odom"):
        open_bag(odometry_only)  # it said "name one with --topic", which cannot help


def test_cli_ingests_recordings_as_the_bin_files_would(live_url, recordings):
    """Each recording ingested through the CLI (poses from /odom or /tf); each .bin scan then
    finds its own keyframe at distance 0: the descriptors are the .bin files' descriptors."""
    from typer.testing import CliRunner

    from overlapmamba.client import PlaceRecognitionClient
    from overlapmamba.client.cli import app

    paths, clouds, poses = recordings
    runner = CliRunner()
    env = {"OVERLAPMAMBA_URL": live_url}
    with PlaceRecognitionClient(live_url) as pr:
        for name, path in paths.items():
            where = ["--tf", "map"] if name in ("mcap", "ros1.bag") else ["--odometry", "/odom"]
            res = runner.invoke(app, ["ingest", str(path), "--map", "bags", *where], env=env)
            assert res.exit_code == 0, res.output
            assert f"{len(FRAMES)} new keyframes" in res.output
            session = open_drive(path).session
            for i in (0, 3):
                top = pr.query("bags", clouds[i], k=1, verify=False).matches[0]
                assert top.distance < 1e-5 and top.keyframe_id.endswith(f"-{i:06d}"), name
                kf = pr.get_keyframe("bags", f"{session}-{i:06d}")
                assert kf.pose is not None and kf.timestamp == pytest.approx(1.0 + 0.1 * i)
                np.testing.assert_allclose(kf.pose[:3], poses[i][:3, 3], atol=1e-4)
    res = runner.invoke(app, ["ingest", str(paths["mcap"]), "--map", "bags", "--topic", "/x"])
    assert res.exit_code == 2 and "no PointCloud2 topic '/x'" in res.output


def test_a_scan_that_cannot_be_read_is_left_out_and_the_drive_goes_on(
    live_url, recordings, tmp_path
):
    """A driver's empty cloud while it starts (width 0): ingest, observe and the fleet
    stopped there with an error, and every scan after it could never be sent. It is left
    out and named at the end; the rest are sent. A drive with no readable scan is an error."""
    from ros_messages import write_recordings
    from typer.testing import CliRunner

    from overlapmamba.client.cli import app

    _, clouds, poses = recordings
    gappy = [clouds[0], np.zeros((0, 4), np.float32), clouds[2], clouds[3]]
    bag = write_recordings(tmp_path / "gappy", gappy, poses)["mcap"]
    runner = CliRunner()
    env = {"OVERLAPMAMBA_URL": live_url}
    res = runner.invoke(app, ["ingest", str(bag), "--map", "gappy", "--session", "g"], env=env)
    text = " ".join(res.output.replace("│", " ").split())
    assert res.exit_code == 0, text
    assert "3 scans → map gappy: 3 new keyframes" in text, text
    assert "1 of 4 scans could not be read" in text and "message 1" in text, text
    res = runner.invoke(
        app, ["observe", str(bag), "--map", "gappy", "--session", "o", "-k", "1"], env=env
    )
    text = " ".join(res.output.replace("│", " ").split())
    assert res.exit_code == 0 and "3 scans observed" in text, text
    report = tmp_path / "fleet.json"
    res = runner.invoke(
        app,
        [
            *("simulate-fleet", "--map", "gappy", "-s", str(bag), "--robots", "1"),
            *("--rate", "50", "--duration", "20", "--out", str(report)),
            *("--plot", str(tmp_path / "f.png")),
        ],
        env=env,
    )
    assert res.exit_code == 0, res.output
    import json

    fleet = json.loads(report.read_text())
    assert fleet["errors"] == {"unreadable_scan": 1} and fleet["observations"] == 4, fleet
    empty = write_recordings(tmp_path / "empty", [np.zeros((0, 4), np.float32)], poses[:1])
    res = runner.invoke(app, ["ingest", str(empty["mcap"]), "--map", "gappy"], env=env)
    text = " ".join(res.output.replace("│", " ").split())
    assert res.exit_code == 2 and "none of the 1 scans could be read" in text, text


def test_a_recording_is_never_written_over_the_drive_it_replays(recordings, tmp_path):
    """``observe drive.mcap --record drive.mcap`` truncated the user's drive to an empty
    MCAP, then ended in a traceback reopening it. A --record that is the drive or inside it
    is refused before anything is opened; a recording replaces its file only once whole,
    and a run that fails before recording anything leaves the file there as it was."""
    from typer.testing import CliRunner

    from overlapmamba.client.cli import app
    from overlapmamba.client.recording import MapRecording

    paths, _, _ = recordings
    runner = CliRunner()
    for name in ("mcap", "rosbag2-sqlite"):
        drive = paths[name]
        into = drive / "out.mcap" if drive.is_dir() else drive
        before = {f: f.read_bytes() for f in ([drive] if drive.is_file() else drive.iterdir())}
        res = runner.invoke(app, ["observe", str(drive), "--map", "m", "--record", str(into)])
        text = " ".join(res.output.replace("│", " ").split())
        assert res.exit_code == 2 and "would overwrite what is being replayed" in text, text
        assert {f: f.read_bytes() for f in before} == before
    kept = tmp_path / "kept.mcap"
    kept.write_bytes(b"an earlier recording")
    res = runner.invoke(
        app,
        ["observe", str(paths["mcap"]), "--map", "m", "--record", str(kept)],
        env={"OVERLAPMAMBA_URL": "http://127.0.0.1:9"},  # nothing listens: fails at once
    )
    assert res.exit_code == 2 and kept.read_bytes() == b"an earlier recording", res.output
    assert [p.name for p in tmp_path.iterdir()] == ["kept.mcap"]  # no part left behind
    with MapRecording(kept) as rec:
        rec.observation("r1", 1.0, [0, 0, 0, 0, 0, 0, 1])
        assert kept.read_bytes() == b"an earlier recording"  # until the recording is whole
    assert kept.read_bytes()[:8] == b"\x89MCAP0\r\n"


@pytest.mark.timeout(300)
def test_eval_reads_a_recording_with_poses_as_it_reads_the_folder(recordings, tmp_path):
    """The same four scans and poses as a KITTI folder and as a ROS 1 bag: read alike."""
    pytest.importorskip("torch")

    from conftest import SMALL_MODEL, save_random_checkpoint
    from typer.testing import CliRunner

    from overlapmamba.cli import app
    from overlapmamba.core.poses import write_poses

    paths, clouds, poses = recordings
    folder = tmp_path / "kitti4"
    (folder / "velodyne").mkdir(parents=True)
    for i, c in enumerate(clouds):
        c.astype("<f4").tofile(folder / "velodyne" / f"{i:06d}.bin")
    write_poses(folder / "poses.txt", poses)
    ckpt = save_random_checkpoint(tmp_path / "random.pt", **SMALL_MODEL)
    runner = CliRunner()
    base = ["eval", "--checkpoint", str(ckpt), "-q", "--json"]
    res = runner.invoke(app, [*base, str(tmp_path / "a.json"), "--sequence", str(folder)])
    # 4 scans hold no loop: eval reads both to the loop table and says so alike (it used to
    # report all-NaN metrics), so also what eval computed from each: the same range images,
    # the same positions
    flat = " ".join(res.output.split())
    assert res.exit_code == 2 and "kitti4 has no loop closure" in flat, res.output
    bag = ["--sequence", str(paths["ros1.bag"]), "--tf", "map"]  # poses from /tf
    res = runner.invoke(app, [*base, str(tmp_path / "b.json"), *bag])
    flat = " ".join(res.output.split())
    assert res.exit_code == 2 and "has no loop closure" in flat, res.output
    assert not list(tmp_path.glob("*.json"))
    from overlapmamba.train.checkpoint import load_model
    from overlapmamba.train.rangecache import range_images

    _, profile, _ = load_model(ckpt)
    seq, bag = open_sequence(folder), open_bag(paths["ros1.bag"], tf="map")
    np.testing.assert_array_equal(range_images(seq, profile), range_images(bag, profile))
    np.testing.assert_allclose(seq.positions(), bag.positions(), atol=1e-5)
    res = runner.invoke(app, ["eval", "--checkpoint", str(ckpt), "--sequence", str(paths["mcap"])])
    assert res.exit_code != 0 and "--odometry" in res.output


def test_a_damaged_scan_message_is_named_and_the_scans_before_it_still_read(recordings, tmp_path):
    """A PointCloud2 message whose bytes are damaged: asking for it raises DatasetError
    naming the message and the cause; the scans before it, read ahead together with it,
    still read."""
    import shutil
    import sqlite3

    paths, clouds, _ = recordings
    bag = tmp_path / "damaged"
    shutil.copytree(paths["rosbag2-sqlite"], bag)
    (db,) = bag.glob("*.db3")
    with sqlite3.connect(db) as con:
        (topic,) = con.execute("SELECT id FROM topics WHERE name = '/points'").fetchone()
        ids = [r[0] for r in con.execute(
            "SELECT id FROM messages WHERE topic_id = ? ORDER BY timestamp", (topic,)
        )]  # fmt: skip
        con.execute("UPDATE messages SET data = ? WHERE id = ?", (b"\x00\x01\x00\x00\x07", ids[2]))
    reader = open_bag(bag)
    np.testing.assert_array_equal(reader.points(0).as_xyzi(), clouds[0])  # reads 0–2 ahead
    np.testing.assert_array_equal(reader.points(1).as_xyzi(), clouds[1])
    with pytest.raises(DatasetError, match=r"message 2 of /points .*cannot be read"):
        reader.points(2)
    np.testing.assert_array_equal(reader.points(3).as_xyzi(), clouds[3])


def test_a_drive_sends_a_scan_without_a_pose_where_its_poses_have_a_gap():
    """What ``open_drive`` makes of a recording's NaN poses (``pose_gaps="nan"``): those
    scans are sent with no pose, counted in ``unposed`` (the CLI's note), the rest as read."""
    from overlapmamba.client._replay import Drive

    poses = np.zeros((3, 7))
    poses[:, 6] = 1.0
    poses[0] = np.nan
    drive = Drive(seq=None, times=np.arange(3.0), poses=poses, loop_radius=None)  # type: ignore[arg-type]
    assert drive.pose(0) is None and drive.unposed == 1
    np.testing.assert_array_equal(drive.pose(1), poses[1])
    assert Drive(seq=None, times=np.arange(3.0), poses=None, loop_radius=None).unposed == 0  # type: ignore[arg-type]


def test_the_default_session_is_a_valid_id_and_tells_a_recordings_topics_apart(tmp_path):
    """``ingest .`` sent session '' and ``ingest "my drive 01"`` a name with spaces: every
    request was refused (422) without a word about --session. Two PointCloud2 topics of one
    recording gave both the same keyframe ids. Valid names are kept as they were."""
    from overlapmamba.client._replay import Drive
    from overlapmamba.core.datasets.bags import Bag

    def session(seq) -> str:  # type: ignore[no-untyped-def]
        return Drive(seq=seq, times=np.zeros(1), poses=None, loop_radius=None).session

    class Folder:
        def __init__(self, root) -> None:  # type: ignore[no-untyped-def]
            self.root = root

    spaced = tmp_path / "my drive 01"
    spaced.mkdir()
    assert session(Folder(spaced)) == "my-drive-01"
    assert session(Folder(spaced / ".")) == "my-drive-01"
    assert session(Folder(spaced / "sub" / "..")) == "my-drive-01"
    assert session(Folder(tmp_path / "00")) == "00"  # KITTI's: as before
    assert session(Folder(tmp_path / "_x")) == "x"  # an id starts with a letter or digit
    bag = tmp_path / "drive_0.bag"
    bag.write_bytes(b"")
    one = Bag(bag, "/points", np.zeros(1, np.int64), None, clouds=("/points",))
    assert session(one) == "drive_0"  # as before
    two = [
        Bag(bag, t, np.zeros(1, np.int64), None, clouds=("/front/points", "/rear/points"))
        for t in ("/front/points", "/rear/points")
    ]
    assert [session(b) for b in two] == ["drive_0-front-points", "drive_0-rear-points"]


def test_pose_samples_that_are_no_pose_are_gaps_not_identities_or_a_refused_drive(tmp_path):
    """Found in review: an all-zero quaternion (a publisher's before it has one) was
    normalised into the identity, so its scan went out with a heading of 0; and one NaN
    sample on the odometry, or on a /tf link nowhere near the LiDAR's chain (a tracked
    person's), made the whole recording unreadable. Such samples are left out as gaps, and
    counted."""
    from ros_messages import STORE, _cloud, _odometry, _tf
    from rosbags.rosbag2 import StoragePlugin, Writer

    from overlapmamba.core.poses import rotation_z

    ser, S = STORE.serialize_cdr, 10**9
    path = tmp_path / "gappy-poses"
    turned = rotation_z(90.0)
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        pc = w.add_connection("/points", "sensor_msgs/msg/PointCloud2", typestore=STORE)
        od = w.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=STORE)
        tf = w.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=STORE)
        rng = np.random.default_rng(0)
        for i in range(8):
            t = 100 * S + i * S // 20
            T = turned.copy()
            T[0, 3] = float(i)
            pts = rng.uniform(-20, 20, (300, 4)).astype(np.float32)
            w.write(pc, t, ser(_cloud(STORE, pts, t), "sensor_msgs/msg/PointCloud2"))
            odo = _odometry(STORE, T, t)
            if i == 3:  # not yet initialised: (0, 0, 0, 0)
                o = odo.pose.pose.orientation
                o.x = o.y = o.z = o.w = 0.0
            w.write(od, t + 1, ser(odo, "nav_msgs/msg/Odometry"))
            links = [("odom", "velodyne", T)]
            msg = _tf(STORE, t, [*links, ("odom", "person_0", np.eye(4))])
            if i == 5:  # a tracker's bad sample, off the LiDAR's chain
                msg.transforms[1].transform.translation.x = float("nan")
            w.write(tf, t + 2, ser(msg, "tf2_msgs/msg/TFMessage"))
    for kw in ({"odometry": "/odom"}, {"tf": "odom"}):
        bag = open_bag(path, **kw)
        assert bag.poses is not None and np.isfinite(bag.poses).all()
        for i in range(8):  # scan 3's heading comes from its neighbours: 90°, not 0°
            np.testing.assert_allclose(bag.poses[i][:2, :2], turned[:2, :2], atol=1e-6)
            assert abs(bag.poses[i][0, 3] - i) < 1e-6
        assert bag.bad_pose_samples == 1, kw


def test_a_huge_quaternion_a_reparented_frame_and_an_all_bad_chain(tmp_path):
    """Found in review of the gaps: a finite quaternion whose norm overflows (1e200) still
    became the identity; a tracker that moves a person's frame from odom to map refused the
    drive, its frame nowhere on the LiDAR's chain; and where every sample of the LiDAR's chain
    was left out, the error said only that a frame was in no transform."""
    from ros_messages import STORE, _cloud, _tf
    from rosbags.rosbag2 import StoragePlugin, Writer

    from overlapmamba.core.poses import rotation_z

    ser, S = STORE.serialize_cdr, 10**9
    turned = rotation_z(90.0)

    def write(path, spoil):
        with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
            pc = w.add_connection("/points", "sensor_msgs/msg/PointCloud2", typestore=STORE)
            tf = w.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=STORE)
            rng = np.random.default_rng(0)
            for i in range(6):
                t = 100 * S + i * S // 20
                pts = rng.uniform(-20, 20, (300, 4)).astype(np.float32)
                w.write(pc, t, ser(_cloud(STORE, pts, t), "sensor_msgs/msg/PointCloud2"))
                person = "map" if i >= 3 else "odom"  # re-parented half way
                msg = _tf(STORE, t, [("odom", "velodyne", turned), (person, "person_0", turned)])
                spoil(i, msg.transforms[0].transform)
                w.write(tf, t + 2, ser(msg, "tf2_msgs/msg/TFMessage"))
        return path

    def huge(i, tr):
        if i == 2:  # the same rotation, scaled by 1e200
            q = tr.rotation
            q.x, q.y, q.z, q.w = (v * 1e200 for v in (q.x, q.y, q.z, q.w))

    bag = open_bag(write(tmp_path / "huge", huge), tf="odom")
    for i in range(6):
        np.testing.assert_allclose(bag.poses[i][:3, :3], turned[:3, :3], atol=1e-6)
    assert bag.bad_pose_samples == 0

    def nan(i, tr):
        tr.translation.x = float("nan")

    with pytest.raises(DatasetError, match=r"velodyne.*\(6 odometry or /tf samples were left out"):
        open_bag(write(tmp_path / "all-bad", nan), tf="odom")
