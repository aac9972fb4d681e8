"""Training, checkpoints and evaluation end to end on the tiny generated towns."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("embreex")

from conftest import ROOT, SMALL_MODEL, kitti_head, save_random_checkpoint, small_run  # noqa: E402
from typer.testing import CliRunner  # noqa: E402

from overlapmamba.cli import app  # noqa: E402
from overlapmamba.core.datasets import open_sequence  # noqa: E402
from overlapmamba.core.errors import DatasetError  # noqa: E402
from overlapmamba.train.batches import GROUP, BatchPlan, BatchSampler, PairIndex  # noqa: E402
from overlapmamba.train.checkpoint import load_model, read_checkpoint, save_checkpoint  # noqa: E402
from overlapmamba.train.errors import CheckpointError, ConfigError, DivergedError  # noqa: E402
from overlapmamba.train.model import OverlapMamba, OverlapMambaConfig  # noqa: E402
from overlapmamba.train.train import TrainConfig, train  # noqa: E402

SMALL = SMALL_MODEL
runner = CliRunner()


@pytest.mark.parametrize("negative", [0.3, 0.1])
def test_batches_hold_anchor_positives_and_a_near_miss(tiny_seq, negative):
    pairs = PairIndex.from_sequences([open_sequence(tiny_seq)])
    sampler = BatchSampler(pairs, BatchPlan(batch_size=16, negative_threshold=negative))
    rng = np.random.default_rng(0)
    revisit_pairs = 0
    for idx in sampler.epoch(rng, 160):
        assert len(idx) == 16 and len(set(idx.tolist())) == 16
        ov = pairs.submatrix(idx)
        np.testing.assert_array_equal(ov, ov.T)
        for g in range(0, 16, GROUP):
            a, p1 = idx[g], idx[g + 1]
            assert ov[g, g + 1] > 0.3 and ov[g, g + 2] > 0.3  # two positives
            assert ov[g, g + 3] <= negative  # the near miss is a clear negative
            revisit_pairs += abs(int(a) - int(p1)) > 100
    assert revisit_pairs >= 10  # about half the anchors meet an old pass of their place
    with pytest.raises(ValueError, match="multiple of 4"):
        BatchSampler(pairs, BatchPlan(batch_size=10))


@pytest.mark.slow
@pytest.mark.timeout(900)  # its set-up generates the tiny-check town
def test_tiny_train_resume_and_eval(tiny_seq, tiny_val_seq, tiny_run, tmp_path):
    cfg = OverlapMambaConfig(**SMALL)
    straight, history = tiny_run  # train([tiny_seq], tiny_val_seq, …, cfg, small_run())
    assert [h["epoch"] for h in history] == [0, 1, 2]
    for h in history:
        assert h["val"]["all"]["queries_with_loop"] > 0
        assert set(h["val"]) == {"all", "same", "reverse"}
    assert history[0]["loss"] is None and history[0]["calibrate_s"] > 0  # epoch 0: no step
    # every epoch turned the real KITTI scans (the shared run has the check on)
    for h in history:
        assert 0 < h["real"]["turned_over_one_metre_step"] < 10 and h["real"]["cosine_min"] > 0.9
    for h in history[1:]:
        assert np.isfinite(h["loss"]) and h["scans_per_s"] > 0 and h["data_s"] > 0
        # health: one record per step (log_every 1), with every number the curves plot
        assert [r["step"] for r in h["health_log"]] == [2 * h["epoch"] - 1, 2 * h["epoch"]]
        for r in h["health_log"]:
            assert r["d_neg"] > 0 and r["d_pos"] >= 0 and r["spread"] > 0
            assert 0 <= r["active"] <= 1 and r["margin"] > 0
        assert h["health"]["loss"] == pytest.approx(h["loss"])
    for name in ("last.pt", "best.pt", "epoch-000.pt", "epoch-001.pt", "epoch-002.pt"):
        assert (straight / name).is_file(), name
    assert (straight / "curves.png").stat().st_size > 20_000  # three panels
    metrics = json.loads((straight / "metrics.json").read_text())
    assert len(metrics["history"]) == 3 and metrics["model_config"]["d_model"] == 32
    # epoch 0 is the initial network with batch norm recalibrated: not the as-built one
    init = read_checkpoint(straight / "epoch-000.pt")["state_dict"]
    torch.manual_seed(0)
    built = OverlapMamba(cfg).state_dict()
    assert not torch.equal(init["spp.cv1.1.running_mean"], built["spp.cv1.1.running_mean"])
    torch.testing.assert_close(init["spp.cv1.0.weight"], built["spp.cv1.0.weight"])

    # One epoch, then --resume to two: the same weights as the uninterrupted run.
    resumed = tmp_path / "resumed"
    train([tiny_seq], tiny_val_seq, resumed, cfg, small_run(epochs=1), progress=False)
    # (--device on a resume: a run may move between a GPU machine and a CPU one)
    args = ["train", "--out", str(resumed), "--resume", "--epochs", "2", "--device", "cpu", "-q"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    a, b = read_checkpoint(straight / "last.pt"), read_checkpoint(resumed / "last.pt")
    for k in a["state_dict"]:
        torch.testing.assert_close(a["state_dict"][k], b["state_dict"][k], rtol=1e-5, atol=1e-5)
    # the learning rate went on where it stopped (warm-up of 2 steps, then full)
    assert [h["lr"] for h in b["train"]["history"]] == [h["lr"] for h in history]
    assert a["train"]["scheduler"] == b["train"]["scheduler"]
    for x, y in zip(history[1:], b["train"]["history"][1:], strict=True):
        assert [r["spread"] for r in x["health_log"]] == pytest.approx(
            [r["spread"] for r in y["health_log"]], rel=1e-4
        )
    # a run written by the older trainer (no warm-up schedule) is refused before any work
    old = read_checkpoint(resumed / "last.pt")
    del old["train"]["schedule"]
    save_checkpoint(tmp_path / "old" / "last.pt", {k: v for k, v in old.items() if k != "format"})
    with pytest.raises(ConfigError, match="older trainer"):
        train([], None, tmp_path / "old", resume=True, progress=False)

    # The checkpoint describes itself: the model rebuilds from it alone.
    model, profile, ckpt = load_model(straight / "best.pt")
    assert model.cfg == cfg and profile.name == "kitti-hdl64"
    assert ckpt["train"]["data"]["val"]["path"] == str(tiny_val_seq.resolve())

    out_json, out_png = tmp_path / "eval.json", tmp_path / "pr.png"
    result = runner.invoke(
        app,
        [
            "eval",
            "--checkpoint",
            str(straight / "best.pt"),
            "--sequence",
            str(tiny_val_seq),
            "--json",
            str(out_json),
            "--plot",
            str(out_png),
            "-q",
        ],
    )
    assert result.exit_code == 0, result.output
    for word in ("AUC", "F1max", "Recall@1", "reverse", "same", "false alarms", "rejected"):
        assert word in result.output
    errors = json.loads(out_json.read_text())["errors"]
    assert set(errors) == {"all", "same", "reverse"} and errors["all"]["far_m"] == 50.0
    record = json.loads(out_json.read_text())["metrics"]
    assert record["all"]["queries_with_loop"] > 0 and 0 <= record["all"]["f1max"] <= 1
    assert out_png.stat().st_size > 10_000

    # A finished run refuses to be overwritten.
    with pytest.raises(ConfigError, match="already holds a run"):
        train([tiny_seq], tiny_val_seq, straight, cfg, small_run(), progress=False)


@pytest.mark.timeout(900)  # when run alone, its set-up generates both tiny towns
def test_training_refuses_bad_data_and_config(tiny_seq, tiny_val_seq, tmp_path, kitti_seq_dir):
    cfg = OverlapMambaConfig(**SMALL)
    with pytest.raises(DatasetError, match="no ground_truth/overlaps.npz"):
        train([kitti_seq_dir], tiny_val_seq, tmp_path / "a", cfg, small_run(), progress=False)
    with pytest.raises(DatasetError, match="no loop closure"):
        train([tiny_seq], kitti_seq_dir, tmp_path / "b", cfg, small_run(), progress=False)
    with pytest.raises(ConfigError, match="both training and validation"):
        train([tiny_seq], tiny_seq, tmp_path / "c", cfg, small_run(), progress=False)
    with pytest.raises(ConfigError, match="nothing to resume"):
        train([], None, tmp_path / "d", resume=True, progress=False)
    with pytest.raises(ConfigError, match="does not match sensor"):
        train(
            [tiny_seq],
            tiny_val_seq,
            tmp_path / "e",
            OverlapMambaConfig(width=512),
            small_run(),
            progress=False,
        )
    (tmp_path / "a-file").write_text("")
    with pytest.raises(ConfigError, match="is a file; a run is written into a folder"):
        train([tiny_seq], tiny_val_seq, tmp_path / "a-file", cfg, small_run(), progress=False)
    with pytest.raises(ConfigError, match="unknown loss"):
        TrainConfig(loss="contrastive")
    with pytest.raises(ConfigError, match="unknown training fields"):
        TrainConfig.from_dict({"epoch": 3})


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"negative_threshold": 0.4}, "negative_threshold 0.4 is not allowed"),
        ({"batch_size": 18}, "use a multiple of 4"),
        ({"group_positives": 6, "group_negatives": 6, "batch_size": 16}, "multiple of 13"),
        ({"augment": {"tilt": 3}}, "unknown augmentation fields"),
        ({"augment": {"dropout": 1.5}}, "dropout=1.5 is out of range"),
        ({"warmup_steps": -1}, "warmup_steps must be ≥ 0"),
        ({"turn_weight": -1}, "use turn_weight ≥ 0"),
        ({"turn_allowance": 1.0}, "0 ≤ turn_allowance < 1"),
        ({"turn_scans": 17}, "more than the batch"),
        ({"look_weight": -1}, "use look_weight ≥ 0"),
        ({"look_scans": 0}, r"1 ≤ look_scans ≤ batch_size \(16\)"),
        ({"init": "model.bin"}, "allowed are a checkpoint"),
        ({"lr": float("inf")}, "lr must be finite"),
        ({"alpha": float("nan")}, "alpha must be finite"),  # NaN passed every `x < 0` test
        ({"margin": -0.5}, "margin must be ≥ 0"),
        ({"revisit_fraction": 5.0}, "revisit_fraction must be within 0 … 1"),
        ({"seed": -1}, "seed must be within 0"),  # a traceback after the data had loaded
        ({"seed": 2**70}, "seed must be within 0"),
    ],
)
def test_recipe_settings_are_checked_with_the_allowed_values(fields, message):
    with pytest.raises(ConfigError, match=message):
        TrainConfig.from_dict(fields)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["train", "--out", "x"], "give --data"),
        (["train", "--out", "x", "--resume", "--lr", "0.1"], "--resume continues"),
        (["eval", "--checkpoint", "nope.pt", "--sequence", "."], "does not exist"),
        (["train", "--data", ".", "--val", ".", "--out", "x", "--init", "gone.onnx"], "gone.onnx"),
    ],
)
def test_cli_errors_are_one_line(args, message, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = runner.invoke(app, args)
    assert result.exit_code == 2
    assert message in result.output


def test_bad_inputs_to_train_and_eval_are_named_before_the_work(tmp_path, kitti_seq_dir):
    """A config file that does not parse, an --init that is not ONNX, an eval whose outputs
    cannot be written or whose sequence has no loop to score: one line, exit 2, no
    traceback, and (for eval) said before minutes of work rather than after."""
    from overlapmamba.train.train_config import load_config_file

    for name, text, says in (
        ("bad.json", "{bad", "is not valid JSON"),
        ("bad.toml", "[train\n", "is not valid TOML"),
        ("m5.toml", "model = 5\n", "section 'model' is int"),
    ):
        (tmp_path / name).write_text(text)
        with pytest.raises(ConfigError, match=says):
            load_config_file(tmp_path / name)
    (tmp_path / "junk.onnx").write_text("not onnx")
    init = ["--data", ".", "--val", ".", "--out", str(tmp_path / "r"), "--init"]
    res = runner.invoke(app, ["train", *init, str(tmp_path / "junk.onnx"), "-q"])
    assert res.exit_code == 2 and "is not an ONNX file" in res.output, res.output
    shipped = str(ROOT / "models" / "overlapmamba-hdl64.onnx")
    ev = ["eval", "--checkpoint", shipped, "--sequence", str(kitti_seq_dir), "-q"]

    def flat(text: str) -> str:  # rich boxes and wraps a usage error
        return " ".join(text.replace("│", " ").split())

    res = runner.invoke(app, [*ev, "--plot", str(tmp_path / "pr.txt")])
    assert res.exit_code == 2 and "allowed formats are" in flat(res.output)
    res = runner.invoke(app, [*ev, "--json", str(tmp_path)])
    assert res.exit_code == 2 and "is a folder" in flat(res.output), res.output
    res = runner.invoke(app, [*ev, "--json", str(tmp_path / "e.json")])  # frames 0–100
    assert res.exit_code == 2 and "has no loop closure" in flat(res.output)
    assert not (tmp_path / "e.json").exists()


def test_checkpoint_errors_name_the_problem(tmp_path):
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        read_checkpoint(junk)
    torch.save({"weights": torch.zeros(1)}, tmp_path / "foreign.pt")
    with pytest.raises(CheckpointError, match="not an OverlapMamba checkpoint"):
        read_checkpoint(tmp_path / "foreign.pt")
    save_checkpoint(tmp_path / "bad.pt", {"model_config": {"d_modle": 3}, "state_dict": {}})
    with pytest.raises(CheckpointError, match="does not rebuild its model"):
        load_model(tmp_path / "bad.pt")


@pytest.mark.real_data
def test_eval_real_prints_invariance_retrieval_and_yaw(kitti_seq_dir, tmp_path):
    save_random_checkpoint(tmp_path / "random.pt", **SMALL)
    out = tmp_path / "real.json"
    result = runner.invoke(
        app,
        [
            "eval-real",
            "--checkpoint",
            str(tmp_path / "random.pt"),
            "--sequence",
            str(kitti_seq_dir),
            "--json",
            str(out),
        ],
    )
    assert result.exit_code == 0, result.output
    assert "odd→even Recall@1" in result.output and "yaw error" in result.output
    r = json.loads(out.read_text())
    assert r["scans"] == 101 and r["retrieval_odd_to_even"]["queries"] == 50
    inv = r["yaw_invariance"]
    assert inv["one_metre_step_pairs"] > 10 and inv["one_metre_step_distance_median"] > 0
    assert inv["turned_over_one_metre_step"] == pytest.approx(
        inv["turned_distance_median"] / inv["one_metre_step_distance_median"]
    )
    # Scan Context is rotation-invariant by its shift search: it finds the neighbours of
    # these turned real scans (the issue measured 100 %)
    assert r["retrieval_odd_to_even"]["scan_context"]["recall@1"] > 0.9
    assert "1 m step" in result.output and "Scan Context" in result.output
    # Exact equivariance holds for column rolls; a continuous turn also re-samples the scan.
    assert r["yaw_invariance"]["cosine_min"] > 0.999
    assert r["yaw_error_deg"]["vs_turned_copy"]["median"] < 1.0
    assert (r["sensor"], r["input"]) == ("kitti-hdl64", "native")


@pytest.mark.real_data
def test_eval_real_thins_the_queries_to_fewer_rings(kitti_seq_dir, tmp_path):
    """--beams 32,16: queries of every 2nd / 4th ring of the real HDL-64E (found by
    elevation) against whole scans, declared as the sensor they now are and not."""
    from overlapmamba.core.sensors import CATALOGUE
    from overlapmamba.train.realscans import thin_points, thinned_sensor

    kitti = CATALOGUE["kitti-hdl64"]
    half = thinned_sensor(kitti, 32)
    assert half.beams == 32 and half.elevations_deg == kitti.elevations_deg[::2]
    with pytest.raises(ValueError, match="whole divisor"):
        thinned_sensor(kitti, 48)
    from overlapmamba.core.datasets import open_sequence

    xyz = open_sequence(kitti_seq_dir).points(0).xyz
    kept = thin_points(xyz, kitti, 16)
    assert 0.15 < len(kept) / len(xyz) < 0.35  # about a quarter of the rings
    save_random_checkpoint(tmp_path / "random.pt", **SMALL)
    out = tmp_path / "real.json"
    args = ["eval-real", "--checkpoint", str(tmp_path / "random.pt"), "--sequence"]
    head = kitti_head(kitti_seq_dir, tmp_path / "head", 24)  # the whole evaluation, on less
    result = runner.invoke(app, [*args, str(head), "--beams", "32,16", "--json", str(out)])
    assert result.exit_code == 0, result.output
    assert "16 rings, declared" in result.output
    report = json.loads(out.read_text())
    assert report["scans"] == 24 and report["retrieval_odd_to_even"]["queries"] == 12
    thin = report["thinned"]
    assert set(thin) == {"32", "16"} and thin["16"]["points_kept"] < thin["32"]["points_kept"]
    for t in thin.values():
        assert t["undeclared"]["input"] == "native" and t["declared"]["input"] != "native"
        for how in ("declared", "undeclared"):
            assert 0 <= t[how]["recall@1"] <= 1 and t[how]["cosine_to_full"]["min"] <= 1.0
    bad = runner.invoke(app, [*args, str(kitti_seq_dir), "--beams", "48"])
    assert bad.exit_code == 2 and "whole divisor" in bad.output


def test_a_diverging_run_stops_at_its_first_nan_loss(tiny_seq, tiny_val_seq, tmp_path, monkeypatch):
    """A learning rate far too high made the loss NaN at the second step, and the run went on
    for every remaining epoch on NaN weights (the collapse check compares a NaN spread, the
    epoch means drop NaN steps), its last.pt NaN for --resume to carry on from. It stops at
    that step, naming it; last.pt holds the last whole epoch. The data paths it records are
    absolute, so a resume from another working directory finds them."""
    monkeypatch.chdir(tiny_seq.parent)
    cfg = OverlapMambaConfig(**SMALL)
    run = small_run(lr=1e6, warmup_steps=0, real="")
    with pytest.raises(DivergedError, match=r"epoch 1, step 2: the loss is nan .* lower lr"):
        train(
            [Path(tiny_seq.name)], Path(tiny_val_seq.name), tmp_path / "r", cfg, run, progress=False
        )
    last = read_checkpoint(tmp_path / "r" / "last.pt")
    assert last["train"]["history"][-1]["epoch"] == 0
    assert all(torch.isfinite(t).all() for t in last["state_dict"].values())
    assert last["train"]["data"]["val"]["path"] == str(tiny_val_seq.resolve())


def test_test_towns_never_select_a_checkpoint(tiny_val_seq, tmp_path):
    """A test town was refused as training data but taken as validation data, where it
    chooses best.pt: a run could be selected on the towns its results are reported on."""
    from overlapmamba.train.train_inputs import open_split
    from overlapmamba.train.valsensors import open_renderings

    town = tmp_path / "test-town"
    town.mkdir()
    for item in tiny_val_seq.iterdir():
        if item.name != "manifest.json":
            (town / item.name).symlink_to(item)
    manifest = json.loads((tiny_val_seq / "manifest.json").read_text())
    manifest["config"]["split"] = "test"
    (town / "manifest.json").write_text(json.dumps(manifest))
    cfg = OverlapMambaConfig(**SMALL)
    for role in ("training", "validation"):
        with pytest.raises(DatasetError, match="is a test split: it is never"):
            open_split(town, cfg, role)
    val = open_sequence(tiny_val_seq)
    with pytest.raises(DatasetError, match="is a test split"):
        open_renderings([str(town)], val, None, False)  # type: ignore[arg-type]


def test_one_run_folder_one_run_and_a_failed_write_keeps_the_last_checkpoint(tmp_path, monkeypatch):
    """Two runs into one --out interleaved their checkpoints (best.pt of one seed, last.pt and
    metrics of the other): the folder is locked. A checkpoint write that failed (a full disk)
    left its temporary file, which kept the disk full, and a traceback: it is removed, the
    previous checkpoint stands, and the error names the file."""
    import errno

    from overlapmamba.train import runfolder

    held = runfolder.RunLock(tmp_path / "run")
    with pytest.raises(ConfigError, match="in use by another training run"):
        runfolder.RunLock(tmp_path / "run")
    held.close()
    runfolder.RunLock(tmp_path / "run").close()  # free again

    path = tmp_path / "run" / "last.pt"
    save_checkpoint(path, {"epoch": 1})
    real_save = torch.save

    def full_disk(obj, f):  # type: ignore[no-untyped-def]
        real_save(obj, f)  # most of it written, then the disk is full
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(torch, "save", full_disk)
    with pytest.raises(CheckpointError, match=r"could not write .*last.pt \(OSError"):
        save_checkpoint(path, {"epoch": 2})
    monkeypatch.undo()
    assert read_checkpoint(path)["epoch"] == 1
    assert sorted(p.name for p in path.parent.iterdir()) == [".lock", "last.pt"]
    (path.parent / ".best.pt.tmp999").write_bytes(b"half")  # a killed run's
    assert [p.name for p in runfolder.remove_stale_writes(path.parent)] == [".best.pt.tmp999"]


def test_the_run_folder_holds_on_mounts_without_locks_or_folder_fsync(tmp_path, monkeypatch):
    """Found in review of the lock and the fsync: a mount without flock (ENOLCK) was told
    "in use by another training run", and one that cannot fsync a folder (CIFS, FUSE: EINVAL)
    ended the run after its checkpoint was written; a run started before paths were recorded
    absolute (data/synth/…) could not be resumed ("other data than the run was started on")."""
    import errno
    import fcntl
    import os
    import stat

    from overlapmamba.train import runfolder
    from overlapmamba.train.runfolder import same_data

    def no_locks(fd, op):  # type: ignore[no-untyped-def]
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", no_locks)
    runfolder.RunLock(tmp_path / "run").close()  # a warning, not a refusal
    monkeypatch.undo()
    real_fsync = os.fsync

    def no_folder_fsync(fd):  # type: ignore[no-untyped-def]
        if stat.S_ISDIR(os.fstat(fd).st_mode):
            raise OSError(errno.EINVAL, "Invalid argument")
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", no_folder_fsync)
    save_checkpoint(tmp_path / "run" / "last.pt", {"epoch": 1})
    assert read_checkpoint(tmp_path / "run" / "last.pt")["epoch"] == 1
    monkeypatch.undo()
    monkeypatch.chdir(tmp_path)
    old = {"train": [{"path": "tiny", "key": "k"}], "val": {"path": "v", "key": "j"}}
    new = {
        "train": [{"path": str(tmp_path / "tiny"), "key": "k"}],
        "val": {"path": str(tmp_path / "v"), "key": "j"},
    }
    assert same_data(old, new)
    assert not same_data(old, {**new, "val": {"path": str(tmp_path / "v"), "key": "x"}})
