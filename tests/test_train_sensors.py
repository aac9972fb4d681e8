"""Training on other sensors' renderings of a drive: their pair table, their input, the
sensor term's copies and validation across sensors, on the tiny generated towns."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("embreex")

from conftest import SMALL_MODEL, small_run  # noqa: E402

from overlapmamba.core.datasets import open_sequence  # noqa: E402
from overlapmamba.core.errors import DatasetError  # noqa: E402
from overlapmamba.core.sensors import get_profile  # noqa: E402
from overlapmamba.train.batches import BatchPlan, BatchSampler, PairIndex  # noqa: E402
from overlapmamba.train.checkpoint import read_checkpoint  # noqa: E402
from overlapmamba.train.errors import ConfigError  # noqa: E402
from overlapmamba.train.model import OverlapMambaConfig  # noqa: E402
from overlapmamba.train.train import train  # noqa: E402

SMALL = SMALL_MODEL


def _rendering(src, dst, sensor: str, shift_m: float = 0.0):
    """``src`` as another sensor's rendering of its drive: its manifest with the sensor
    changed, its poses (drifting up to ``shift_m`` in x), its scans linked, no pair table."""
    dst.mkdir()
    for name in ("calib.txt", "times.txt"):
        (dst / name).write_bytes((src / name).read_bytes())
    (dst / "velodyne").symlink_to((src / "velodyne").resolve())
    poses = np.loadtxt(src / "poses.txt").reshape(-1, 12)
    poses[:, 3] += shift_m * np.linspace(0, 1, len(poses))
    np.savetxt(dst / "poses.txt", poses)
    manifest = json.loads((src / "manifest.json").read_text())
    manifest["config"]["sensor"] = sensor
    (dst / "manifest.json").write_text(json.dumps(manifest))
    return dst


def test_a_drive_on_another_mount_is_levelled_for_the_structure_input_only(tiny_seq, tmp_path):
    """A drive's manifest says where its sensor sat: a robot's low, pitched sensor becomes
    the sequence's mount, and the structure input (whose ground is the reference mount's)
    levels its scans first; the other modes take them as recorded. The reference mount is
    no mount."""
    from overlapmamba.core.sensors.mount import Mount
    from overlapmamba.train.checkpoint import input_of_mode

    assert open_sequence(tiny_seq).mount is None  # a car's roof: the reference
    robot = _rendering(tiny_seq, tmp_path / "robot", "vlp16")
    manifest = json.loads((robot / "manifest.json").read_text())
    manifest["resolved"]["mounting"].update(height=0.7, pitch_deg=2.0, roll_deg=-1.0)
    (robot / "manifest.json").write_text(json.dumps(manifest))
    seq = open_sequence(robot)
    assert seq.mount == Mount(height=0.7, pitch_deg=2.0, roll_deg=-1.0)
    profile = get_profile("kitti-hdl64")
    assert input_of_mode(profile, seq, "structure").mount == seq.mount
    assert input_of_mode(profile, seq, "common").mount is None
    # returns on the robot's −7° beam from its road 0.7 m below, and on its +1° beam from a
    # wall: once levelled the road is ground, which the structure input drops; the wall stays
    structure = input_of_mode(profile, seq, "structure")
    road, wall = _on_beam(-7.0, 0.7, z_level=-0.7), _on_beam(1.0, 0.7, r=10.0)
    assert not (structure.project(road) > 0).any()
    assert (structure.project(wall) > 0).sum() >= len(wall)
    manifest["resolved"]["mounting"] = {"height": "low"}
    (robot / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(DatasetError, match="unreadable mounting"):
        open_sequence(robot)


def _on_beam(el_deg: float, height: float, z_level: float | None = None, r: float = 0.0):
    """(8, 3) returns on a beam at ``el_deg`` of a sensor ``height`` m up, pitched 2° and
    rolled −1°, in its frame, at 8 azimuths: at range ``r``, or where the level frame's z
    is ``z_level``."""
    from overlapmamba.core.sensors.mount import platform_from_sensor

    tilt = platform_from_sensor(2.0, -1.0)
    el, az = np.radians(el_deg), np.radians(np.arange(8) * 45.0 + 10.0)
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.full(8, np.sin(el))], 1)
    rng = np.full(8, r) if z_level is None else z_level / (d @ tilt.T)[:, 2]
    assert (rng > 0).all()
    return (d * rng[:, None]).astype(np.float32)


def test_renderings_of_one_drive_share_its_pair_table(tiny_seq, tmp_path):
    """Another sensor's rendering of a drive (gen-data --sensor … --no-ground-truth) is
    labelled by the drive's table: frame i of one rendering overlaps frame j of the other as
    i and j do, fully when i = j, and that copy is a positive, never a revisit."""
    ref = open_sequence(tiny_seq)
    other = open_sequence(_rendering(tiny_seq, tmp_path / "vlp16", "vlp16"))
    alone = PairIndex.from_sequences([ref])
    both = PairIndex.from_sequences([ref, other])
    n = len(ref)
    assert len(both) == 2 * n and both.frame is not None
    a = alone.overlap.toarray()
    full = both.overlap.toarray()
    for block in (full[:n, :n], full[n:, n:], full[:n, n:] - np.diag(np.diag(full[:n, n:]))):
        np.testing.assert_array_equal(block, a - np.diag(np.diag(a)))
    np.testing.assert_array_equal(np.diag(full[:n, n:]), 1.0)
    np.testing.assert_array_equal(full, full.T)
    sampler = BatchSampler(both, BatchPlan(batch_size=16))
    for i in range(0, 2 * n, 37):
        assert (i + n) % (2 * n) in sampler.positives[i]  # the same place, the other sensor
        revisits = sampler.revisits[i]
        assert np.all(np.abs(both.frame[revisits] - both.frame[i]) > 100)
    # a rendering elsewhere, or a drive with no table at all, is refused
    moved = open_sequence(_rendering(tiny_seq, tmp_path / "moved", "vlp16", shift_m=3.0))
    with pytest.raises(DatasetError, match="not a rendering of the same drive"):
        PairIndex.from_sequences([ref, moved])
    with pytest.raises(DatasetError, match="no ground_truth/overlaps.npz in any rendering"):
        PairIndex.from_sequences([other])


def test_training_takes_another_sensors_rendering_only_when_asked(tiny_seq, tmp_path):
    from overlapmamba.train.train_inputs import Images, open_split, training_input

    cfg = OverlapMambaConfig(**SMALL)
    path = _rendering(tiny_seq, tmp_path / "vlp16", "vlp16")
    with pytest.raises(DatasetError, match="recorded with vlp16.*any_sensor = true"):
        open_split(path, cfg, "training")
    with pytest.raises(DatasetError, match="recorded with vlp16, the model expects"):
        open_split(path, cfg, "validation", any_sensor=True)  # validation: the model's own
    seq = open_split(path, cfg, "training", any_sensor=True)
    profile = get_profile(cfg.sensor)
    inp = training_input(profile, seq)
    assert inp is not None and inp.kind == "elevation"
    assert training_input(profile, open_sequence(tiny_seq)) is None
    images = Images([seq], profile, progress=False)
    idx = np.array([0, 5])
    got = images[idx]
    for k, i in enumerate(idx):  # as the exported model will take a VLP-16's scan
        np.testing.assert_allclose(got[k], inp.project(seq.points(int(i)))[0], atol=0.05)
    empty_rows = np.all(got == profile.empty_value, axis=(0, 2))
    assert 0 < empty_rows.sum() < profile.height  # rows no VLP-16 beam reaches stay empty
    turned = images.turned(idx, np.array([0.0, 90.0]))
    np.testing.assert_allclose(turned[0], got[0], atol=0.05)
    assert turned.shape == got.shape and not np.allclose(turned[1], got[1], atol=0.05)


@pytest.mark.timeout(900)  # its set-up waits for the tiny towns, made in the background
def test_validation_across_sensors_scores_renderings_and_selects_on_their_mean(
    tiny_seq, tiny_val_seq, tmp_path
):
    """val_sensors: a rendering of the validation drive by another sensor is scored every
    epoch on its own and against the validation scans; select_on sensors keeps the epoch
    with the best mean; a rendering of another drive is refused by name."""
    from overlapmamba.train.evaluate import (
        cross_loop_closure,
        loop_closure,
        sequence_loops,
        summary,
    )
    from overlapmamba.train.valsensors import selection_score

    vlp = _rendering(tiny_val_seq, tmp_path / "val-vlp16", "vlp16")
    cfg = small_run(epochs=1, val_sensors=[str(vlp)], select_on="sensors", real="")
    out = tmp_path / "run"
    history = train([tiny_seq], tiny_val_seq, out, OverlapMambaConfig(**SMALL), cfg, progress=False)
    for entry in history:
        got = entry["val_sensors"]["vlp16"]
        assert set(got) == {"own", "cross"} and 0 <= got["cross"]["all"]["f1max"] <= 1
    best = read_checkpoint(out / "best.pt")["train"]["best"]
    scores = [selection_score(e["val"], e["val_sensors"]) for e in history]
    assert best["select_on"] == "sensors" and best["score"] == pytest.approx(max(scores))
    assert best["epoch"] == int(np.argmax(scores))
    # the same descriptors as queries and database: the loop-closure protocol itself
    gt = sequence_loops(open_sequence(tiny_val_seq))
    desc = np.random.default_rng(0).standard_normal((gt.n_frames, 8)).astype(np.float32)
    assert cross_loop_closure(desc, desc, gt) == summary(loop_closure(desc, gt))

    other = _rendering(tiny_seq, tmp_path / "train-vlp16", "vlp16")
    bad = small_run(epochs=1, val_sensors=[str(other)], real="")
    with pytest.raises(DatasetError, match="not a rendering of the validation drive"):
        train([tiny_seq], tiny_val_seq, tmp_path / "bad", OverlapMambaConfig(**SMALL), bad)
    with pytest.raises(ConfigError, match="select_on 'sensors' needs val_sensors"):
        small_run(select_on="sensors")


def test_batch_copies_take_only_the_model_sensors_scans_and_draw_only_when_on():
    """The sensor term's copies are of the batch's scans of the model's own sensor (their
    places in the batch returned), none when it has none; nothing is drawn for a term
    that is off."""
    from overlapmamba.core.sensors import get_profile
    from overlapmamba.train.augment import AugmentConfig, Augmenter
    from overlapmamba.train.train_inputs import batch_copies

    profile = get_profile("kitti-hdl64")
    rng0 = np.random.default_rng(0)
    scans = rng0.uniform(5, 60, (6, profile.height, profile.width)).astype(np.float32)

    class Batch:  # the things batch_copies reads of train_inputs.Images (a range-image input)
        mode = "elevation"

        def __init__(self, native):
            self.parts = [scans]
            self.flags = np.asarray(native, bool)

        def __getitem__(self, idx):
            return scans[idx]

        def native(self, idx):
            return self.flags[idx]

    aug = Augmenter(AugmentConfig.none(), profile, circular=True)
    idx = np.array([5, 4, 3, 2, 1, 0])
    mixed = Batch([True, False, True, False, False, True])  # scans 0, 2 and 5: its own
    turned, at, looked = batch_copies(mixed, idx, np.random.default_rng(1), aug, 0, 2)
    assert turned.shape == (0, profile.height, profile.width)
    np.testing.assert_array_equal(at, [0, 3])  # scans 5 and 2: the first two of its own
    assert looked.shape == (2, profile.height, profile.width)
    for copy, scan in zip(looked, scans[idx[at]], strict=True):  # its rows, some emptied
        kept = copy != profile.empty_value
        assert kept.any() and (~kept).any() and np.isin(copy[kept], scan).all()
    _, at, looked = batch_copies(Batch([False] * 6), idx, np.random.default_rng(1), aug, 0, 2)
    assert len(at) == 0 and len(looked) == 0  # none of the model's sensor: no copies
    rng = np.random.default_rng(2)
    batch_copies(mixed, idx, rng, aug, 0, 0)
    assert rng.random() == np.random.default_rng(2).random()  # both off: nothing drawn
