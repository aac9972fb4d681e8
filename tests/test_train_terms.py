"""The training recipe's terms on the tiny generated towns: band groups and the band term,
a run continued from an exported encoder with the turn and sensor terms, the loss's health
over a few steps, and mined hard negatives."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("embreex")

from conftest import SMALL_MODEL, small_run  # noqa: E402

from overlapmamba.core.datasets import open_sequence  # noqa: E402
from overlapmamba.core.sensors import get_profile  # noqa: E402
from overlapmamba.train.batches import GROUP, BatchPlan, BatchSampler, PairIndex  # noqa: E402
from overlapmamba.train.checkpoint import load_model, read_checkpoint  # noqa: E402
from overlapmamba.train.errors import ConfigError  # noqa: E402
from overlapmamba.train.model import OverlapMamba, OverlapMambaConfig  # noqa: E402
from overlapmamba.train.train import TrainConfig, train  # noqa: E402

SMALL = SMALL_MODEL


def test_band_groups_bring_a_neighbour_and_cost_no_draw_when_off(tiny_seq):
    """With a band share of 1 every group's negative is a scan of the anchor's ambiguous band
    (overlap in (0.1, 0.3]) where the anchor has one; with 0 the batches are those drawn
    without the option (the same generator state gives the same batches)."""
    pairs = PairIndex.from_sequences([open_sequence(tiny_seq)])
    sampler = BatchSampler(pairs, BatchPlan(batch_size=16, negative_threshold=0.1))
    banded = 0
    for idx in sampler.epoch(np.random.default_rng(0), 160, band=1.0):
        ov = pairs.submatrix(idx)
        for g in range(0, 16, GROUP):
            assert ov[g, g + 1] > 0.3 and ov[g, g + 2] > 0.3
            if len(sampler.band[int(idx[g])]) > 3:  # free ones left even in a full batch
                assert 0.1 < ov[g, g + 3] <= 0.3
                banded += 1
    assert banded >= 5
    plain = sampler.epoch(np.random.default_rng(1), 64)
    off = sampler.epoch(np.random.default_rng(1), 64, band=0.0)
    assert all(np.array_equal(a, b) for a, b in zip(plain, off, strict=True))
    with pytest.raises(ConfigError, match="needs loss 'imtrihard'"):
        TrainConfig(band_weight=0.5, loss="triplet")
    with pytest.raises(ConfigError, match="0 ≤ band_share ≤ 1"):
        TrainConfig(band_share=2.0)


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_band_term_starts_at_its_epoch_and_changes_nothing_before(
    tiny_seq, tiny_val_seq, tiny_run, tmp_path
):
    """A run with the band ranking from epoch 2 is the plain run, weight for weight, through
    epoch 1 (so a recipe that switches it on late may continue a plain run's checkpoint), and
    then trains with it: its hinges are counted in epoch 2's health only."""
    straight, _ = tiny_run
    band = dict(band_weight=0.5, band_alpha=0.2, band_share=1.0, band_from_epoch=2)
    out = tmp_path / "band"
    history = train(
        [tiny_seq],
        tiny_val_seq,
        out,
        OverlapMambaConfig(**SMALL),
        small_run(**band),
        progress=False,
    )
    a, b = read_checkpoint(straight / "epoch-001.pt"), read_checkpoint(out / "epoch-001.pt")
    for k in a["state_dict"]:
        torch.testing.assert_close(a["state_dict"][k], b["state_dict"][k], rtol=1e-6, atol=1e-7)
    assert all(r["band_active"] != r["band_active"] for r in history[1]["health_log"])  # NaN
    assert all(0 <= r["band_active"] <= 1 for r in history[2]["health_log"])
    assert all(r["d_band"] > 0 for r in history[2]["health_log"])  # every batch has some
    c = read_checkpoint(straight / "epoch-002.pt")["state_dict"]
    d = read_checkpoint(out / "epoch-002.pt")["state_dict"]
    assert any(not torch.equal(c[k], d[k]) for k in c if k.endswith("weight"))


@pytest.mark.timeout(900)  # when run alone, its set-up waits for the tiny towns and run
def test_a_run_continues_an_exported_encoder_with_the_turn_term(
    tiny_seq, tiny_val_seq, tiny_run, tiny_onnx, tmp_path
):
    """--init MODEL.onnx: the run starts from the encoder's recovered weights (epoch 0 is
    that network, validated, its batch norm neither recalibrated nor updated after), and
    the turn term feeds turned copies and the sensor term copies seen as another sensor,
    each recording how far they moved; a start that does not fit the run is refused with
    the reason."""
    straight, history = tiny_run
    model, _, _ = load_model(straight / "epoch-002.pt")
    onnx_path = tiny_onnx  # that checkpoint exported
    turn = dict(turn_weight=1.0, turn_scans=2, epochs=1, freeze_bn=True, init=str(onnx_path))
    turn |= {"look_weight": 1.0, "look_scans": 3}
    out = tmp_path / "continued"
    got = train([tiny_seq], tiny_val_seq, out, None, small_run(**turn), progress=False)
    f1 = history[2]["val"]["all"]["f1max"]
    assert got[0]["val"]["all"]["f1max"] == pytest.approx(f1, abs=1e-3)
    start, after = (read_checkpoint(out / f"epoch-00{e}.pt")["state_dict"] for e in (0, 1))
    assert read_checkpoint(out / "epoch-000.pt")["model_config"] == model.cfg.to_dict()
    for key in ("spp.cv1.1.running_mean", "spp.cv1.1.running_var", "spp.cv2.1.running_mean"):
        torch.testing.assert_close(start[key], after[key], rtol=0, atol=0)  # frozen
    assert not torch.equal(start["blocks.0.in_proj.weight"], after["blocks.0.in_proj.weight"])
    assert all(r["d_turn"] > 0 for r in got[1]["health_log"])
    assert all(r["d_look"] > 0 for r in got[1]["health_log"])
    for key in ("d_turn", "d_look"):
        assert all(r[key] != r[key] for r in history[1]["health_log"])  # off: NaN

    with pytest.raises(ConfigError, match="set freeze_bn = true"):
        small_run(init=str(onnx_path))
    with pytest.raises(ConfigError, match="a network with other d_model"):
        train(
            [tiny_seq],
            tiny_val_seq,
            tmp_path / "other",
            OverlapMambaConfig(**{**SMALL, "d_model": 16}),
            small_run(**turn),
            progress=False,
        )
    with pytest.raises(ConfigError, match="is not a file"):
        train(
            [tiny_seq],
            tiny_val_seq,
            tmp_path / "gone",
            None,
            small_run(**{**turn, "init": str(tmp_path / "gone.onnx")}),
            progress=False,
        )


@pytest.mark.timeout(900)  # when run alone, its set-up waits for the tiny towns and run
def test_a_run_continues_an_aligned_encoder_on_aligned_images(
    tiny_seq, tiny_val_seq, tiny_run, tiny_onnx, tmp_path
):
    """--init of a file with aligned columns: the run takes the file's column phase, trains
    and validates on aligned images (epoch 0 scores what evaluating the file scores), and its
    export is aligned again; a config given alongside may set the phase, the turn term is
    refused with aligned columns, and a bird's-eye input takes them."""
    import shutil

    from overlapmamba.train.evaluate import describe_sequence, loop_closure, sequence_loops
    from overlapmamba.train.export import export_onnx
    from overlapmamba.train.modelfile import read_metadata, with_column_phase
    from overlapmamba.train.train_inputs import start_config

    straight, _ = tiny_run
    model, profile, _ = load_model(straight / "epoch-002.pt")
    onnx_path = Path(shutil.copy(tiny_onnx, tmp_path / "start.onnx"))  # epoch-002.pt's
    with_column_phase(onnx_path, "aligned")
    exported, _, _ = load_model(onnx_path)
    val = open_sequence(tiny_val_seq)
    desc, _ = describe_sequence(exported, val, profile)
    f1 = loop_closure(desc, sequence_loops(val, profile))["all"].f1max
    plain, _ = describe_sequence(model, val, profile)
    assert not np.allclose(desc, plain, atol=1e-3)  # the phase matters to this network

    run = dict(epochs=1, freeze_bn=True, init=str(onnx_path))
    out = tmp_path / "aligned"
    got = train([tiny_seq], tiny_val_seq, out, None, small_run(**run), progress=False)
    assert got[0]["val"]["all"]["f1max"] == pytest.approx(f1, abs=1e-3)
    continued, _, _ = load_model(out / "epoch-001.pt")
    assert continued.cfg.column_phase == "aligned"
    path = export_onnx(continued, profile, tmp_path / "after.onnx", weight_format="float32").path
    assert read_metadata(path).column_phase == "aligned"

    # the run's config is start_config's (its checkpoint kept it, above)
    assert start_config(small_run(**run), None).column_phase == "aligned"
    sensor = OverlapMambaConfig(**{**SMALL, "column_phase": "sensor"})
    assert start_config(small_run(**run), sensor).column_phase == "sensor"
    assert start_config(small_run(**run), OverlapMambaConfig(**SMALL)).column_phase == "aligned"
    with pytest.raises(ConfigError, match="the turn term has nothing to teach"):
        train(
            [tiny_seq],
            tiny_val_seq,
            tmp_path / "turn",
            None,
            small_run(**run, turn_weight=1.0, turn_scans=2),
            progress=False,
        )
    bev = OverlapMambaConfig(**{**SMALL, "column_phase": "aligned", "sensor_input": "bev-span"})
    assert bev.column_phase == "aligned"
    with pytest.raises(ValueError, match="column_phase 'diagonal' is unknown"):
        OverlapMambaConfig(**{**SMALL, "column_phase": "diagonal"})


@pytest.mark.timeout(600)  # when run alone, its set-up generates the tiny town
def test_the_recipe_keeps_the_spread_and_grows_the_separation(tiny_seq):
    """The shipped recipe's sampler, augmentation and loss for 12 steps of the small network on
    the tiny town: the descriptors must not shrink towards one point (the collapse the old
    margin caused) while negatives move away from positives at the descriptors' scale."""
    from overlapmamba.train.augment import Augmenter
    from overlapmamba.train.health import HealthLog, batch_distances
    from overlapmamba.train.losses import pair_masks
    from overlapmamba.train.rangecache import range_images

    tc = TrainConfig()  # the defaults are the recipe
    seq = open_sequence(tiny_seq)
    pairs = PairIndex.from_sequences([seq])
    plan = BatchPlan(16, tc.positive_threshold, negative_threshold=tc.negative_threshold)
    sampler = BatchSampler(pairs, plan)
    model_cfg = OverlapMambaConfig(**SMALL)
    images = range_images(seq, get_profile(model_cfg.sensor), progress=False)
    augment = Augmenter(tc.augment_config(), get_profile(model_cfg.sensor), model_cfg.circular)
    torch.manual_seed(0)
    model = OverlapMamba(model_cfg).train()
    opt = torch.optim.Adam(model.parameters(), lr=tc.lr)
    loss_fn, health = tc.loss_fn(), HealthLog(every=3)
    rng = np.random.default_rng(0)
    for idx in sampler.epoch(rng, 16 * 12):
        desc, _ = model(torch.from_numpy(augment(images[idx], rng))[:, None])
        overlap = torch.from_numpy(pairs.submatrix(idx))
        out = loss_fn(desc, overlap)
        opt.zero_grad()
        out.value.backward()
        opt.step()
        masks = pair_masks(overlap, tc.positive_threshold, tc.negative_threshold)
        health.add(
            {"loss": out.value.item(), "active": out.active, "margin": out.margin}
            | batch_distances(desc, *masks)
        )
    spreads = [r["spread"] for r in health.logged]
    assert len(spreads) == 4 and min(spreads) > 0.5 * spreads[0], spreads
    assert not health.collapsing()
    sep = [r["separation"] for r in health.logged]
    assert sep[-1] > sep[0] > 0, sep


def test_mined_negatives_are_the_nearest_clearly_different_scans(tiny_seq):
    """overlapmamba.train.mining on the tiny town with stand-in descriptors: each anchor's
    candidates are its nearest pool scans (squared L2) that do not overlap it, and a batch
    of mined groups takes its negatives from them."""
    from overlapmamba.train.mining import mine

    pairs = PairIndex.from_sequences([open_sequence(tiny_seq)])
    sampler = BatchSampler(pairs, BatchPlan(batch_size=16, negative_threshold=0.1))
    rng = np.random.default_rng(0)
    pool = np.sort(rng.choice(len(pairs), 200, replace=False))
    desc = rng.normal(size=(len(pool), 8)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    hard = mine(pool, desc, lambda a: sampler.related[a], sampler.anchors, top=5)
    assert len(hard.anchors) > 20 and hard.stats["mined_d2"] < hard.stats["pool_d2"]
    at = {int(g): i for i, g in enumerate(pool)}
    for a, cands in hard.candidates.items():
        allowed = [j for j in pool if j != a and j not in set(sampler.related[a].tolist())]
        d2 = {int(j): float(((desc[at[a]] - desc[at[int(j)]]) ** 2).sum()) for j in allowed}
        want = sorted(d2, key=lambda j: (d2[j], j))[: len(cands)]
        assert sorted(d2[int(c)] for c in cands) == pytest.approx([d2[j] for j in want])
        assert a in sampler.anchors and a not in cands
    for idx in sampler.epoch(rng, 64, hard, share=1.0):
        ov = pairs.submatrix(idx)
        for g in range(0, 16, GROUP):
            anchor, negative = int(idx[g]), int(idx[g + 3])
            assert anchor in hard.candidates and negative in hard.candidates[anchor]
            assert ov[g, g + 3] <= 0.1 and ov[g, g + 1] > 0.3
    with pytest.raises(ConfigError, match="0 ≤ hard_negatives ≤ 1"):
        TrainConfig(hard_negatives=1.5)


def test_an_init_file_that_is_nowhere_names_both_places_looked(tmp_path, monkeypatch):
    """Found in review: ``train --init nope.pt`` run from another folder said only that
    REPO/nope.pt does not exist, as if the path were taken from the repository; it is
    looked for from here first, and both places are named."""
    from overlapmamba.core.errors import ConfigError
    from overlapmamba.train.train_config import ROOT, TrainConfig
    from overlapmamba.train.train_inputs import start_config

    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError) as err:
        start_config(TrainConfig(init="nope.pt"), None)
    assert f"neither {tmp_path / 'nope.pt'} nor {ROOT / 'nope.pt'} is a file" in str(err.value)
