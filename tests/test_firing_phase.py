"""benchmarks/firing_phase.py compares a town with its drifting twin: it refuses any pair that
differs in more than the firings, and summarises the test towns only."""

from __future__ import annotations

import json

import pytest
from conftest import benchmark_module

from overlapmamba.synth.presets import DRIFT_PRESETS, PRESETS

firing_phase = benchmark_module("firing_phase")


def _town(root, name: str, **update) -> None:
    cfg = PRESETS[name].model_copy(update=update) if update else PRESETS[name]
    root.mkdir(parents=True)
    (root / "manifest.json").write_text(json.dumps({"config": cfg.model_dump()}))


def test_only_a_town_and_its_drifting_twin_are_compared(tmp_path):
    assert DRIFT_PRESETS == ("val-drift", "test-drift", "test-b-drift", "test-c-drift")
    _town(tmp_path / "test", "test")
    _town(tmp_path / "test-drift", "test-drift")
    firing_phase.check_twins(tmp_path / "test", tmp_path / "test-drift")
    with pytest.raises(SystemExit, match="must be locked"):
        firing_phase.check_twins(tmp_path / "test-drift", tmp_path / "test")
    _town(tmp_path / "test-b-drift", "test-b-drift")
    with pytest.raises(SystemExit, match=r"\['seed'\] differ"):
        firing_phase.check_twins(tmp_path / "test", tmp_path / "test-b-drift")
    with pytest.raises(SystemExit, match="make data data-drift"):
        firing_phase.check_twins(tmp_path / "test", tmp_path / "nowhere")


def test_the_summary_reads_the_test_towns_not_val():
    def cell(f1: float) -> dict:
        return {"descriptor": {"all": {"f1max": f1, "recall@1": f1}}}

    rows = {
        "a": {
            "val": {"locked": cell(0.0), "drifting": cell(1.0)},
            "test": {"locked": cell(0.8), "drifting": cell(0.7)},
            "test-b": {"locked": cell(0.6), "drifting": cell(0.7)},
        }
    }
    got = firing_phase.summary(rows, ["val", "test", "test-b"])
    assert got["towns"] == ["test", "test-b"]
    d = got["a"]["descriptor"]
    assert d["locked"] == pytest.approx(0.7) and d["drifting"] == pytest.approx(0.7)
    assert d["drifting_minus_locked"] == pytest.approx(0.0)
