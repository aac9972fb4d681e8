"""``benchmarks/across_pairs.py``: issue 40's bar across sensors, pair by pair; and
``benchmarks/rerank_across.py``: the second stage's shortlist and weight across sensors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import benchmark_module
from service_kit import MODEL

across = benchmark_module("across_pairs")
rerank_across = benchmark_module("rerank_across")


def _row(q: str, m: str, desc: float, two: float, sc: float) -> dict:
    def ar(x: float) -> dict:
        return {"ar@1": x, "ar@5": x, "ar@20": x}

    return {
        "queries": q,
        "map": m,
        "descriptor": ar(desc),
        "two_stage": ar(two),
        "scan_context": ar(sc),
    }


def test_the_verdict_counts_pairs_across_sensors_that_clear_the_bar_and_beat_scan_context():
    rows = [
        _row("vlp16", "vlp16", 0.10, 0.10, 0.99),  # the same sensor: not one of the bar's pairs
        _row("vlp16", "xt32", 0.90, 0.84, 0.50),  # the descriptor meets it, two stages do not
        _row("xt32", "vlp16", 0.86, 0.95, 0.88),  # both clear 0.85, the descriptor not Scan Context
        _row("os0-128", "xt32", 0.85, 0.85, 0.85),  # at the bar, level with Scan Context: fails
    ]
    v = across.verdict(rows)
    assert v["pairs_across"] == 3
    assert v["descriptor"]["meeting_bar"] == 1 and v["two_stage"]["meeting_bar"] == 1
    assert v["descriptor"]["above_scan_context"] == 1 and v["two_stage"]["above_scan_context"] == 2
    assert v["descriptor"]["min_ar@1"] == 0.85 and v["two_stage"]["min_ar@1"] == 0.84
    assert v["scan_context"]["meeting_bar"] == 2 and v["scan_context"]["above_scan_context"] is None
    assert v["descriptor"]["mean_ar@1"] == pytest.approx((0.90 + 0.86 + 0.85) / 3)


@pytest.fixture(scope="module")
def two_drives(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two 20-scan drives through one small town, the first (``map``) by the KITTI HDL-64E,
    the second (``queries``) by a VLP-16 keeping to the first's streets (no overlap tables:
    AR needs the poses only)."""
    pytest.importorskip("embreex")
    from overlapmamba.synth.generate import generate
    from overlapmamba.synth.presets import PRESETS

    root = tmp_path_factory.mktemp("two-drives")
    town = {"nx": 2, "ny": 2, "block_min": 40.0, "block_max": 50.0}
    base = PRESETS["tiny"].model_copy(
        update={"seed": 1, "frames": 20, "preset": None, "world": town}
    )
    for name, session, sensor in (("map", 0, "kitti-hdl64"), ("queries", 1, "vlp16")):
        cfg = base.model_copy(update={"session": session, "sensor": sensor})
        generate(root / name, cfg, ground_truth=False, progress=False, stall_timeout_s=60)
    return root


@pytest.mark.timeout(600)
def test_a_pair_of_drives_by_two_sensors_answers_three_ways_and_keeps_its_scan_contexts(
    two_drives, tmp_path
):
    from overlapmamba.service.encoder import Encoder

    enc = Encoder(MODEL)
    drives = across.Drives(enc, tmp_path / "scratch")
    rerank = across.Rerank(20, 0.2)
    got = across.pair(drives, two_drives / "map", two_drives / "queries", rerank)
    assert got["queries_n"] == 20
    for name in across.ANSWERS:
        r = got[name]
        assert 0.0 <= r["ar@1"] <= r["ar@5"] <= r["ar@20"] <= 1.0
    # the Scan Contexts are kept beside the scratch drives, keyed by drive and recording,
    # and a second model's run reads them back unchanged
    kept = sorted((tmp_path / "scratch" / "scan-context").iterdir())
    assert [p.name.split("-")[0] for p in kept] == ["map", "queries"]
    first = np.load(kept[1])
    again = across.Drives(enc, tmp_path / "scratch")
    np.testing.assert_array_equal(again.scan_context(two_drives / "queries"), first)
    assert across.pair(again, two_drives / "map", two_drives / "queries", rerank) == got
    # a drive generated again (here: one pose moved) is described again, not read back
    import shutil

    moved = tmp_path / "again" / "map"
    shutil.copytree(two_drives / "map", moved)
    poses = (moved / "poses.txt").read_text().splitlines()
    first_pose = poses[0].split()
    first_pose[3] = str(float(first_pose[3]) + 1.0)
    (moved / "poses.txt").write_text("\n".join([" ".join(first_pose), *poses[1:]]) + "\n")
    again.scan_context(moved)
    assert len(list((tmp_path / "scratch" / "scan-context").iterdir())) == 3
    # a drive is never its own query session
    with pytest.raises(Exception, match="same session"):
        across.pair(drives, two_drives / "map", two_drives / "map", rerank)


def test_the_grid_and_the_choice_of_a_setting():
    assert rerank_across.settings((1, 20, 50), (0.2, 1.0)) == [
        (1, 0.0),
        (20, 0.2),
        (20, 1.0),
        (50, 0.2),
        (50, 1.0),
    ]
    rows = [
        {"shortlist": 50, "weight": 1.0, "mean_ar@1": 0.80},
        {"shortlist": 20, "weight": 1.0, "mean_ar@1": 0.80},  # as good, shorter: chosen
        {"shortlist": 20, "weight": 0.2, "mean_ar@1": 0.79},
        {"shortlist": 20, "weight": 8.0, "mean_ar@1": 0.80},  # as good, heavier
    ]
    assert rerank_across.choose(rows) is rows[1]
    rows.append({"shortlist": 200, "weight": 8.0, "mean_ar@1": 0.81})
    assert rerank_across.choose(rows) is rows[-1]


@pytest.mark.timeout(600)
def test_the_sweep_answers_as_the_service_s_second_stage_at_every_setting(two_drives, tmp_path):
    """One pass of correlations serves every (shortlist, weight): each AR@1 is what
    ``descriptor_recall`` gives with that second stage (the service's re-ranking)."""
    from overlapmamba.core.datasets import open_sequence
    from overlapmamba.core.rerank import OFF, Rerank
    from overlapmamba.service.encoder import Encoder
    from overlapmamba.train.sessions import descriptor_recall, town_positions

    drives = across.Drives(Encoder(MODEL), tmp_path / "scratch")
    pair = rerank_across.Pair(drives, two_drives / "map", two_drives / "queries", 200)
    assert pair.dist.shape == (20, 20)  # no longer than the map
    (d_db, y_db), (d_q, y_q) = (
        drives.model(two_drives / "map"),
        drives.model(two_drives / "queries"),
    )
    pos_db = town_positions(open_sequence(two_drives / "map"))
    pos_q = town_positions(open_sequence(two_drives / "queries"))
    for k, w in [(1, 0.0), (5, 0.2), (20, 0.2), (20, 8.0)]:
        rr = Rerank(k, w) if k > 1 else OFF
        want = descriptor_recall(d_db, pos_db, d_q, pos_q, yaw=(y_db, y_q), rerank=rr)["ar@1"]
        assert pair.ar1(k, w) == pytest.approx(want), (k, w)
    # scored by a leading part of each vector (a mixed first stage's network descriptor):
    # what descriptor_recall gives with that part
    part = rerank_across.Pair(drives, two_drives / "map", two_drives / "queries", 200, 64)
    for k, w in [(5, 0.2), (20, 8.0)]:
        rr = Rerank(k, w, part=64)
        want = descriptor_recall(d_db, pos_db, d_q, pos_q, yaw=(y_db, y_q), rerank=rr)["ar@1"]
        assert part.ar1(k, w, "network") == pytest.approx(want), (k, w)
        assert part.ar1(k, w) == pair.ar1(k, w)
    row = rerank_across.score({("vlp16", "kitti-hdl64"): pair}, (20, 0.2))
    assert row["cross_mean_ar@1"] == row["mean_ar@1"] == pair.ar1(20, 0.2)
    assert row["same_mean_ar@1"] is None and row["pairs_at_bar"] == int(pair.ar1(20, 0.2) >= 0.85)
