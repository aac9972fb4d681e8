"""A first stage reduced to fewer floats in an exported encoder (overlapmamba.train.reduce_head):
the fit, the graph's descriptor against the numpy reduction, the files it would mislead, the
way back to the network's descriptor, the second stage's score it can still give, the CLI on a
generated town and the service serving the reduced descriptor."""

from __future__ import annotations

import numpy as np
import pytest
from service_kit import MODEL, running, three_keyframes_then_a_turned_query

from overlapmamba.core.rerank import Rerank, with_score
from overlapmamba.core.yaw_spectrum import FirstStage, unit
from overlapmamba.service.encoder import Encoder
from overlapmamba.service.settings import Settings
from overlapmamba.train.errors import ExportError
from overlapmamba.train.export import run_onnx
from overlapmamba.train.modelfile import read_metadata, rewrite_metadata
from overlapmamba.train.reduce_head import (
    fit_directions,
    parse_reduction,
    reduce_vectors,
    split_directions,
    with_reduction,
)
from overlapmamba.train.spectrum_head import with_first_stage, without_first_stage

STAGE = FirstStage.parse("mixed:0.75:8:sqrt")  # 256 + 16 · 8 = 384 floats


@pytest.fixture(scope="module")
def staged(tmp_path_factory) -> object:
    """The shipped encoder without its calibration, a mixed first stage written in."""
    root = tmp_path_factory.mktemp("reduce")
    rewrite_metadata(MODEL, root / "plain.onnx", lambda meta: {"calibration": {}})
    with_first_stage(root / "plain.onnx", root / "staged.onnx", STAGE)
    return root


def images(seed: int, n: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0, 1, size=(n, 1, 64, 900)).astype(np.float32)


def test_the_directions_are_orthonormal_ordered_and_repeatable():
    rng = np.random.default_rng(0)
    x = unit(rng.normal(size=(200, 40)) * np.linspace(3, 0.1, 40) + 5.0)
    d, kept = fit_directions(x, 6)
    assert d.shape == (40, 6) and d.dtype == np.float32
    np.testing.assert_allclose(d.T @ d, np.eye(6), atol=1e-5)
    var = ((x - x.mean(0)) @ d).var(axis=0)
    assert np.all(np.diff(var) <= 1e-9) and 0 < kept < 1
    assert fit_directions(x, 12)[1] > kept
    np.testing.assert_array_equal(fit_directions(x[::-1].copy(), 6)[0].round(4), d.round(4))
    y = reduce_vectors(x, d)
    np.testing.assert_allclose(np.linalg.norm(y, axis=1), 1.0, atol=1e-5)


@pytest.mark.parametrize(
    ("rows", "dim", "match"),
    [(200, 40, r"keep 1 … 39 floats; got 40"), (200, 0, "got 0"), (5, 6, "at least 6 needed")],
)
def test_a_fit_that_cannot_be_made_is_refused(rows, dim, match):
    x = np.random.default_rng(1).normal(size=(rows, 40))
    with pytest.raises(ValueError, match=match):
        fit_directions(x, dim)
    x[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN or infinite"):
        fit_directions(x, 3)


def test_the_graphs_descriptor_is_the_numpy_reduction_and_the_yaw_features_stay(staged, tmp_path):
    fit = run_onnx(staged / "staged.onnx", images(2, 24))[0]
    directions, kept = fit_directions(fit, 16)
    out = tmp_path / "reduced.onnx"
    meta = with_reduction(staged / "staged.onnx", out, directions, {"a town": {"scans": 24}}, kept)
    before = read_metadata(staged / "staged.onnx")
    assert meta.descriptor_dim == 16 and meta.first_stage == STAGE.name
    assert meta.reduction["from_dim"] == 384 and meta.reduction["dim"] == 16
    assert meta.reduction["source_model_id"] == before.model_id
    assert meta.model_id != before.model_id and read_metadata(out) == meta
    x = images(3, 2)
    d0, y0 = run_onnx(staged / "staged.onnx", x)
    d1, y1 = run_onnx(out, x)
    np.testing.assert_array_equal(y1, y0)
    np.testing.assert_allclose(d1, reduce_vectors(d0, directions), atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(d1, axis=1), 1.0, atol=1e-5)


def test_files_it_would_mislead_are_refused(staged, tmp_path):
    d = np.linalg.qr(np.random.default_rng(4).normal(size=(384, 8)))[0]
    with pytest.raises(ExportError, match="carries calibration"):
        with_reduction(MODEL, tmp_path / "x.onnx", d[:256], {}, 0.5)
    with pytest.raises(ExportError, match=r"shape \(384, 8\) do not take .*256-float"):
        with_reduction(staged / "plain.onnx", tmp_path / "x.onnx", d, {}, 0.5)
    once = tmp_path / "once.onnx"
    with_reduction(staged / "staged.onnx", once, d, {}, 0.5)
    with pytest.raises(ExportError, match=r"reduced already \(384 → 8 floats\)"):
        with_reduction(once, tmp_path / "x.onnx", d[:8, :4], {}, 0.5)
    with pytest.raises(ExportError, match="already carries first stage"):
        with_first_stage(once, tmp_path / "x.onnx", FirstStage(1.0, 8))
    assert not (tmp_path / "x.onnx").exists()


def test_the_second_stage_cannot_score_by_a_network_descriptor_no_longer_there(staged, tmp_path):
    d = np.linalg.qr(np.random.default_rng(5).normal(size=(384, 8)))[0]
    meta = with_reduction(staged / "staged.onnx", tmp_path / "r.onnx", d, {}, 0.5)
    assert with_score(Rerank(), "stage", meta).part is None
    with pytest.raises(ValueError, match="no\\s+longer hold the network's own descriptor"):
        with_score(Rerank(), "network", meta)
    assert with_score(Rerank(), "network", read_metadata(staged / "staged.onnx")).part == 256


@pytest.mark.parametrize(
    ("text", "want"), [("256", (256, None)), ("96+160", (256, 96)), (" 8+8 ", (16, 8))]
)
def test_a_reduction_is_k_or_k1_plus_k2(text, want):
    assert parse_reduction(text) == want


@pytest.mark.parametrize("text", ["", "0", "96+0", "1+2+3", "a+b", "-4", "256.5"])
def test_a_reduction_that_is_neither_is_refused_naming_both(text):
    with pytest.raises(ValueError, match=r"is not K or K1\+K2"):
        parse_reduction(text)


def test_a_split_reduction_keeps_the_network_part_to_score_by(staged, tmp_path):
    """K1+K2: the descriptor's part and the spectrum's reduced each on its own, the network's
    distance approximated by the leading K1 floats, which a 'network' second stage reads."""
    fit = run_onnx(staged / "staged.onnx", images(9, 24))[0]
    d, kept = split_directions(fit, 256, 6, 10)
    assert d.shape == (384, 16) and not d[256:, :6].any() and not d[:256, 6:].any()
    np.testing.assert_allclose(d[:256, :6], fit_directions(fit[:, :256], 6)[0])
    assert 0 < kept < 1
    meta = with_reduction(staged / "staged.onnx", tmp_path / "s.onnx", d, {}, kept, 6)
    assert meta.reduction["network_part"] == 6
    assert with_score(Rerank(), "network", meta).part == 6
    assert with_score(Rerank(), "stage", meta).part is None
    with pytest.raises(ValueError, match="not one of stage, network"):
        with_score(Rerank(), "both", meta)
    mixed = d.copy()
    mixed[300, 0] = 0.1  # a network column reading the spectrum
    with pytest.raises(ExportError, match="first 6 columns must read only the network"):
        with_reduction(staged / "staged.onnx", tmp_path / "x.onnx", mixed, {}, kept, 6)
    plain_d = np.linalg.qr(np.random.default_rng(9).normal(size=(256, 8)))[0]
    with pytest.raises(ExportError, match="needs a mixed first stage"):
        with_reduction(staged / "plain.onnx", tmp_path / "x.onnx", plain_d, {}, 0.5, 4)
    assert not (tmp_path / "x.onnx").exists()


def test_taking_the_first_stage_out_takes_the_reduction_too(staged, tmp_path):
    d = np.linalg.qr(np.random.default_rng(6).normal(size=(384, 8)))[0]
    with_reduction(staged / "staged.onnx", tmp_path / "r.onnx", d, {}, 0.5)
    back = without_first_stage(tmp_path / "r.onnx", tmp_path / "back.onnx")
    unreduced = without_first_stage(staged / "staged.onnx", tmp_path / "unreduced.onnx")
    assert back.reduction == {} and back.first_stage == "descriptor"
    assert back.descriptor_dim == 256 and back.model_id == unreduced.model_id
    x = images(7, 2)
    np.testing.assert_allclose(
        run_onnx(tmp_path / "back.onnx", x)[0], run_onnx(staged / "plain.onnx", x)[0], atol=1e-6
    )


def test_the_cli_fits_on_a_town_and_refuses_half_an_order(staged, tmp_path, synthetic_seq_dir):
    """On a 48-scan drive: the fit needs more scans than the floats it keeps, and every scan
    is described as the three-view file describes it (a 350-scan town took 150 s)."""
    from typer.testing import CliRunner

    from overlapmamba.cli import app

    town = synthetic_seq_dir
    out = tmp_path / "cli.onnx"
    args = ["export", str(staged / "staged.onnx"), "--out", str(out)]
    r = CliRunner().invoke(app, [*args, "--reduce", "8"])
    assert r.exit_code == 2 and "--reduce and --fit-on go together" in r.output, r.output
    assert not out.exists()
    r = CliRunner().invoke(app, [*args, "--reduce", "8", "--fit-on", str(town)])
    assert r.exit_code == 0, r.output
    meta = read_metadata(out)
    assert meta.descriptor_dim == 8 and meta.reduction["fitted_on"][town.name]["scans"] > 8
    r = CliRunner().invoke(app, [*args, "--reduce", "384", "--fit-on", str(town)])
    assert r.exit_code == 2 and "allowed: 1 … 383" in r.output, r.output
    r = CliRunner().invoke(app, [*args, "--reduce", "4+x", "--fit-on", str(town)])
    assert r.exit_code == 2 and "is not K or K1+K2" in r.output, r.output
    split = tmp_path / "split.onnx"
    source = str(staged / "staged.onnx")
    fit = ["--fit-on", str(town)]
    r = CliRunner().invoke(app, ["export", source, "--out", str(split), "--reduce", "4+4", *fit])
    assert r.exit_code == 0, r.output
    got = read_metadata(split)
    assert (got.descriptor_dim, got.reduction["network_part"]) == (8, 4)


@pytest.mark.anyio
async def test_the_service_serves_the_reduced_descriptor(staged, tmp_path):
    fit = run_onnx(staged / "staged.onnx", images(8, 24))[0]
    directions, kept = fit_directions(fit, 16)
    out = tmp_path / "reduced.onnx"
    meta = with_reduction(staged / "staged.onnx", out, directions, {}, kept)
    enc = Encoder(out, intra_op_threads=2)
    assert enc.dim == meta.descriptor_dim == 16
    async with running(Settings(data_dir=tmp_path / "data"), enc) as c:
        best, d = await three_keyframes_then_a_turned_query(c)
        assert best["keyframe_id"] == "k2"
        assert len(d["descriptor"]) == 16 and d["model_id"] == meta.model_id
