"""Sub-column views met at the tokens (``OverlapMambaConfig.token_views``): the network's
order of a scan's views, the exported graph (V images a scan in, one descriptor a scan
out), the export from an exported encoder and back, the service's encoder and evaluation on
such a file, and what is refused."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")

from typer.testing import CliRunner  # noqa: E402

from overlapmamba.cli import app  # noqa: E402
from overlapmamba.core.datasets import open_sequence  # noqa: E402
from overlapmamba.core.modelmeta import EncoderMetadata, ModelMetadataError  # noqa: E402
from overlapmamba.core.sensors import get_profile  # noqa: E402
from overlapmamba.core.views import project_views  # noqa: E402
from overlapmamba.train.errors import ConfigError, ExportError  # noqa: E402
from overlapmamba.train.export import export_onnx, run_onnx  # noqa: E402
from overlapmamba.train.model import OverlapMamba, OverlapMambaConfig  # noqa: E402
from overlapmamba.train.modelfile import read_metadata, with_calibration, with_views  # noqa: E402

PROFILE = get_profile("kitti-hdl64")
TINY = dict(d_model=16, d_state=4, dt_rank=4, conv_last2=32, clusters=4, out_dim=16)
TINY |= dict(yaw_channels=4)


def tiny(views: int = 1, seed: int = 0) -> OverlapMamba:
    torch.manual_seed(seed)
    return OverlapMamba(OverlapMambaConfig(**TINY, token_views=views)).eval()


def out_of(model: OverlapMamba, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    with torch.no_grad():
        d, y = model(torch.from_numpy(np.ascontiguousarray(images, np.float32)))
    return d.numpy(), y.numpy()


@pytest.fixture(scope="module")
def views(kitti_seq_dir) -> np.ndarray:
    """Two real KITTI scans' two sub-column views each, (2, 2, H, W)."""
    seq = open_sequence(kitti_seq_dir)
    return np.stack([project_views(seq.points(i), PROFILE, 2) for i in (0, 40)])


def test_the_network_takes_each_scans_views_in_a_row_and_averages_their_tokens(views):
    plain, two = tiny(1), tiny(2)
    two.load_state_dict(plain.state_dict())
    a, b = views[0, :1], views[1, :1]
    # the same image twice is that image: scan-major order, one output a scan
    d, y = out_of(two, np.stack([a, a, b, b]))
    d1, y1 = out_of(plain, np.stack([a, b]))
    assert d.shape == (2, TINY["out_dim"]) and y.shape == (2, 4, PROFILE.width)
    np.testing.assert_allclose(d, d1, atol=1e-6)
    np.testing.assert_allclose(y, y1, atol=1e-5)
    # two different views: the tokens' mean, not either view's descriptor nor their mean
    d2, _ = out_of(two, views.reshape(4, 1, *views.shape[2:]))
    each, _ = out_of(plain, views.reshape(4, 1, *views.shape[2:]))
    assert not np.allclose(d2[0], each[0], atol=1e-4)
    mean = each[:2].mean(0)
    assert not np.allclose(d2[0], mean / np.linalg.norm(mean), atol=1e-4)


@pytest.mark.parametrize("bad", [0, 9])
def test_a_token_view_count_outside_one_to_eight_is_refused(bad):
    with pytest.raises(ValueError, match="token_views"):
        OverlapMambaConfig(**TINY, token_views=bad)


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict:
    """A plain exported encoder (float32, a training record, a calibration) and the same
    weights written with two views met at the tokens, by the CLI."""
    d = tmp_path_factory.mktemp("tokens")
    model = tiny(seed=4)
    with torch.no_grad():  # batch norm with statistics worth folding (a trained network's)
        for bn in (model.spp.cv1[1], model.spp.cv2[1]):
            bn.running_mean.uniform_(-0.5, 0.5)
            bn.running_var.uniform_(0.5, 2.0)
    ckpt = {"train": {"history": [{"epoch": 1}], "data": {"train": [{"path": "t"}]}}}
    plain = export_onnx(model, PROFILE, d / "plain.onnx", weight_format="float32", checkpoint=ckpt)
    from overlapmamba.core.calibration import Calibrated

    entry = Calibrated(
        values={"weight": 0.3, "shortlist": 10}, chosen_by="test", data="val", at="2026-11-27"
    )
    with_calibration(plain.path, "rerank", entry)
    args = ["export", str(plain.path), "--views", "2", "--meet", "tokens"]
    res = CliRunner().invoke(app, [*args, "--out", str(d / "tokens.onnx")])
    assert res.exit_code == 0, res.output
    said = " ".join(res.output.split())
    return {"model": model, "plain": plain.path, "tokens": d / "tokens.onnx", "out": said}


def test_the_exported_graph_takes_v_images_a_scan_and_keeps_the_record(files, views):
    meta, src = read_metadata(files["tokens"]), read_metadata(files["plain"])
    assert (meta.views, meta.graph_views, meta.descriptors_per_scan) == (2, 2, 1)
    assert meta.model_id in files["out"] and "met at the tokens" in files["out"]
    assert meta.model_id != src.model_id and meta.graph_id != src.model_id
    assert (meta.weights, meta.training_data, meta.metrics) == (
        src.weights,
        src.training_data,
        src.metrics,
    )
    assert src.calibration and not meta.calibration  # chosen for other descriptors
    assert meta.weight_format == "float32" and meta.network["token_views"] == 2
    dims = onnx.load(str(files["tokens"])).graph
    assert dims.input[0].type.tensor_type.shape.dim[0].dim_param == "batch"
    assert dims.output[0].type.tensor_type.shape.dim[0].dim_param == "scans"
    d, y = run_onnx(files["tokens"], views.reshape(4, 1, *views.shape[2:]))
    two = tiny(2)
    two.load_state_dict(files["model"].state_dict())
    ref_d, ref_y = out_of(two, views.reshape(4, 1, *views.shape[2:]))
    assert d.shape == (2, TINY["out_dim"])
    np.testing.assert_allclose(d, ref_d, atol=1e-5)
    np.testing.assert_allclose(y, ref_y, atol=1e-4)


@pytest.mark.parametrize("kernel", [False, True])
def test_the_service_and_evaluation_describe_a_scan_by_the_graph_alone(files, views, kernel):
    from overlapmamba.service.encoder import Encoder
    from overlapmamba.train.checkpoint import load_model, views_of
    from overlapmamba.train.evaluate import describe

    enc = Encoder(files["tokens"], intra_op_threads=2, scan_kernel=kernel)
    assert enc.views == 2
    if kernel:
        assert enc.scan_path.startswith("c-kernel"), enc.scan_path
    desc, yaw = enc.encode(views)
    ref, ref_yaw = run_onnx(files["tokens"], views.reshape(4, 1, *views.shape[2:]))
    np.testing.assert_allclose(desc, ref, atol=1e-4)
    np.testing.assert_allclose(yaw, ref_yaw, atol=1e-4)
    model, _, _ = load_model(files["tokens"])
    assert views_of(model) == 2
    np.testing.assert_allclose(describe(model, views)[0], ref, atol=1e-5)
    with pytest.raises(ValueError, match=r"averages 2 views .* got 1 image"):
        describe(model, views[:, 0])
    with pytest.raises(ValueError, match=r"\(B, 2, 64, 900\)"):
        enc.encode(views[:, :1])


def test_a_tokens_graph_goes_back_to_descriptor_views_and_keeps_its_count(files, views, tmp_path):
    with pytest.raises(ExportError, match="views must be 2, got 3"):
        with_views(files["tokens"], tmp_path / "x.onnx", 3)
    assert not (tmp_path / "x.onnx").exists()
    # a tokens file rewritten keeps its meeting unless asked (found in review: the default
    # meeting made it the plain graph unasked)
    same = tmp_path / "same.onnx"
    res = CliRunner().invoke(app, ["export", str(files["tokens"]), "--out", str(same)])
    assert res.exit_code == 0, res.output
    assert read_metadata(same).model_id == read_metadata(files["tokens"]).model_id
    out = tmp_path / "back.onnx"
    args = ["export", str(files["tokens"]), "--views", "2", "--meet", "descriptors"]
    res = CliRunner().invoke(app, [*args, "--out", str(out)])
    assert res.exit_code == 0, res.output
    meta = read_metadata(out)
    assert (meta.views, meta.graph_views, meta.descriptors_per_scan) == (2, 1, 2)
    # the plain network again (traced anew from recovered weights: not the same bytes)
    images = views.reshape(4, 1, *views.shape[2:])
    np.testing.assert_allclose(
        run_onnx(out, images)[0], run_onnx(files["plain"], images)[0], atol=1e-5
    )
    res = CliRunner().invoke(
        app, ["export", str(files["plain"]), "--meet", "views", "--out", str(tmp_path / "y.onnx")]
    )
    assert res.exit_code == 2 and "--meet must be one of descriptors, tokens" in res.output


def test_what_a_tokens_network_refuses(files, tmp_path):
    with pytest.raises(ExportError, match="views must be 2, got 3"):
        export_onnx(tiny(2), PROFILE, tmp_path / "x.onnx", views=3)
    meta = read_metadata(files["tokens"])
    props = {**meta.to_props(), "overlapmamba.views": "1"}
    with pytest.raises(ModelMetadataError, match="views must be 2, got 1"):
        EncoderMetadata.from_props(props)
    from overlapmamba.train.train import TrainConfig, train

    with pytest.raises(ConfigError, match="training takes one image a scan"):
        train([tmp_path], tmp_path, tmp_path / "run", tiny(2).cfg, TrainConfig())
    # a tokens file as a training start trains the same weights on one image a scan
    from overlapmamba.train.train_inputs import start_config

    cfg = start_config(TrainConfig(init=str(files["tokens"]), freeze_bn=True), None)
    assert cfg.token_views == 1 and cfg.d_model == TINY["d_model"]
