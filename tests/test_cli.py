"""The ``overlapmamba`` command line, through typer's CliRunner."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from overlapmamba.cli import app
from overlapmamba.core.renamed import DeprecatedName

runner = CliRunner()


def text(res) -> str:
    """Output with line wrapping and box borders flattened."""
    return " ".join(res.output.replace("│", " ").split())


def test_range_image_on_real_reference_scan(kitti_reference_dir, tmp_path):
    scan = kitti_reference_dir / "000000.bin"
    out = tmp_path / "d.npy"
    res = runner.invoke(app, ["range-image", str(scan), "--max-range", "50", "--out", str(out)])
    assert res.exit_code == 0, res.output
    img = np.load(out)
    assert img.shape == (64, 900) and img.dtype == np.float32
    ref = np.load(kitti_reference_dir / "depth_000000.npy")
    assert ((img > 0) == (ref > 0)).mean() > 0.999


def test_range_image_png_and_custom_profile(synthetic_seq_dir, tmp_path):
    scan = synthetic_seq_dir / "velodyne" / "000000.bin"
    out = tmp_path / "view.png"
    res = runner.invoke(
        app,
        [
            "range-image",
            str(scan),
            "-s",
            "hdl32",
            "--width",
            "360",
            "--row-scale",
            "2",
            "--out",
            str(out),
        ],
    )
    assert res.exit_code == 0, res.output
    im = Image.open(out)
    assert im.size == (360, 64) and im.mode == "RGB"
    assert np.asarray(im).max() > 0


def test_range_image_errors_are_clear(synthetic_seq_dir, tmp_path):
    scan = synthetic_seq_dir / "velodyne" / "000000.bin"
    res = runner.invoke(app, ["range-image", str(scan), "--out", str(tmp_path / "x.jpg")])
    assert res.exit_code == 2 and "allowed output suffixes are .npy and .png" in text(res)
    res = runner.invoke(
        app, ["range-image", str(scan), "-s", "lidar9000", "--out", str(tmp_path / "x.npy")]
    )
    assert res.exit_code == 2 and "unknown sensor profile 'lidar9000'" in text(res)
    bad = tmp_path / "bad.bin"
    bad.write_bytes(b"\0" * 17)
    res = runner.invoke(app, ["range-image", str(bad), "--out", str(tmp_path / "x.npy")])
    assert res.exit_code == 2 and "not a multiple of the 16-byte" in text(res)
    # found in review: an output the system refuses was a traceback (FileExistsError,
    # IsADirectoryError), in export and ground-truth after the work; one line, exit 2
    (tmp_path / "afile").write_text("")
    (tmp_path / "d.npy").mkdir()
    for where, says in (("afile/x.npy", "afile is a file, not a folder"), ("d.npy", "d.npy")):
        res = runner.invoke(app, ["range-image", str(scan), "--out", str(tmp_path / where)])
        assert res.exit_code == 2 and says in text(res), text(res)
        assert "Traceback" not in text(res) and res.exception.__class__ is SystemExit


def test_ground_truth_command(synthetic_seq_dir, tmp_path):
    out = tmp_path / "gt.npz"
    args = [
        "ground-truth",
        str(synthetic_seq_dir),
        "--exclude-recent-frames",
        "12",
        "--radius",
        "10",
        "--out",
        str(out),
        "--quiet",
    ]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    assert "queries with a loop" in text(res) and out.is_file()
    first = np.load(out)["query"]
    # the old name still works for one release, with a warning, and means the same
    renames = {"--exclude-recent-frames": "--exclude-recent", str(out): str(tmp_path / "old.npz")}
    with pytest.warns(DeprecatedName, match="--exclude-recent is deprecated.*--exclude-recent-fr"):
        res = runner.invoke(app, [renames.get(a, a) for a in args])
    assert res.exit_code == 0, res.output
    assert np.array_equal(np.load(tmp_path / "old.npz")["query"], first)
    res = runner.invoke(app, [*args, "--exclude-recent", "12", "--exclude-recent-frames", "5"])
    assert res.exit_code == 2 and "--exclude-recent is its old name" in text(res)
    res = runner.invoke(app, ["ground-truth", str(tmp_path), "-q"])
    assert res.exit_code == 2 and "matches no known layout" in text(res)
    # found in review: --no-cache --out recomputed and wrote nothing; the table's row named
    # the automatic cache path where the generator's own table was used
    fresh = tmp_path / "fresh.npz"
    res = runner.invoke(app, [*args[:-3], "--out", str(fresh), "--no-cache", "-q"])
    assert res.exit_code == 0 and np.array_equal(np.load(fresh)["query"], first), res.output
    import shutil

    from overlapmamba.core.datasets import open_sequence
    from overlapmamba.core.overlap import LoopParams, loop_ground_truth
    from overlapmamba.core.sensors import get_profile

    seq_dir = shutil.copytree(synthetic_seq_dir, tmp_path / "seq")
    seq, profile = open_sequence(seq_dir), get_profile("kitti-hdl64")
    loops = LoopParams(exclude_recent_frames=12, radius=10.0)
    shipped = seq_dir / "ground_truth" / "loops.npz"  # as the generator ships its own
    loop_ground_truth(seq, profile, loops, cache=shipped, progress=False)
    assert loop_ground_truth(seq, profile, loops, progress=False).source == shipped
    assert loop_ground_truth(seq, profile, loops, cache=False, progress=False).source is None


def test_installed_console_script_runs():
    """The packaging entry point, as a user runs it (not through CliRunner)."""
    import subprocess
    import sys
    from pathlib import Path

    script = Path(sys.executable).with_name("overlapmamba")
    assert script.is_file(), "pip install did not create the overlapmamba console script"
    res = subprocess.run([str(script), "--help"], capture_output=True, text=True, check=True)
    assert "range-image" in res.stdout and "ground-truth" in res.stdout


def test_report_refuses_a_model_that_is_not_an_exported_encoder(tmp_path):
    """``report --model`` names the encoder its shipped row reads: a checkpoint or a missing
    file is refused before anything is evaluated, naming what to give."""
    ckpt = tmp_path / "best.pt"
    ckpt.write_bytes(b"not read")
    for model in (ckpt, tmp_path / "gone.onnx"):
        res = runner.invoke(app, ["report", "--runs", str(tmp_path), "--model", str(model)])
        assert res.exit_code == 2, res.output
        assert "give an exported encoder (.onnx) that exists" in text(res)


def test_help_shows_the_defaults_and_patterns_written_in_brackets():
    """rich read "[default: 127.0.0.1]" or "[a-z0-9]" in a help text as markup and dropped
    it: ``--help`` showed no default for serve's options and "{0,63}" for a map id."""
    from overlapmamba.client.cli import app as client_app

    serve = text(runner.invoke(app, ["serve", "--help"], env={"COLUMNS": "200"}))
    assert "bind address [default: 127.0.0.1]" in serve and "[default: 8000]" in serve, serve
    train = text(runner.invoke(app, ["train", "--help"], env={"COLUMNS": "200"}))
    assert "with [model] and [train] sections" in train and "narrow-hn (the shipped" in train
    maps = text(runner.invoke(client_app, ["maps", "create", "--help"], env={"COLUMNS": "200"}))
    assert "[a-z0-9][a-z0-9_-]{0,63}" in maps and "[default: yes]" in maps, maps


def test_serve_names_misspelt_variables_and_never_prints_a_key(tmp_path):
    """``OVERLAPMAMBA_QDRANT_URL`` (one underscore) was ignored without a word, and the
    settings error that followed printed the raw input, with the last 20 characters of the
    Qdrant API key in it, into the container's log. The variable is named with the setting
    it is nearest, and the error says where and why only."""
    key = "K" * 20 + "the-secret-end-of-the-key"
    env = {
        "COLUMNS": "200",
        "OVERLAPMAMBA_INDEX__BACKEND": "qdrant",
        "OVERLAPMAMBA_QDRANT_URL": "http://qdrant:6333",
        "OVERLAPMAMBA_QDRANT__API_KEY": key,
        "OVERLAPMAMBA_BATCHNG__MAX_BATCH": "1",
    }
    res = runner.invoke(app, ["serve", "--data-dir", str(tmp_path)], env=env)
    out = text(res)
    assert res.exit_code == 2, out
    assert "the-secret" not in out and "input_value" not in out, out
    assert "needs qdrant.url" in out
    assert "OVERLAPMAMBA_QDRANT_URL is not a setting" in out and "OVERLAPMAMBA_QDRANT__URL" in out
    assert "did you mean OVERLAPMAMBA_BATCHING__MAX_BATCH" in out


def test_serve_names_a_variable_that_overrides_the_config_files_setting(tmp_path):
    """Found in review: the image sets OVERLAPMAMBA_DATA_DIR (and host, port, model) in its
    environment, which wins over a mounted config file: a file's ``data_dir`` was ignored
    unsaid, and the maps went to the anonymous volume. Each such variable is named, with
    the setting it overrides, and never its value (it may be a key)."""
    from overlapmamba.service.settings import shadowed

    cfg = tmp_path / "svc.toml"
    cfg.write_text('data_dir = "/srv/om"\n[qdrant]\napi_key = "k"\n[batching]\nmax_batch = 4\n')
    env = {
        "OVERLAPMAMBA_DATA_DIR": str(tmp_path / "d"),
        "OVERLAPMAMBA_QDRANT__API_KEY": "the-secret",
        "OVERLAPMAMBA_PORT": "8001",  # not in the file: nothing overridden
        "OVERLAPMAMBA_CONFIG": str(cfg),
    }
    assert shadowed(None, env) == [
        ("OVERLAPMAMBA_DATA_DIR", "data_dir"),
        ("OVERLAPMAMBA_QDRANT__API_KEY", "qdrant.api_key"),
    ]
    assert shadowed(None, {"OVERLAPMAMBA_PORT": "1"}) == []  # no file
    # a setting the command line gives wins over both: not said to be the variable's
    assert shadowed(None, env, given=["data_dir"]) == [
        ("OVERLAPMAMBA_QDRANT__API_KEY", "qdrant.api_key")
    ]
    res = runner.invoke(app, ["serve", "--model", str(tmp_path / "none.onnx")], env=env)
    out = " ".join(text(res).split())
    assert "OVERLAPMAMBA_DATA_DIR overrides data_dir in the config file" in out, out
    assert "OVERLAPMAMBA_QDRANT__API_KEY overrides qdrant.api_key" in out
    assert "the-secret" not in out and "OVERLAPMAMBA_PORT overrides" not in out
    # a flag's setting is the flag's: its variable is not said to override the file
    flag = ["--data-dir", str(tmp_path / "flag"), "--index-backend", "faiss"]
    res = runner.invoke(app, ["serve", "--model", str(tmp_path / "none.onnx"), *flag], env=env)
    out = " ".join(text(res).split())
    assert "OVERLAPMAMBA_DATA_DIR overrides" not in out, out
    assert "OVERLAPMAMBA_QDRANT__API_KEY overrides qdrant.api_key" in out, out


def test_hash_key_prints_an_entry_for_the_environment_variable_as_json():
    import json
    import tomllib

    from overlapmamba.service.auth import hash_key
    from overlapmamba.service.settings import Settings

    res = runner.invoke(
        app, ["hash-key", "--role", "robot", "--name", 'r "1"', "--key", "k1", "--json"]
    )
    entry = json.loads(res.stdout)
    assert entry == {"name": 'r "1"', "role": "robot", "sha256": hash_key("k1")}
    assert Settings(auth={"keys": [entry]}).auth.keys[0].name == 'r "1"'
    # a robot limited to its site's maps, as TOML: serve reads it back
    res = runner.invoke(
        app,
        ["hash-key", "--key", "k2", "--maps", "a-live", "--query-maps", "a-base, a-old"],
    )
    toml = tomllib.loads(res.stdout)["auth"]["keys"][0]
    assert toml["maps"] == ["a-live"] and toml["query_maps"] == ["a-base", "a-old"]
    assert Settings(auth={"keys": [toml]}).auth.keys[0].query_maps == ["a-base", "a-old"]
    res = runner.invoke(app, ["hash-key", "--role", "mapper", "--key", "k", "--maps", "a"])
    assert res.exit_code == 2 and "robot keys only" in text(res), text(res)
    # found in review: an empty --key printed the entry of a new key it never showed, and a
    # map no id can be (which the key could then never reach) was written into the entry
    res = runner.invoke(app, ["hash-key", "--key", ""])
    assert res.exit_code == 2 and "--key is empty" in text(res) and "sha256" not in res.stdout
    res = runner.invoke(app, ["hash-key", "--key", "k", "--maps", "Town 1"])
    assert res.exit_code == 2 and "which no map id can be" in text(res), text(res)


def test_research_commands_refuse_what_they_cannot_do_in_one_line(
    tmp_path, kitti_seq_dir, monkeypatch
):
    """Found in review: `ground-truth --radius 0` (allowed by the option, refused by the
    loop parameters) ended in a pydantic traceback; `eval-real` on one scan in numpy's "need
    at least one array to stack"; a gen-data run that ran out of disk half-way read as a
    usage error, with no word that its folder is a dead partial run; `report` and `eval`
    JSON holds null, never NaN (strict readers refuse it)."""
    import errno
    import json
    import shutil

    from overlapmamba.train.health import strict_json

    res = runner.invoke(app, ["ground-truth", str(kitti_seq_dir), "--radius", "0", "-q"])
    assert res.exit_code == 2 and "Traceback" not in text(res), text(res)
    one = tmp_path / "one"
    (one / "velodyne").mkdir(parents=True)
    shutil.copy(next(iter(sorted((kitti_seq_dir / "velodyne").iterdir()))), one / "velodyne")
    (one / "poses.txt").write_text((kitti_seq_dir / "poses.txt").read_text().splitlines()[0] + "\n")
    shutil.copy(kitti_seq_dir / "calib.txt", one / "calib.txt")
    res = runner.invoke(
        app, ["eval-real", "--checkpoint", "models/overlapmamba-hdl64.onnx", "--sequence", str(one)]
    )
    assert res.exit_code != 0 and "needs at least 2 scans" in text(res), text(res)
    # an output that cannot be written is refused before the work (it was a traceback after)
    (tmp_path / "afile").write_text("")

    def no_work(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise AssertionError("the evaluation started before its output was checked")

    monkeypatch.setattr("overlapmamba.train.checkpoint.load_model", no_work)
    args = ["eval-real", "--checkpoint", "models/overlapmamba-hdl64.onnx", "--sequence"]
    res = runner.invoke(app, [*args, str(kitti_seq_dir), "--json", f"{tmp_path}/afile/x.json"])
    # (a long temporary path wraps in the error's box, inside a word where it falls: read
    # without any whitespace; a run under pytest-25/popen-gw0 broke "afile" there)
    said = "".join(text(res).split())
    assert res.exit_code == 2 and "afileisafile,notafolder" in said, text(res)

    def full_disk(out_dir, *args, **kwargs):  # type: ignore[no-untyped-def]
        out_dir.mkdir(parents=True)
        (out_dir / ".incomplete").write_text("")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("overlapmamba.synth.generate.generate", full_disk)
    res = runner.invoke(
        app, ["gen-data", str(tmp_path / "town"), "--seed", "7", "--frames", "3", "-q"]
    )
    out = text(res)
    assert res.exit_code == 1 and "No space left" in out and "incomplete: delete it" in out, out
    assert "Usage" not in out

    # Ctrl-C said nothing of the partial folder, and a second run called it merely not empty
    def interrupted(out_dir, *args, **kwargs):  # type: ignore[no-untyped-def]
        out_dir.mkdir(parents=True)
        (out_dir / ".incomplete").write_text("")
        raise KeyboardInterrupt

    monkeypatch.setattr("overlapmamba.synth.generate.generate", interrupted)
    res = runner.invoke(app, ["gen-data", str(tmp_path / "cut"), "--seed", "7", "--frames", "3"])
    assert res.exit_code == 130 and "cut is incomplete: delete it" in text(res), text(res)
    monkeypatch.undo()
    res = runner.invoke(app, ["gen-data", str(tmp_path / "cut"), "--seed", "7", "--frames", "3"])
    assert res.exit_code == 2 and "incomplete run's folder" in text(res), text(res)

    record = {"f1max": float("nan"), "t": np.float32("-inf"), "n": np.int64(3), "ok": 0.5}
    assert json.loads(strict_json(record)) == {"f1max": None, "t": None, "n": 3, "ok": 0.5}


def test_serve_takes_sigterm_from_its_first_step(monkeypatch):
    """Found in review: as a container's PID 1 the process has no default action for
    SIGTERM, so a stop sent during the seconds serve's checks and the model's load take
    was lost until uvicorn took the signals over (``docker stop`` then waited for its
    SIGKILL). serve handles SIGTERM before its first check."""
    import signal

    import overlapmamba.service.settings as settings_module

    seen = []

    def load(*args, **kwargs):  # type: ignore[no-untyped-def]
        seen.append(signal.getsignal(signal.SIGTERM))
        raise ValueError("stop here")

    monkeypatch.setattr(settings_module, "load_settings", load)
    before = signal.getsignal(signal.SIGTERM)
    try:
        res = runner.invoke(app, ["serve"])
        assert signal.getsignal(signal.SIGTERM) == before  # given back after a refused start
    finally:
        signal.signal(signal.SIGTERM, before)
    assert res.exit_code == 2 and len(seen) == 1
    assert callable(seen[0]) and seen[0] not in (signal.SIG_DFL, signal.SIG_IGN), seen
    with pytest.raises(SystemExit) as stop:
        seen[0](signal.SIGTERM, None)
    assert stop.value.code == 128 + signal.SIGTERM


def test_serve_gives_sigterm_back_before_the_server_runs(tmp_path, monkeypatch):
    """The start-up's SIGTERM handler is the one before it again once the server runs
    (uvicorn takes the signals over and, when it ends, restores what it found: a SIGTERM
    after that printed "stopped before the service started")."""
    import signal

    import overlapmamba.service.app as app_module

    seen = []
    monkeypatch.setattr(app_module, "run", lambda s: seen.append(signal.getsignal(signal.SIGTERM)))
    before = signal.getsignal(signal.SIGTERM)
    try:
        res = runner.invoke(app, ["serve", "--data-dir", str(tmp_path / "d"), "--port", "1"])
    finally:
        signal.signal(signal.SIGTERM, before)
    assert res.exit_code == 0, text(res)
    assert seen == [before]


def test_a_long_path_in_an_error_is_not_wrapped_under_the_tests(tmp_path, kitti_seq_dir):
    """The suite gives the commands' consoles 400 columns (conftest): at 80, rich wrapped a
    long temporary path inside a word, and a test reading the error broke on some runs."""
    deep = tmp_path / ("d" * 60) / ("e" * 60)
    deep.mkdir(parents=True)
    (deep / "afile").write_text("")
    wanted = f"{deep}/afile/x.json"
    args = ["eval-real", "--checkpoint", "models/overlapmamba-hdl64.onnx", "--sequence"]
    res = runner.invoke(app, [*args, str(kitti_seq_dir), "--json", wanted])
    assert res.exit_code == 2 and str(deep / "afile") in res.output, res.output
