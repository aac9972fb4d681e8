"""Choosing a run's epoch on the calibration town's pairs (benchmarks/epoch_pairs.py): the
choice and its tie rule, the trainer's own scores read back as it chose by them, the rank
correlation, a folder without checkpoints refused by name, and a continued run's first epochs
taken from its original's report only where the checkpoints are the same bytes."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from conftest import benchmark_module

bench = benchmark_module("epoch_pairs")


def _row(epoch: int, mean: float) -> dict:
    return {"epoch": epoch, "val": {"mean_ar@1": mean}}


def test_the_epoch_of_best_mean_pairs_recall_is_chosen_and_ties_go_to_the_earlier():
    assert bench.choose([_row(0, 0.2), _row(1, 0.6), _row(2, 0.5)]) == 1
    assert bench.choose([_row(3, 0.6), _row(4, 0.7), _row(5, 0.7)]) == 4


def test_spearman_ranks_and_ties():
    assert bench.spearman([1, 2, 3, 4], [10, 20, 30, 40]) == pytest.approx(1.0)
    assert bench.spearman([1, 2, 3, 4], [4, 3, 2, 1]) == pytest.approx(-1.0)
    # ranks, not values: a monotone but uneven relation is still 1
    assert bench.spearman([1, 2, 3, 4], [0.1, 0.2, 5.0, 90.0]) == pytest.approx(1.0)
    # ties share their mean rank: [0.5, 0.5, 2, 3] against [0, 1, 2, 3]
    want = 0.9486832980505138
    assert bench.spearman([1, 1, 2, 3], [0, 1, 2, 3]) == pytest.approx(want)
    assert math.isnan(bench.spearman([1, 1, 1], [1, 2, 3]))  # nothing to rank


def _metrics(tmp_path: Path, select_on: str) -> Path:
    def val(f1: float) -> dict:
        return {"all": {"f1max": f1}}

    sensors = {"vlp16": {"own": val(0.2), "cross": val(0.4)}}
    history = [
        {"epoch": 0, "val": val(0.9), "val_sensors": sensors},
        {"epoch": 1, "val": val(0.6), "val_sensors": sensors},
    ]
    record = {
        "train_config": {"select_on": select_on},
        "best": {"epoch": 0 if select_on == "val" else 1},
        "history": history,
    }
    (tmp_path / "metrics.json").write_text(json.dumps(record))
    return tmp_path


def test_the_trainers_scores_are_read_as_it_chose_by_them(tmp_path):
    scores, best = bench.trainer_scores(_metrics(tmp_path, "val"))
    assert scores == {0: 0.9, 1: 0.6} and best == 0
    scores, best = bench.trainer_scores(_metrics(tmp_path, "sensors"))
    assert scores[0] == pytest.approx((0.9 + 0.2 + 0.4) / 3)
    assert scores[1] == pytest.approx((0.6 + 0.2 + 0.4) / 3)
    assert best == 1


def test_epoch_checkpoints_are_found_by_number_and_a_folder_without_them_is_refused(tmp_path):
    for name in ("epoch-010.pt", "epoch-002.pt", "best.pt", "last.pt", "epoch-x.pt"):
        (tmp_path / name).write_bytes(b"")
    assert list(bench.epoch_files(tmp_path)) == [2, 10]
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(SystemExit, match="no epoch-NNN.pt"):
        bench.epoch_files(empty)


def _run_folder(path: Path, checkpoints: dict[int, bytes]) -> dict[int, Path]:
    path.mkdir()
    for epoch, data in checkpoints.items():
        (path / f"epoch-{epoch:03d}.pt").write_bytes(data)
    return bench.epoch_files(path)


def test_a_continued_runs_rows_are_reused_only_for_the_same_checkpoints_and_splits(tmp_path):
    _run_folder(tmp_path / "first", {0: b"a", 1: b"b", 2: b"c"})
    more = _run_folder(tmp_path / "more", {0: b"a", 1: b"B", 2: b"c", 3: b"d"})

    def measured(epoch: int, splits: tuple[str, ...]) -> dict:
        return {"epoch": epoch, "trainer_score": 0.5, **{s: {"mean_ar@1": 0.1} for s in splits}}

    report = tmp_path / "epoch-pairs-first.json"
    rows = [measured(0, ("val", "test")), measured(1, ("val", "test")), measured(2, ("val",))]
    report.write_text(json.dumps({"run": str(tmp_path / "first"), "epochs": rows}))
    # epoch 1 differs in bytes, epoch 2 lacks test, epoch 3 was never in the report
    assert list(bench.reusable_rows(report, more, ("val", "test"))) == [0]
    assert list(bench.reusable_rows(report, more, ("val",))) == [0, 2]
    assert set(bench.reusable_rows(report, more, ("val",))[0]) == {"epoch", "trainer_score", "val"}


def test_reuse_of_a_report_whose_run_folder_is_gone_is_refused(tmp_path):
    more = _run_folder(tmp_path / "more", {0: b"a"})
    report = tmp_path / "epoch-pairs-gone.json"
    report.write_text(json.dumps({"run": str(tmp_path / "gone"), "epochs": []}))
    with pytest.raises(SystemExit, match="not here to compare"):
        bench.reusable_rows(report, more, ("val",))


def test_reuse_of_a_report_measured_on_other_drives_lengths_is_refused(tmp_path):
    _run_folder(tmp_path / "first", {0: b"a"})
    more = _run_folder(tmp_path / "more", {0: b"a"})
    report = tmp_path / "epoch-pairs-first.json"
    rows = [{"epoch": 0, "trainer_score": 0.5, "val": {"mean_ar@1": 0.1}}]
    record = {"run": str(tmp_path / "first"), "frames": 300, "epochs": rows}
    report.write_text(json.dumps(record))
    with pytest.raises(SystemExit, match="300 scans a drive"):
        bench.reusable_rows(report, more, ("val",), frames=500)
    assert list(bench.reusable_rows(report, more, ("val",), frames=300)) == [0]
