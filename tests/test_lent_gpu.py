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
    assert {k: v for k, v in gt.params.items() if k != "fingerprint"} == {
        k: v for k, v in carried.params.items() if k != "fingerprint"
    }
