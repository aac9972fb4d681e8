"""The baselines (Scan Context, the OT-style network), the training presets and the report."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import SMALL_MODEL, make_world, save_random_checkpoint

from overlapmamba.core.metrics import evaluate_loop_closure, evaluate_retrieval, nearest
from overlapmamba.core.poses import rotation_z, transform_points
from overlapmamba.core.rerank import Rerank
from overlapmamba.core.scancontext import (
    ScanContextParams,
    brute_force_shift_distance,
    match,
    retrieve,
    ring_key,
    scan_context,
)


@pytest.fixture(scope="module")
def world() -> np.ndarray:
    return make_world(np.random.default_rng(3))


def test_scan_context_bins_heights_and_ring_key():
    p = ScanContextParams(rings=4, sectors=8, max_range=40.0, lidar_height=2.0)
    pts = np.array(
        [
            [5.0, 0.1, 1.0],  # ring 0, sector 0 → 3.0
            [5.0, 0.2, -1.0],  # same bin, lower → max stays 3.0
            [-0.1, 15.0, 0.5],  # ring 1, sector 2 (azimuth 90.4°) → 2.5
            [-35.0, -0.1, -5.0],  # ring 3, sector 4, below ground → clipped to 0
            [90.0, 0.0, 1.0],  # beyond max_range: dropped
            [np.nan, 1.0, 1.0],  # not finite: dropped
        ]
    )
    sc = scan_context(pts, p)
    assert sc.shape == (4, 8) and sc.dtype == np.float32
    assert sc[0, 0] == 3.0 and sc[1, 2] == 2.5 and sc.sum() == 5.5
    np.testing.assert_allclose(ring_key(sc), [1 / 8, 1 / 8, 0, 0])


@pytest.mark.parametrize("theta", [0.0, 30.0, -84.0, 150.0, 179.0])
def test_scan_context_recovers_yaw_and_matches_the_slow_twin(world, theta):
    sc = scan_context(world)
    turned = scan_context(transform_points(world, rotation_z(-theta)))
    d, yaw = match(turned, sc[None])
    err = (yaw[0] - theta + 180) % 360 - 180
    assert abs(err) <= 6.0  # one sector
    assert d[0] < 0.1
    assert d[0] == pytest.approx(brute_force_shift_distance(turned, sc), abs=1e-9)
    # The ring key does not see the turn beyond points changing bins at sector edges.
    assert np.abs(ring_key(turned) - ring_key(sc)).max() <= 0.05


def test_scan_context_tells_places_apart(world):
    here = scan_context(world)
    moved = world.copy()
    moved[:, 0] += 25.0  # 25 m away
    d_same, _ = match(scan_context(transform_points(world, rotation_z(-40.0))), here[None])
    d_other, _ = match(scan_context(moved), here[None])
    assert d_same[0] < d_other[0]


def test_scan_context_retrieval_respects_the_database_limit():
    rng = np.random.default_rng(0)
    ctx = rng.uniform(0, 5, (30, 20, 60)).astype(np.float32)
    ctx[25] = ctx[3]  # frame 25 revisits frame 3
    queries, db_size = np.array([25, 26]), np.array([10, 1])
    ranked, dist = retrieve(ctx, queries, db_size, k=12, candidates=10)
    assert ranked[0, 0] == 3 and dist[0, 0] == pytest.approx(0.0, abs=1e-6)
    assert set(ranked[0][ranked[0] >= 0]) <= set(range(10))
    assert ranked[1, 0] == 0 and (ranked[1, 1:] == -1).all()
    assert np.isinf(dist[0, 10:]).all()  # beyond the re-ranked candidates: ranks only


def test_evaluate_retrieval_with_l2_equals_evaluate_loop_closure():
    rng = np.random.default_rng(1)
    desc = rng.normal(size=(160, 8))
    desc[130:] = desc[:30] + rng.normal(0, 0.05, (30, 8))
    positives = [np.array([i - 130]) if i >= 130 else np.array([], int) for i in range(160)]

    def l2(q, n, k):
        return nearest(desc[q], desc, k, allowed=np.arange(160)[None] < n[:, None])

    a = evaluate_loop_closure(desc, positives, exclude_recent_frames=20)
    b = evaluate_retrieval(l2, 160, positives, exclude_recent_frames=20)
    assert (a.auc, a.f1max, a.recall_at_1) == (b.auc, b.f1max, b.recall_at_1)
    assert a.recall_at_1 == 1.0


torch = pytest.importorskip("torch")

from typer.testing import CliRunner  # noqa: E402

from overlapmamba.cli import app  # noqa: E402
from overlapmamba.train.errors import ConfigError  # noqa: E402
from overlapmamba.train.evaluate import RERANKED  # noqa: E402
from overlapmamba.train.export import export_onnx  # noqa: E402
from overlapmamba.train.model import OverlapMamba, OverlapMambaConfig  # noqa: E402
from overlapmamba.train.presets import PRESETS, SHIPPED, TEST_DATA, get_preset  # noqa: E402
from overlapmamba.train.train import TrainConfig, train  # noqa: E402

SMALL = SMALL_MODEL
runner = CliRunner()


def test_transformer_mixer_is_yaw_invariant_and_exports(tmp_path):
    from overlapmamba.core.sensors import get_profile

    torch.manual_seed(0)
    cfg = OverlapMambaConfig(**SMALL, mixer="transformer", spp=False, ff_dim=64)
    model = OverlapMamba(cfg).eval()
    x = torch.rand(2, 1, 64, 900) * 40
    with torch.no_grad():
        d, y = model(x)
        d2, y2 = model(torch.roll(x, 321, -1))
    torch.testing.assert_close(d, d2, atol=1e-5, rtol=0)
    torch.testing.assert_close(torch.roll(y, 321, -1), y2, atol=1e-4, rtol=0)
    # The OT-style peer exports (for the encoder benchmark), verified against PyTorch.
    res = export_onnx(
        model, get_profile("kitti-hdl64"), tmp_path / "x.onnx", weight_format="float32"
    )
    assert res.scan_nodes == 0 and res.verification["descriptor_max_abs"] <= 1e-4
    with pytest.raises(ValueError, match="mixer 'lstm' is unknown"):
        OverlapMambaConfig(mixer="lstm")
    with pytest.raises(ValueError, match="not divisible by heads"):
        OverlapMambaConfig(mixer="transformer", d_model=30, heads=4)


def test_every_preset_builds_its_configs():
    assert {"default", "ot", "abl-full", "abl-ot"} <= set(PRESETS)
    for p in PRESETS.values():
        cfg = OverlapMambaConfig.from_dict(p.model)
        tc = TrainConfig.from_dict(p.train)
        assert not set(TEST_DATA) & set(p.data) and not any("/test" in d for d in p.data)
        # validation: the val town, or the sensor towns' validation drive (with renderings)
        allowed = ("data/synth/val", "data/synth/val-kitti-hdl64", "data/synth/val-drift")
        assert p.val in allowed, p.name
        assert all(v.startswith("data/synth/val-") for v in tc.val_sensors), p.name
        if tc.select_on == "sensors":
            assert p.val == "data/synth/val-kitti-hdl64" and tc.val_sensors
        if p.name.startswith("abl-"):
            assert tc.epochs * tc.epoch_scans == 10000  # one equal budget
            assert cfg.d_model == 64  # the shipped width
        assert (cfg.mixer == "transformer") == (p.name.removesuffix("-s1") in ("ot", "abl-ot"))
        base = PRESETS.get(p.name.removesuffix("-s1"))
        if p.name.endswith("-s1") and base is not None:  # a seed twin differs by its seed alone
            assert (p.model, p.data, p.val) == (base.model, base.data, base.val), p.name
            assert p.train == {**base.train, "seed": 1}, p.name
    # the shipped recipe: four towns, the scale-free loss, the ambiguous band left out
    d = TrainConfig.from_dict(get_preset("default").train)
    assert len(get_preset("default").data) == 4 and d.margin_scale == "normalised"
    assert d.negative_threshold < d.positive_threshold
    assert TrainConfig.from_dict(get_preset("robust").train).augment_config().dropout > 0
    d = get_preset("default")
    assert d.model == {} and TrainConfig.from_dict(d.train).loss == "imtrihard"
    with pytest.raises(ConfigError, match="unknown training preset 'x'; allowed: default"):
        get_preset("x")


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--preset", "nope"], "unknown training preset 'nope'"),
        (["--preset", "default", "--data", "x"], "--preset fixes the data"),
        (["--preset", "default"], "needs data/synth/train"),
        ([], "give --data"),
    ],
)
def test_train_preset_cli_errors(args, message, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # no data/synth here
    result = runner.invoke(app, ["train", *args])
    assert result.exit_code != 0
    assert message in result.output


@pytest.mark.real_data
def test_eval_real_transfers_to_hdl32_as_that_sensors_scans(nuscenes_dir, tmp_path):
    from overlapmamba.core.modelmeta import EncoderMetadata

    save_random_checkpoint(tmp_path / "random.pt", **SMALL)
    out = tmp_path / "real.json"
    args = ["eval-real", "--checkpoint", str(tmp_path / "random.pt"), "--sequence"]
    args += [str(nuscenes_dir), "--sensor", "hdl32", "--hit-radius", "6", "--json", str(out)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    r = json.loads(out.read_text())
    mode = EncoderMetadata.model_fields["sensor_input"].default  # what its export will say
    assert (r["sensor"], r["input"], r["scans"]) == ("hdl32", mode, 39)
    assert r["yaw_invariance"]["cosine_min"] > 0.999
    bad = runner.invoke(app, [*args[:-2], "--sensor", "mid360"])
    assert bad.exit_code == 2 and "unknown sensor 'mid360'" in bad.output


@pytest.mark.real_data
def test_eval_real_of_the_shipped_model_describes_each_scan_by_its_views(nuscenes_dir, tmp_path):
    """The shipped .onnx (sub-column views) through eval-real with another sensor's scans:
    every scan's views projected as an HDL-32E's, the views combined."""
    from overlapmamba.core.modelmeta import EncoderMetadata

    model = Path(__file__).resolve().parents[1] / "models" / "overlapmamba-hdl64.onnx"
    out = tmp_path / "real.json"
    args = ["eval-real", "--checkpoint", str(model), "--sequence", str(nuscenes_dir)]
    args += ["--profile", "hdl32", "--hit-radius", "6", "--json", str(out)]  # --sensor's alias
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    r = json.loads(out.read_text())
    assert r["sensor"] == "hdl32" and r["input"] != "native" and r["scans"] == 39
    onnx = pytest.importorskip("onnx")
    props = {p.key: p.value for p in onnx.load(str(model)).metadata_props}
    assert EncoderMetadata.from_props(props).views > 1
    # one view of this network gave 0.99827 here (README, Real scans)
    assert r["yaw_invariance"]["cosine_min"] > 0.999
    assert r["retrieval_odd_to_even"]["reranked"]["recall@1"] == 1.0


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_report_tables_from_tiny_runs(tiny_seq, tiny_val_seq, tiny_run, tmp_path, monkeypatch):
    import overlapmamba.train.report as report_mod
    from overlapmamba.train.report import (
        NARROW_RUNS,
        NARROW_UNTRAINED_LABEL,
        NETWORKS,
        build_report,
        row_label,
    )

    described: list[int] = []
    real_describe = report_mod.describe_sequence

    def counted(model, seq, profile, **kw):
        described.append(len(seq))
        return real_describe(model, seq, profile, **kw)

    monkeypatch.setattr(report_mod, "describe_sequence", counted)
    # the real-scan rows: the smaller real set only (KITTI's eval-real has its own test)
    real = {k: v for k, v in report_mod.REAL.items() if k == "nuscenes-hdl32"}
    monkeypatch.setattr(report_mod, "REAL", real)

    runs = tmp_path / "runs"
    # abl-full: SMALL for 2 epochs of 32 scans in batches of 16 (the session's tiny run)
    shutil.copytree(tiny_run[0], runs / "abl-full")
    ot = OverlapMambaConfig(**SMALL, mixer="transformer", spp=False, ff_dim=64)
    # (this run also goes through the training loop's mining: half its groups take a
    # negative mined by the starting weights from a pool of 64 scans)
    one = TrainConfig(
        epochs=1,
        epoch_scans=32,
        batch_size=16,
        recalibrate_batches=0,
        real="",
        hard_negatives=0.5,
        mine_pool=64,
    )
    history = train([tiny_seq], tiny_val_seq, runs / "abl-ot", ot, one, progress=False)
    mined = history[-1]["mining"]
    assert mined["pool"] == 64 and mined["anchors"] > 0 and mined["mine_s"] > 0
    assert mined["mined_d2"] < mined["pool_d2"]
    # the shipped run (presets.SHIPPED) is a copy of abl-full, its row the last epoch (a
    # tiny run's best may be its epoch 0); its epoch 0 is the untrained row
    shutil.copytree(runs / "abl-full", runs / SHIPPED)
    shutil.copy(runs / SHIPPED / "epoch-002.pt", runs / SHIPPED / "best.pt")
    shutil.copy(runs / SHIPPED / "epoch-002.pt", runs / "abl-full" / "best.pt")
    shipped = next(row_label(k) for k, v in NETWORKS.items() if v == (SHIPPED, "best.pt"))
    untrained_label = next(
        k
        for k, v in NETWORKS.items()
        if v == (SHIPPED, "epoch-000.pt")
        or (k == NARROW_UNTRAINED_LABEL and SHIPPED in NARROW_RUNS)
    )

    report = build_report(runs, tiny_val_seq, tmp_path / "report", progress=False)
    t1 = report["table1"]
    assert shipped.endswith(" (shipped)")
    assert list(t1) == [
        "Scan Context",
        untrained_label,
        "OT-style narrow, ablation budget",
        "OverlapMamba narrow, ablation budget",
        shipped,
        shipped + RERANKED,  # the service's answer: the yaw features re-rank the shortlist
    ]
    # the shipped run is a copy of abl-full: that network is described once, for both rows
    assert len(described) == 3
    assert t1["OverlapMamba narrow, ablation budget"] == t1[shipped]
    untrained = t1[untrained_label]["all"]
    assert untrained != t1[shipped]["all"]
    for subs in t1.values():
        assert set(subs) == {"all", "same", "reverse"}
        assert 0 <= subs["all"]["f1max"] <= 1 and subs["all"]["queries_with_loop"] > 0
    assert set(report["ablation"]) == {"full", "OT-style (transformer mixer, no SPP)"}
    assert report["ablation"]["full"]["scans_seen"] == 64
    assert report["ablation"]["full"]["forward_ms"] > 0
    # Table IV starts from epoch 0: the initial weights, batch norm recalibrated, no loss
    table_four = report["epochs"]["ImTrihard (abl-full)"]["history"]
    assert [h["epoch"] for h in table_four] == [0, 1, 2] and table_four[0]["loss"] is None
    assert t1[shipped + RERANKED] != t1[shipped]
    nus = report["real"]["nuscenes-hdl32"]
    assert "skipped" in nus or nus["yaw_invariance"]["cosine_min"] > 0.9
    reranked = nus.get("retrieval_odd_to_even", {}).get("reranked", {})
    assert "skipped" in nus or reranked["shortlist"] == Rerank().shortlist
    # where each method loses F1max, per town: every query of the subset is sorted once
    errors = report["errors"][tiny_val_seq.name]
    assert set(errors) == set(t1)
    for label, subs in errors.items():
        for sub in ("all", "same", "reverse"):
            e, m = subs[sub], t1[label][sub]
            fa, miss = e["false_alarms"], e["missed_loops"]
            assert e["accepted"] == e["true_closures"] + fa["total"]
            assert fa["total"] == fa["neighbours"] + fa["look_alikes"]
            assert miss["total"] == miss["wrong_top1"] + miss["rejected"]
            assert e["true_closures"] + miss["total"] == m["queries_with_loop"]
    md = (tmp_path / "report" / "tables.md").read_text()
    assert "| nuscenes-hdl32" in md
    assert "| Scan Context | reverse |" in md and "Table IV" in md
    assert "Where F1max is lost" in md
    for png in ("pr_test.png", "epochs.png"):
        assert (tmp_path / "report" / png).stat().st_size > 10_000
    on_disk = json.loads((tmp_path / "report" / "report.json").read_text())
    assert on_disk["table1"]["Scan Context"]["all"]["f1max"] == t1["Scan Context"]["all"]["f1max"]


def test_table_one_mean_over_towns_averages_rates_and_sums_counts():
    from overlapmamba.train.report import mean_over_towns

    def town(f1, n):
        row = {"auc": f1, "f1max": f1, "recall@1": f1, "recall@1%": 1.0}
        return {"Scan Context": {"all": {**row, "queries": n, "queries_with_loop": n // 2}}}

    nan = float("nan")
    mean = mean_over_towns({"a": town(0.5, 10), "b": town(0.7, 20), "c": town(nan, 4)})
    m = mean["Scan Context"]["all"]
    assert m["f1max"] == pytest.approx(0.6)  # a town without loops of a kind does not count
    assert m["queries"] == 34 and m["queries_with_loop"] == 17


def test_the_shipped_row_falls_back_to_the_exported_encoder(tmp_path):
    """Without the shipped run's best.pt (a fresh machine), Table I's shipped row and the
    real-scan checks read the exported .onnx; with it, the checkpoint; with neither, none."""
    from overlapmamba.train.checkpoint import ExportedNetwork, load_model
    from overlapmamba.train.export import export_onnx
    from overlapmamba.train.presets import SHIPPED
    from overlapmamba.train.report import NETWORKS, _networks, row_label, shipped_model

    ckpt = save_random_checkpoint(tmp_path / "random.pt", **SMALL_MODEL)
    model, profile, _ = load_model(ckpt)
    onnx = tmp_path / "shipped.onnx"
    export_onnx(model, profile, onnx, weight_format="float32")
    runs = tmp_path / "runs"
    runs.mkdir()
    shipped = next(row_label(k) for k, v in NETWORKS.items() if v == (SHIPPED, "best.pt"))
    assert shipped_model(runs, onnx) == onnx
    rows = {label: net for label, net, _ in _networks(runs, onnx)}
    assert list(rows) == [shipped] and isinstance(rows[shipped], ExportedNetwork)
    assert shipped_model(runs, None) is None and not list(_networks(runs, None))
    (runs / SHIPPED).mkdir()
    shutil.copy(ckpt, runs / SHIPPED / "best.pt")
    assert shipped_model(runs, onnx) == runs / SHIPPED / "best.pt"
    rows = {label: net for label, net, _ in _networks(runs, onnx)}
    assert not isinstance(rows[shipped], ExportedNetwork)


def test_the_report_scores_the_service_answer_with_the_files_own_second_stage():
    """The report's "as the service answers" rows re-rank with the second stage the service
    applies with that file: its calibrated rerank (the one-pass file chose another than the
    defaults on val), the defaults for a checkpoint or a file without one."""
    from overlapmamba.train.checkpoint import load_model
    from overlapmamba.train.report import SERVICE_RERANK, service_rerank

    models = Path(__file__).resolve().parents[1] / "models"
    for name in ("overlapmamba-hdl64.onnx", "overlapmamba-hdl64-one-pass.onnx"):
        model, _, _ = load_model(models / name)
        values = model.meta.calibration["rerank"].values
        got = service_rerank(model)
        assert (got.shortlist, got.weight) == (values["shortlist"], values["weight"]), name
    one_pass, _, _ = load_model(models / "overlapmamba-hdl64-one-pass.onnx")
    assert service_rerank(one_pass) != SERVICE_RERANK  # else this test checks nothing
    # scored as calibrated: by the network's 256 floats ahead of 16 channels × 32 bins
    assert one_pass.meta.calibration["rerank"].values["score"] == "network"
    assert service_rerank(one_pass).part == 256
    assert service_rerank(object()) == SERVICE_RERANK  # a network without a file's metadata


def test_the_report_refuses_a_test_town_without_loops(kitti_seq_dir, tmp_path):
    """Found in review: ``report`` on a test town with no revisit wrote tables of NaN and
    exited 0, where ``eval`` refuses the same town: it is refused, naming it."""
    from service_kit import MODEL

    from overlapmamba.core.errors import DatasetError
    from overlapmamba.train.report import table_one

    (tmp_path / "runs").mkdir()
    with pytest.raises(DatasetError, match="has no loop closure"):
        table_one(tmp_path / "runs", kitti_seq_dir, progress=False, onnx=MODEL)
