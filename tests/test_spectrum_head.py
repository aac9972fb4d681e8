"""A first stage written into an exported encoder (overlapmamba.train.spectrum_head): the
graph's descriptor is the numpy stage's vector, the yaw features are untouched, files it
would mislead are refused, and the service serves the new descriptor end to end."""

from __future__ import annotations

import numpy as np
import pytest
from service_kit import MODEL, running, three_keyframes_then_a_turned_query

from overlapmamba.core.yaw_spectrum import FirstStage
from overlapmamba.service.encoder import Encoder
from overlapmamba.service.settings import Settings
from overlapmamba.train.errors import ExportError
from overlapmamba.train.export import run_onnx
from overlapmamba.train.modelfile import read_metadata, rewrite_metadata
from overlapmamba.train.spectrum_head import dft_matrices, with_first_stage


@pytest.fixture(scope="module")
def plain(tmp_path_factory) -> object:
    """The shipped encoder without its calibration (fitted on its own descriptor)."""
    out = tmp_path_factory.mktemp("head") / "plain.onnx"
    rewrite_metadata(MODEL, out, lambda meta: {"calibration": {}})
    return out


def test_the_dft_matrices_are_rfft():
    x = np.random.default_rng(0).normal(size=(3, 40)).astype(np.float32)
    cos, sin = dft_matrices(40, 7)
    np.testing.assert_allclose(x @ cos + 1j * (x @ sin), np.fft.rfft(x)[:, :7], atol=1e-4)


@pytest.mark.parametrize("text", ["mixed:0.75:32:sqrt", "spectrum:16:none"])
def test_the_graphs_descriptor_is_the_numpy_stage_and_the_yaw_features_stay(plain, tmp_path, text):
    stage = FirstStage.parse(text)
    out = tmp_path / "head.onnx"
    meta = with_first_stage(plain, out, stage)
    before = read_metadata(plain)
    want_dim = 16 * stage.bins + (before.descriptor_dim if stage.mix < 1 else 0)
    assert meta.first_stage == text and meta.descriptor_dim == want_dim
    assert meta.model_id != before.model_id and read_metadata(out) == meta
    images = np.random.default_rng(1).uniform(0, 1, size=(2, 1, 64, 900)).astype(np.float32)
    d0, y0 = run_onnx(plain, images)
    d1, y1 = run_onnx(out, images)
    np.testing.assert_array_equal(y1, y0)
    np.testing.assert_allclose(d1, stage.vectors(d0, y0), atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(d1, axis=1), 1.0, atol=1e-5)


def test_files_it_would_mislead_are_refused(plain, tmp_path):
    with pytest.raises(ExportError, match="carries calibration"):
        with_first_stage(MODEL, tmp_path / "x.onnx", FirstStage(1.0, 8))
    with pytest.raises(ExportError, match="nothing to add"):
        with_first_stage(plain, tmp_path / "x.onnx", FirstStage())
    with pytest.raises(ExportError, match="900 columns have 451 frequencies"):
        with_first_stage(plain, tmp_path / "x.onnx", FirstStage(1.0, 452))
    once = tmp_path / "once.onnx"
    with_first_stage(plain, once, FirstStage(1.0, 8))
    with pytest.raises(ExportError, match="already carries first stage 'spectrum:8:sqrt'"):
        with_first_stage(once, tmp_path / "twice.onnx", FirstStage(0.5, 8))
    assert not (tmp_path / "x.onnx").exists() and not (tmp_path / "twice.onnx").exists()


@pytest.mark.anyio
async def test_the_service_serves_the_first_stage_as_its_descriptor(plain, tmp_path):
    out = tmp_path / "head.onnx"
    meta = with_first_stage(plain, out, FirstStage.parse("mixed:0.75:32:sqrt"))
    enc = Encoder(out, intra_op_threads=2)
    assert enc.dim == meta.descriptor_dim == 256 + 16 * 32
    async with running(Settings(data_dir=tmp_path / "data"), enc) as c:
        best, d = await three_keyframes_then_a_turned_query(c)
        assert best["keyframe_id"] == "k2" and abs(best["yaw_deg"] - 40.0) < 1.5
        assert len(d["descriptor"]) == meta.descriptor_dim and d["model_id"] == meta.model_id


def test_a_new_trace_would_drop_the_first_stage_and_is_refused(plain, tmp_path):
    from overlapmamba.train.recover import with_token_views

    once = tmp_path / "once.onnx"
    with_first_stage(plain, once, FirstStage(1.0, 8))
    with pytest.raises(ExportError, match="a new trace would drop"):
        with_token_views(once, tmp_path / "tokens.onnx", 3)
    assert not (tmp_path / "tokens.onnx").exists()


def test_the_cli_refuses_a_file_before_writing_anything(plain, tmp_path):
    """`overlapmamba export FILE.onnx --first-stage …` checks the source first: a calibrated
    file is refused with the reason, and --out is never written (not even the views' copy)."""
    from typer.testing import CliRunner

    from overlapmamba.cli import app

    out = tmp_path / "x.onnx"
    runner = CliRunner()
    args = ["export", str(MODEL), "--first-stage", "spectrum:8:sqrt", "--out", str(out)]
    r = runner.invoke(app, args)
    assert r.exit_code == 2 and "carries calibration" in r.output, r.output
    assert not out.exists()
    r = runner.invoke(
        app, ["export", str(plain), "--first-stage", "spectrum:8:sqrt", "--out", str(out)]
    )
    assert r.exit_code == 0, r.output
    assert read_metadata(out).first_stage == "spectrum:8:sqrt"


@pytest.mark.parametrize("text", ["mixed:0.5:8:none", "spectrum:16:sqrt"])
def test_taking_the_first_stage_out_gives_the_network_back(plain, tmp_path, text):
    """``without_first_stage``: the network's descriptor again, 256-d, uncalibrated; the same
    stage written in again gives the same file (graph and model id); the CLI does it with
    ``--first-stage descriptor``; a file without a stage is refused."""
    from typer.testing import CliRunner

    from overlapmamba.cli import app
    from overlapmamba.core.calibration import Calibrated
    from overlapmamba.train.modelfile import with_calibration
    from overlapmamba.train.spectrum_head import without_first_stage

    staged = tmp_path / "staged.onnx"
    meta = with_first_stage(plain, staged, FirstStage.parse(text))
    entry = Calibrated(
        values={"shortlist": 50, "weight": 8.0}, chosen_by="a test", data="none", at="2026"
    )
    with_calibration(staged, "rerank", entry)
    back = without_first_stage(staged, tmp_path / "back.onnx")
    before = read_metadata(plain)
    assert back.first_stage == "descriptor" and back.descriptor_dim == before.descriptor_dim
    assert back.calibration == {} and back.model_id != meta.model_id
    images = np.random.default_rng(2).uniform(0, 1, size=(2, 1, 64, 900)).astype(np.float32)
    d0, y0 = run_onnx(plain, images)
    d1, y1 = run_onnx(tmp_path / "back.onnx", images)
    np.testing.assert_allclose(d1, d0, atol=1e-6)
    np.testing.assert_array_equal(y1, y0)
    again = with_first_stage(
        tmp_path / "back.onnx", tmp_path / "again.onnx", FirstStage.parse(text)
    )
    assert (again.graph, again.model_id) == (meta.graph, meta.model_id)
    with pytest.raises(ExportError, match="carries no first stage"):
        without_first_stage(tmp_path / "back.onnx", tmp_path / "x.onnx")
    out = tmp_path / "cli.onnx"
    r = CliRunner().invoke(
        app,
        ["export", str(staged), "--first-stage", "descriptor", "--views", "3", "--out", str(out)],
    )
    assert r.exit_code == 0, r.output
    assert read_metadata(out).model_id == back.model_id
