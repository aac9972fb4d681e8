"""benchmarks/lent_gpu.py: a town simulated again elsewhere keeps the loop table carried to it."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import benchmark_module


@pytest.fixture(scope="module")
def lent():
    return benchmark_module("lent_gpu")


def resimulated(town: Path, out: Path) -> Path:
    """``town`` as another machine's simulation of it: the same files (linked), but for one
    scan that lost its last return (16 bytes), as re-simulated scans differ at a few edges."""
    shutil.copytree(town, out, ignore=shutil.ignore_patterns("velodyne"))
    (out / "velodyne").mkdir()
    scans = sorted((town / "velodyne").iterdir())
    for scan in scans:
        (out / "velodyne" / scan.name).symlink_to(scan)
    changed = out / "velodyne" / scans[7].name
    changed.unlink()
    changed.write_bytes(scans[7].read_bytes()[:-16])
    return out


def test_a_carried_loop_table_gets_the_new_scans_fingerprint_and_is_then_used(
    lent, tiny_seq: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    from overlapmamba.core import overlap
    from overlapmamba.core.datasets import open_sequence
    from overlapmamba.core.overlap import LoopGroundTruth
    from overlapmamba.train.evaluate import sequence_loops

    def recomputed(*args, **kwargs):
        raise AssertionError("the loop table was recomputed")

    monkeypatch.setenv("OVERLAPMAMBA_CACHE", str(tmp_path / "cache"))  # no table cached
    monkeypatch.setattr(overlap, "pair_overlaps", recomputed)

    stored, computed = lent.loop_fingerprint(tiny_seq)
    assert stored == computed  # what `pack` checks before a table travels
    town = resimulated(tiny_seq, tmp_path / "tiny")
    stored, computed = lent.loop_fingerprint(town)
    assert stored != computed  # without the patch the table would be recomputed there
    carried = LoopGroundTruth.load(town / "ground_truth" / "loops.npz")
    assert lent.patch_loops(town) is True
    assert lent.patch_loops(town) is False  # already the scans' own
    gt = sequence_loops(open_sequence(town))  # the carried table, not a recomputed one
    assert gt.params["fingerprint"] == computed
    np.testing.assert_array_equal(gt.query, carried.query)
    np.testing.assert_array_equal(gt.overlap, carried.overlap)
    # the fingerprint and the content digest are the scans simulated here; nothing else moved
    assert gt.params["content"] == open_sequence(town).content_digest()
    mine = ("fingerprint", "content")
    assert {k: v for k, v in gt.params.items() if k not in mine} == {
        k: v for k, v in carried.params.items() if k not in mine
    }


def test_a_run_that_ended_is_not_alive_though_nobody_waited_for_it(lent):
    """A child that ended stays a zombie until reaped, and a zombie answers a signal: a
    window once waited out its whole lease on three runs that had failed at their start."""
    import subprocess
    import time

    proc = subprocess.Popen(["true"])
    time.sleep(0.5)  # ended; not waited for
    assert lent._alive(proc.pid) is False
    proc.wait()  # Popen learns it ended (already reaped above)
    sleeper = subprocess.Popen(["sleep", "30"])
    try:
        assert lent._alive(sleeper.pid) is True
    finally:
        sleeper.kill()
        sleeper.wait()


def test_a_window_whose_towns_failed_launches_nothing(lent, monkeypatch, tmp_path):
    launched = []
    monkeypatch.setattr(lent, "preflight", lambda town, device: None)
    monkeypatch.setattr(lent, "prepare", lambda towns, carry, workers, presets: ["val-vlp16"])
    monkeypatch.setattr(lent, "launch", lambda *args: launched.append(args))
    opts = {"carry": tmp_path, "workers": 1, "device": "cpu", "threads": 1}
    with pytest.raises(SystemExit, match="val-vlp16 not prepared; no run launched"):
        lent.window(["train-x00", "val-vlp16"], ["bev-span-long"], 60.0, tmp_path / "out", **opts)
    assert launched == []


def test_preflight_simulates_two_scans_and_steps_a_network(lent, capsys):
    lent.preflight("train-x00", "cpu")  # the VLP-16 town: the cheapest world to build
    assert "preflight on cpu: simulated and stepped" in capsys.readouterr().out
