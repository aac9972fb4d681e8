"""Place recognition across sessions: AR@N by hand, the town frame, refused pairs, and the
``eval --database`` command on two drives through one generated town."""

from __future__ import annotations

import json

import numpy as np
import pytest

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.errors import DatasetError
from overlapmamba.train.sessions import (
    HIT_RADIUS,
    check_sessions,
    descriptor_recall,
    town_positions,
)


def test_average_recall_by_hand():
    pos_db = np.array([[0.0, 0, 0], [10, 0, 0], [20, 0, 0], [30, 0, 0]])
    desc_db = np.eye(4)
    # queries: near db 0, near db 2 (but looks like db 3), far from everything
    pos_q = np.array([[1.0, 0, 0], [21, 0, 0], [100, 0, 0]])
    desc_q = np.array([[1.0, 0, 0, 0], [0, 0, 0.6, 0.8], [0, 1.0, 0, 0]])
    r = descriptor_recall(desc_db, pos_db, desc_q, pos_q)
    assert r["queries"] == 2 and r["queries_total"] == 3 and r["radius_m"] == HIT_RADIUS
    assert r["ar@1"] == 0.5  # the second query's top-1 is db 3, 9 m away
    assert r["ar@5"] == r["ar@20"] == 1.0  # there are only 4 database scans
    # the one wrong first answer is 9 m from its query: the right street, too coarse
    assert r["wrong_top1"] == {"5-10 m": 1, "10-20 m": 0, "20-50 m": 0, "> 50 m": 0}
    far_db = pos_db.copy()
    far_db[3] = [131.0, 0, 0]  # the look-alike is now 110 m away: another place
    r = descriptor_recall(desc_db, far_db, desc_q[:2], pos_q[:2])
    assert r["ar@1"] == 0.5 and r["wrong_top1"]["> 50 m"] == 1


def _fake_session(root, seed, session, world_from=None):
    from conftest import write_synthetic_kitti

    write_synthetic_kitti(root, seed=seed, n_per_lap=4, laps=1)
    m = {"config": {"seed": seed, "session": session, "world": {"nx": 2}}}
    if world_from is not None:
        m["world_from_sequence"] = world_from.tolist()
    (root / "manifest.json").write_text(json.dumps(m))
    return open_sequence(root)


def test_positions_in_the_town_frame_and_pairs_that_are_refused(tmp_path):
    shift = np.eye(4)
    shift[:3, 3] = [3.0, -2.0, 0.5]
    a = _fake_session(tmp_path / "a", 1, 0)
    b = _fake_session(tmp_path / "b", 1, 1, world_from=shift)
    np.testing.assert_allclose(town_positions(b), b.poses[:, :3, 3] + [3.0, -2.0, 0.5])
    check_sessions(a, b)  # two sessions of town 1: fine
    with pytest.raises(DatasetError, match="are different towns"):
        check_sessions(a, _fake_session(tmp_path / "c", 2, 1))
    with pytest.raises(DatasetError, match="same session"):
        check_sessions(a, _fake_session(tmp_path / "d", 1, 0))
    far = np.eye(4)
    far[:3, 3] = [500.0, 0.0, 0.0]  # the same town, but a drive 500 m away from the first
    with pytest.raises(DatasetError, match="passes within 5 m.*share no place"):
        check_sessions(a, _fake_session(tmp_path / "e", 1, 1, world_from=far))


@pytest.mark.timeout(600)
def test_eval_across_sessions_of_a_generated_town(tmp_path):
    pytest.importorskip("torch")
    pytest.importorskip("embreex")
    from conftest import SMALL_MODEL, save_random_checkpoint
    from typer.testing import CliRunner

    from overlapmamba.cli import app
    from overlapmamba.synth.generate import generate
    from overlapmamba.synth.presets import PRESETS

    # two 30-scan drives through a 2 × 2 town: the second keeps to the first's streets, so
    # all 30 of its scans pass within 5 m of the first's (checked from the planned poses)
    town = {"nx": 2, "ny": 2, "block_min": 40.0, "block_max": 50.0}
    base = PRESETS["tiny"].model_copy(
        update={"seed": 1, "frames": 30, "preset": None, "world": town}
    )
    # (no overlap tables: 30 scans hold no loop, and the protocol needs only the poses)
    for name, session in (("s0", 0), ("s1", 1)):
        cfg = base.model_copy(update={"session": session})
        generate(tmp_path / name, cfg, ground_truth=False, progress=False, stall_timeout_s=60)
    ckpt = save_random_checkpoint(tmp_path / "random.pt", **SMALL_MODEL)
    out = tmp_path / "cross.json"
    args = ["eval", "--checkpoint", str(ckpt), "--sequence", str(tmp_path / "s1")]
    res = CliRunner().invoke(
        app, [*args, "--database", str(tmp_path / "s0"), "--json", str(out), "-q"]
    )
    assert res.exit_code == 0, res.output
    assert "Across sessions" in res.output and "Scan Context" in res.output
    cross = json.loads(out.read_text())["cross_session"]
    for method in ("model", "scan_context"):
        r = cross[method]
        assert r["queries"] == r["queries_total"] == 30
        assert 0 <= r["ar@1"] <= r["ar@5"] <= r["ar@20"] <= 1
        # every wrong first answer lands in one distance band
        assert sum(r["wrong_top1"].values()) == round((1 - r["ar@1"]) * r["queries"])
    assert "wrong" in res.output  # the bands' column (rich wraps its header)
    # the report's cross-session table: the same numbers for the same network
    import shutil

    from overlapmamba.train.presets import SHIPPED
    from overlapmamba.train.report import NETWORKS, cross_sessions, row_label

    (tmp_path / "runs" / SHIPPED).mkdir(parents=True)
    shutil.copy(ckpt, tmp_path / "runs" / SHIPPED / "best.pt")
    table = cross_sessions(tmp_path / "runs", tmp_path / "s0", tmp_path / "s1", progress=False)
    assert table["Scan Context"] == cross["scan_context"]
    shipped = next(row_label(k) for k, v in NETWORKS.items() if v == (SHIPPED, "best.pt"))
    assert table[shipped] == cross["model"]
    # the same session twice is refused with the reason
    res = CliRunner().invoke(app, [*args, "--database", str(tmp_path / "s1"), "-q"])
    assert res.exit_code != 0 and "same session" in res.output
    # across sensors: a third drive by a VLP-16 on a delivery robot against the HDL-64E map
    robot = base.model_copy(update={"session": 2, "sensor": "vlp16", "mount": "robot"})
    generate(tmp_path / "s2", robot, ground_truth=False, progress=False, stall_timeout_s=60)
    out2 = tmp_path / "across.json"
    args2 = ["eval", "--checkpoint", str(ckpt), "--sequence", str(tmp_path / "s2")]
    res = CliRunner().invoke(
        app, [*args2, "--database", str(tmp_path / "s0"), "--json", str(out2), "-q"]
    )
    assert res.exit_code == 0, res.output
    assert "vlp16 scans" in res.output and "no loop table" in res.output
    rec = json.loads(out2.read_text())
    assert rec["sensor"]["sensor"] == "vlp16" and rec["sensor"]["input"] != "native"
    assert rec["database_sensor"] == {"sensor": "kitti-hdl64", "input": "native"}
    assert "metrics" not in rec and rec["command"].startswith("overlapmamba eval")
    assert 0 <= rec["cross_session"]["model"]["ar@1"] <= 1
    # the sensor a drive was recorded with can be named; an unknown one is refused by name
    res = CliRunner().invoke(app, [*args2, "--database", str(tmp_path / "s0"), "--sensor",
                                   "mid360", "-q"])  # fmt: skip
    assert res.exit_code == 2 and "unknown sensor 'mid360'" in res.output
