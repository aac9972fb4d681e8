"""ONNX export: interface, metadata, the scan as Scan loops, parity with PyTorch (random and
real scans, B = 1 and 8), yaw-roll invariance in onnxruntime, int8 storage, the CLI."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

from typer.testing import CliRunner  # noqa: E402

from overlapmamba.cli import app  # noqa: E402
from overlapmamba.core.datasets import open_sequence  # noqa: E402
from overlapmamba.core.modelmeta import (  # noqa: E402
    SCAN_DOMAIN,
    SCAN_OPS,
    EncoderMetadata,
    ModelMetadataError,
)
from overlapmamba.core.projection import project  # noqa: E402
from overlapmamba.core.sensors import get_profile  # noqa: E402
from overlapmamba.train.checkpoint import save_checkpoint  # noqa: E402
from overlapmamba.train.errors import CheckpointError  # noqa: E402
from overlapmamba.train.export import (  # noqa: E402
    ExportError,
    count_nodes,
    export_onnx,
    run_onnx,
    verification_images,
)
from overlapmamba.train.model import OverlapMamba, OverlapMambaConfig  # noqa: E402
from overlapmamba.train.modelfile import read_metadata  # noqa: E402

PROFILE = get_profile("kitti-hdl64")
TINY = dict(d_model=16, d_state=4, dt_rank=4, conv_last2=32, clusters=4, out_dim=16)
TINY |= dict(yaw_channels=4)


def tiny_model(seed: int = 0, **over) -> OverlapMamba:
    torch.manual_seed(seed)
    return OverlapMamba(OverlapMambaConfig(**(TINY | over))).eval()


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> dict:
    d = tmp_path_factory.mktemp("onnx")
    model = tiny_model()
    f32 = export_onnx(model, PROFILE, d / "f32.onnx", weight_format="float32")
    # A low threshold so the tiny model's NetVLAD reduction matrix goes int8 as the real one.
    i8 = export_onnx(model, PROFILE, d / "i8.onnx", weight_format="int8", int8_min_size=2000)
    return {"model": model, "f32": f32, "i8": i8}


def torch_out(model: OverlapMamba, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    with torch.no_grad():
        d, y = model(torch.from_numpy(images))
    return d.numpy(), y.numpy()


def test_interface_batch_axis_and_scan_loops(exported):
    proto = onnx.load(str(exported["f32"].path))
    onnx.checker.check_model(proto, full_check=True)
    (inp,) = proto.graph.input
    dims = inp.type.tensor_type.shape.dim
    assert inp.name == "range_image" and dims[0].dim_param == "batch"
    assert [d.dim_value for d in dims[1:]] == [1, 64, 900]
    assert inp.type.tensor_type.elem_type == onnx.TensorProto.FLOAT
    assert [o.name for o in proto.graph.output] == ["descriptor", "yaw_features"]
    total, loops = count_nodes(proto)
    # The scan is ONNX Scan loops over an (M, N, E) state (not unrolled), inside one
    # overlapmamba node per block whose body ships in the file as a local function: no
    # runtime needs anything but the standard operators.
    assert loops >= 3 and total < 400, (loops, total)
    scans = [n for n in proto.graph.node if n.domain == SCAN_DOMAIN]
    assert [n.op_type for n in scans] == [SCAN_OPS[exported["model"].cfg.circular]]
    assert {n.domain for n in proto.graph.node} <= {"", SCAN_DOMAIN}
    (fn,) = proto.functions
    assert (fn.domain, fn.name) == (SCAN_DOMAIN, scans[0].op_type)
    assert "Scan" in {n.op_type for n in fn.node}
    assert {n.domain for n in fn.node} <= {"", "ai.onnx"}
    assert {o.domain for o in proto.opset_import} <= {"", "ai.onnx", SCAN_DOMAIN}


def test_metadata_describes_the_model(exported):
    meta = read_metadata(exported["f32"].path)
    assert meta == exported["f32"].metadata
    assert meta.profile == PROFILE
    assert OverlapMambaConfig.from_dict(meta.network) == exported["model"].cfg
    assert meta.descriptor_dim == 16 and meta.yaw_channels == 4
    assert meta.weights == "random" and meta.weight_format == "float32"
    assert meta.model_id.startswith("om-") and meta.source_commit
    # The service's view: onnxruntime's metadata map alone rebuilds the same record.
    sess = ort.InferenceSession(str(exported["f32"].path), providers=["CPUExecutionProvider"])
    assert EncoderMetadata.from_props(sess.get_modelmeta().custom_metadata_map) == meta
    assert exported["i8"].metadata.model_id != meta.model_id


def test_the_model_id_is_the_graph_and_weights_only(exported, tmp_path):
    """The same network exported again (in the same process: the exporter numbers its nodes
    across calls) gets the same model id, and the file names no source file or line (the
    exporter's stack traces, which made the id depend on the checkout's folder)."""
    again = export_onnx(
        exported["model"], PROFILE, tmp_path / "again.onnx", weight_format="float32"
    )
    assert again.metadata.model_id == exported["f32"].metadata.model_id
    raw = exported["f32"].path.read_bytes()
    assert b"stack_trace" not in raw and str(Path(__file__).parents[1]).encode() not in raw


@pytest.mark.parametrize("batch", [1, 8])
def test_parity_on_random_range_images(exported, batch):
    images = verification_images(PROFILE, count=batch, seed=batch)
    ref_d, ref_y = torch_out(exported["model"], images)
    d, y = run_onnx(exported["f32"].path, images, threads=2)
    assert d.shape == (batch, 16) and y.shape == (batch, 4, 900)
    np.testing.assert_allclose(d, ref_d, rtol=0, atol=1e-4)
    np.testing.assert_allclose(y, ref_y, rtol=0, atol=1e-4)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-5)


@pytest.fixture(scope="module")
def kitti_images(kitti_seq_dir) -> np.ndarray:
    seq = open_sequence(kitti_seq_dir)
    frames = range(0, 80, 10)  # 8 real scans
    return np.stack([project(seq.points(i).xyz, PROFILE) for i in frames])[:, None]


@pytest.mark.parametrize("batch", [1, 8])
def test_parity_on_real_kitti_scans(exported, kitti_images, batch):
    images = kitti_images[:batch]
    ref_d, ref_y = torch_out(exported["model"], images)
    d, y = run_onnx(exported["f32"].path, images)
    np.testing.assert_allclose(d, ref_d, rtol=0, atol=1e-4)
    np.testing.assert_allclose(y, ref_y, rtol=0, atol=1e-4)


def test_yaw_roll_invariance_holds_in_onnxruntime(exported, kitti_images):
    images = kitti_images[:4]
    d, y = run_onnx(exported["f32"].path, images)
    for k in (1, 225, 613):
        d_k, y_k = run_onnx(exported["f32"].path, np.roll(images, k, axis=-1))
        np.testing.assert_allclose(d_k, d, rtol=0, atol=1e-4)
        np.testing.assert_allclose(y_k, np.roll(y, k, axis=-1), rtol=0, atol=1e-4)


def dequantized(model: OverlapMamba, path: Path) -> OverlapMamba:
    """The PyTorch model with the int8-stored matrix replaced by its dequantised value."""
    proto = onnx.load(str(path))
    inits = {t.name: onnx.numpy_helper.to_array(t) for t in proto.graph.initializer}
    (name,) = [n[: -len("_int8")] for n in inits if n.endswith("_int8")]
    w = inits[f"{name}_int8"].astype(np.float32) * inits[f"{name}_scale"]
    copy = tiny_model()
    copy.load_state_dict(model.state_dict())
    weight = copy.reduce.weight
    value = torch.from_numpy(w if w.shape == weight.shape else w.T)
    with torch.no_grad():
        weight.copy_(value)
    return copy.eval()


def test_int8_weights_match_their_dequantised_model_and_keep_the_cosine(exported, kitti_images):
    assert exported["i8"].size_bytes < exported["f32"].size_bytes
    proto = onnx.load(str(exported["i8"].path))
    assert any(t.data_type == onnx.TensorProto.INT8 for t in proto.graph.initializer)
    images = kitti_images
    d, y = run_onnx(exported["i8"].path, images)
    ref_d, ref_y = torch_out(dequantized(exported["model"], exported["i8"].path), images)
    np.testing.assert_allclose(d, ref_d, rtol=0, atol=1e-4)
    np.testing.assert_allclose(y, ref_y, rtol=0, atol=1e-4)
    f32_d, _ = torch_out(exported["model"], images)
    assert (d * f32_d).sum(1).min() >= 0.999


def test_open_scan_one_direction_two_blocks_exports_too(tmp_path):
    model = tiny_model(
        seed=1,
        circular=False,
        bidirectional=False,
        shift=False,
        spp=False,
        n_blocks=2,
        backbone="all-rows",  # its zero rows and (h, 1) convolution export too
    )
    res = export_onnx(model, PROFILE, tmp_path / "open.onnx", weight_format="float32")
    images = verification_images(PROFILE, count=2, seed=5)
    ref_d, ref_y = torch_out(model, images)
    d, y = run_onnx(res.path, images)
    np.testing.assert_allclose(d, ref_d, rtol=0, atol=1e-4)
    np.testing.assert_allclose(y, ref_y, rtol=0, atol=1e-4)
    # The served C-kernel path cuts two scans into three sessions and agrees.
    from overlapmamba.service.encoder import Encoder

    fast = Encoder(res.path, intra_op_threads=2, scan_kernel=True)
    assert fast.scan_path.startswith("c-kernel (2 scans, 3 sessions"), fast.scan_path
    d2, y2 = fast.encode(images)
    np.testing.assert_allclose(d2, d, rtol=0, atol=1e-5)
    np.testing.assert_allclose(y2, y, rtol=0, atol=1e-5)
    # The benchmark's split of the served time: sessions and kernel, adding up, same answer.
    assert fast.staged is not None
    parts: dict[str, float] = {}
    t0 = time.perf_counter()
    d3, _ = fast.staged.run(images, parts)
    whole = time.perf_counter() - t0
    assert parts.keys() == {"sessions", "scan"} and min(parts.values()) > 0
    assert sum(parts.values()) <= whole
    np.testing.assert_array_equal(d3, d2)


@pytest.mark.parametrize("fmt", ["f32", "i8"])
def test_served_c_kernel_path_matches_the_portable_graph_on_real_scans(exported, kitti_images, fmt):
    from overlapmamba.service.encoder import Encoder

    fast = Encoder(exported[fmt].path, intra_op_threads=2, scan_kernel=True)
    portable = Encoder(exported[fmt].path, intra_op_threads=2, scan_kernel=False)
    assert fast.scan_path.startswith("c-kernel (1 scans, 2 sessions"), fast.scan_path
    assert portable.scan_path == "portable (scan_kernel = false)" and portable.staged is None
    for batch in (1, 8):
        d0, y0 = portable.encode(kitti_images[:batch])
        d1, y1 = fast.encode(kitti_images[:batch])
        assert d1.shape == d0.shape and y1.shape == y0.shape
        np.testing.assert_allclose(d1, d0, rtol=0, atol=1e-4)
        np.testing.assert_allclose(y1, y0, rtol=0, atol=1e-4)


def test_an_encoder_with_views_describes_a_scan_by_the_mean_of_its_views(
    exported, kitti_seq_dir, tmp_path
):
    from overlapmamba.core.views import project_views
    from overlapmamba.service.encoder import Encoder
    from overlapmamba.train.checkpoint import load_model
    from overlapmamba.train.evaluate import describe
    from overlapmamba.train.modelfile import with_views

    two = with_views(exported["i8"].path, tmp_path / "two.onnx", 2)
    enc = Encoder(tmp_path / "two.onnx", intra_op_threads=2)
    assert enc.views == 2 and enc.model_id == two.model_id
    seq = open_sequence(kitti_seq_dir)
    images = np.stack([enc.project(seq.points(i)) for i in (0, 50)])
    assert images.shape == (2, 2, PROFILE.height, PROFILE.width)
    np.testing.assert_array_equal(images[1], project_views(seq.points(50), PROFILE, 2))
    desc, yaw = enc.encode(images)
    # the graph on each view alone, one image a row
    each, each_yaw = run_onnx(exported["i8"].path, images.reshape(4, 1, *images.shape[2:]))
    mean = each.reshape(2, 2, -1).mean(1)
    np.testing.assert_allclose(desc, mean / np.linalg.norm(mean, axis=1)[:, None], atol=1e-5)
    np.testing.assert_allclose(yaw, each_yaw[[0, 2]], atol=1e-5)  # view 0's
    # evaluation describes a scan the same way (an .onnx's count comes from its metadata)
    model, _, _ = load_model(tmp_path / "two.onnx")
    np.testing.assert_allclose(describe(model, images)[0], desc, atol=1e-5)
    # images that are not the model's views are refused, naming the shape it takes
    with pytest.raises(ValueError, match=r"\(B, 2, 64, 900\)"):
        enc.encode(images[:, :1])


def test_an_encoder_with_aligned_columns_is_turn_invariant_in_one_pass(
    exported, kitti_seq_dir, tmp_path
):
    """``export --column-phase aligned``: the same graph under another id; a scan turned by
    any angle gets the same descriptor in one pass, and the yaw features, shifted back to
    the sensor's columns, still say the turn (the service's Encoder and evaluation alike)."""
    from overlapmamba.core.poses import rotation_z, transform_points
    from overlapmamba.core.views import unshift_features
    from overlapmamba.core.yaw import estimate_yaw
    from overlapmamba.service.encoder import Encoder
    from overlapmamba.train.checkpoint import load_model
    from overlapmamba.train.evaluate import describe
    from overlapmamba.train.modelfile import read_metadata

    src, out = exported["i8"].path, tmp_path / "aligned.onnx"
    res = CliRunner().invoke(
        app, ["export", str(src), "--column-phase", "aligned", "--out", str(out)]
    )
    assert res.exit_code == 0, res.output
    meta, plain = read_metadata(out), read_metadata(src)
    assert meta.aligned and meta.model_id != plain.model_id and meta.graph == plain.model_id
    assert meta.model_id in " ".join(res.output.split())
    enc, sensor_cols = Encoder(out, intra_op_threads=2), Encoder(src, intra_op_threads=2)
    xyz = open_sequence(kitti_seq_dir).points(30).xyz
    thetas = [0.0, 37.3, -151.9]
    scans = [transform_points(xyz, rotation_z(-t)) for t in thetas]
    desc, yaw = enc.describe(scans)
    assert (desc[1:] @ desc[0]).min() > 0.9999
    d_plain = sensor_cols.describe(scans)[0]
    assert (d_plain[1:] @ d_plain[0]).min() < (desc[1:] @ desc[0]).min()
    for t, y in zip(thetas[1:], yaw[1:], strict=True):
        est = estimate_yaw(yaw[0], y)[0][0]
        assert abs((est - t + 180) % 360 - 180) < 0.2, (t, est)
    # the images' own columns (offsets 0) are the sensor's shifted by the offsets; without
    # offsets the file refuses to encode, naming what to pass
    images, offsets = zip(*(enc.project_offset(s) for s in scans), strict=True)
    raw = enc.encode(np.stack(images), np.zeros(len(images)))[1]
    np.testing.assert_allclose(unshift_features(raw, np.array(offsets)), yaw, atol=1e-5)
    with pytest.raises(ValueError, match="pass the images' column offsets"):
        enc.encode(np.stack(images))
    # evaluation describes scans the same way
    model, _, _ = load_model(out)
    d_eval, y_eval = describe(model, np.stack(images), offsets=np.array(offsets))
    np.testing.assert_allclose(d_eval, desc, atol=1e-5)
    np.testing.assert_allclose(y_eval, yaw, atol=1e-4)
    # back to the sensor's columns: the first file's id; an unknown phase is refused
    back = tmp_path / "back.onnx"
    res = CliRunner().invoke(
        app, ["export", str(out), "--column-phase", "sensor", "--out", str(back)]
    )
    assert res.exit_code == 0 and read_metadata(back).model_id == plain.model_id
    # back to the sensor's columns and on to a bird's-eye input in one call (the phase first)
    bev = tmp_path / "bev.onnx"
    args = ["export", str(out), "--column-phase", "sensor", "--sensor-input", "bev"]
    res = CliRunner().invoke(app, [*args, "--out", str(bev)])
    assert res.exit_code == 0, res.output
    assert (read_metadata(bev).sensor_input, read_metadata(bev).column_phase) == ("bev", "sensor")
    res = CliRunner().invoke(
        app, ["export", str(src), "--column-phase", "north", "--out", str(tmp_path / "x.onnx")]
    )
    assert res.exit_code == 2 and "got 'north'" in res.output
    assert not (tmp_path / "x.onnx").exists()


def test_the_c_kernel_path_falls_back_to_the_portable_graph_and_says_why(
    exported, kitti_images, tmp_path, monkeypatch, caplog
):
    import onnx.inliner

    import overlapmamba.core.scan_kernel as scan_kernel
    import overlapmamba.service.fastscan as fastscan
    from overlapmamba.service.encoder import Encoder

    path = exported["f32"].path
    want, _ = Encoder(path, scan_kernel=False).encode(kitti_images[:2])

    def served(p: Path, reason: str) -> None:
        caplog.clear()
        enc = Encoder(p, intra_op_threads=2)
        assert enc.scan_path.startswith(f"portable ({reason}"), enc.scan_path
        assert any(reason in r.getMessage() and r.levelname == "WARNING" for r in caplog.records)
        np.testing.assert_allclose(enc.encode(kitti_images[:2])[0], want, rtol=0, atol=1e-5)

    # A file whose scans are not marked (its functions inlined, as files exported before).
    flat = tmp_path / "flat.onnx"
    onnx.save(onnx.inliner.inline_local_functions(onnx.load(str(path))), flat)
    served(flat, "the graph has no overlapmamba scan node")
    # A kernel that computes something else is caught by the load-time check.
    monkeypatch.setattr(fastscan, "scan_forward", lambda u, *a, **k: np.zeros_like(u))
    served(path, "it disagrees with the portable graph by")
    monkeypatch.undo()

    # No kernel (no compiler on the machine).
    def no_kernel():
        raise scan_kernel.KernelBuildError("no C compiler found (set $CC or install gcc) …")

    monkeypatch.setattr(scan_kernel, "load", no_kernel)
    served(path, "no C compiler found")


def test_export_refuses_a_profile_of_another_size_and_unknown_formats(tmp_path):
    model = tiny_model()
    with pytest.raises(ExportError, match="makes 32×900 images but the model takes 64×900"):
        export_onnx(model, get_profile("hdl32"), tmp_path / "x.onnx")
    with pytest.raises(ExportError, match="allowed: int8, float32"):
        export_onnx(model, PROFILE, tmp_path / "x.onnx", weight_format="fp8")
    assert not list(tmp_path.iterdir())


def test_a_model_without_our_metadata_is_refused(tmp_path):
    graph = onnx.helper.make_graph(
        [onnx.helper.make_node("Identity", ["x"], ["y"])],
        "g",
        [onnx.helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [1])],
        [onnx.helper.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [1])],
    )
    onnx.save(onnx.helper.make_model(graph), tmp_path / "foreign.onnx")
    with pytest.raises(ModelMetadataError, match="overlapmamba export"):
        read_metadata(tmp_path / "foreign.onnx")


def test_cli_exports_a_checkpoint(tmp_path):
    model = tiny_model(seed=2)
    ckpt = tmp_path / "m.pt"
    save_checkpoint(
        ckpt,
        {
            "model_config": model.cfg.to_dict(),
            "profile": PROFILE.model_dump(),
            "state_dict": model.state_dict(),
            "train": {},
            "metrics": {},
        },
    )
    runner = CliRunner()
    res = runner.invoke(app, ["export", str(ckpt), "--out", str(tmp_path / "m.onnx")])
    assert res.exit_code == 0, res.output
    assert "om-" in res.output and (tmp_path / "m.onnx").is_file()
    res = runner.invoke(app, ["export", str(ckpt), "--out", str(tmp_path / "m.bin")])
    assert res.exit_code != 0 and "must end in .onnx" in res.output
    res = runner.invoke(
        app, ["export", str(ckpt), "--out", str(tmp_path / "n.onnx"), "--weights", "fp8"]
    )
    assert res.exit_code == 2 and "allowed: int8, float32" in res.output
    # an exported encoder is written again with other views: the same graph, another id
    two = tmp_path / "two.onnx"
    args = ["export", str(tmp_path / "m.onnx"), "--views", "2", "--out", str(two)]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    one, meta = read_metadata(tmp_path / "m.onnx"), read_metadata(two)
    assert (one.views, meta.views, meta.graph_id) == (1, 2, one.model_id)
    assert meta.model_id != one.model_id and meta.model_id in res.output
    assert meta.model_copy(update={"views": 1, "model_id": one.model_id, "graph_id": ""}) == one
    graphs = [onnx.load(str(p)) for p in (tmp_path / "m.onnx", two)]
    for g in graphs:
        del g.metadata_props[:]
    assert graphs[0].SerializeToString() == graphs[1].SerializeToString()
    # and back to one view: the first file's id again
    back = ["export", str(two), "--out", str(tmp_path / "back.onnx"), "--views", "1"]
    res = runner.invoke(app, back)
    assert res.exit_code == 0 and read_metadata(tmp_path / "back.onnx") == one
    # found in review: another change asked of an exported file (here none) kept none of its
    # views, the default being one; its own count is kept unless --views says otherwise
    res = runner.invoke(app, ["export", str(two), "--out", str(tmp_path / "same.onnx")])
    assert res.exit_code == 0 and read_metadata(tmp_path / "same.onnx") == meta, res.output
    # and it never writes over the file it reads (the shipped model was rewritten in place)
    res = runner.invoke(app, ["export", str(two), "--out", str(two), "--views", "3"])
    said = " ".join(res.output.replace("│", " ").split())
    assert res.exit_code == 2 and "is the file export reads" in said, said
    assert read_metadata(two) == meta
    # nor one whose work file (NAME.part.onnx beside --out) is the file it reads
    part = tmp_path / "w.part.onnx"
    part.write_bytes(two.read_bytes())
    res = runner.invoke(app, ["export", str(part), "--out", str(tmp_path / "w.onnx")])
    said = " ".join(res.output.replace("│", " ").split())
    assert res.exit_code == 2 and "works in w.part.onnx, the file export reads" in said, said
    assert part.read_bytes() == two.read_bytes()
    part.unlink()  # a source, not a work file left behind (checked below)
    for bad, says in (
        (["--weights", "float32"], "keeps its weights as"),
        (["--views", "9"], "--views"),
    ):
        res = runner.invoke(app, ["export", str(two), "--out", str(tmp_path / "x.onnx"), *bad])
        assert res.exit_code == 2 and says in " ".join(res.output.split()), res.output
    assert not (tmp_path / "x.onnx").exists()
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    foreign = tmp_path / "foreign.onnx"
    onnx.save(onnx.helper.make_model(onnx.helper.make_graph([], "g", [], [])), foreign)
    for src, says in (
        (tmp_path / "gone.onnx", "does not exist"),
        (tmp_path / "junk.onnx", "is not an ONNX file"),
        (foreign, "overlapmamba.format"),
    ):
        res = runner.invoke(app, ["export", str(src), "--views", "2", "--out", str(two)])
        assert res.exit_code == 2 and says in " ".join(res.output.split()), res.output
    assert read_metadata(two) == meta  # a refused rewrite leaves the target as it was
    # a chain whose late step fails (the towns a reduction is fitted on do not open): --out
    # is left as it was, or not made, never a file of the steps before that looks whole
    reduce = ["--views", "1", "--reduce", "8", "--fit-on", str(tmp_path / "nowhere")]
    for target in (two, tmp_path / "new.onnx"):
        res = runner.invoke(
            app, ["export", str(tmp_path / "m.onnx"), "--out", str(target), *reduce]
        )
        assert res.exit_code == 2 and "does not exist" in res.output, res.output
    assert read_metadata(two) == meta and not (tmp_path / "new.onnx").exists()
    assert not list(tmp_path.glob("*.part.onnx")) and not list(tmp_path.glob(".*tmp*"))


def test_an_exported_encoder_evaluates_like_its_network(exported, kitti_images, tmp_path):
    """load_model opens the .onnx (the shipped model has no checkpoint beside it): the same
    descriptors as its network through describe, its profile and config from the metadata,
    its model id as the digest; a foreign or missing file is refused with the reason."""
    from overlapmamba.train.checkpoint import ExportedNetwork, load_model
    from overlapmamba.train.evaluate import describe, network_digest

    net, profile, info = load_model(exported["f32"].path)
    assert isinstance(net, ExportedNetwork) and not net.training
    assert profile == PROFILE and net.cfg == exported["model"].cfg
    assert info["encoder"]["model_id"] == exported["f32"].metadata.model_id
    assert network_digest(net) == exported["f32"].metadata.model_id
    d, y = describe(net, kitti_images[:5, 0])
    d_ref, y_ref = describe(exported["model"], kitti_images[:5, 0])
    np.testing.assert_allclose(d, d_ref, atol=1e-4)
    np.testing.assert_allclose(y, y_ref, atol=1e-3)
    from overlapmamba.train.recover import recover  # a file its weights cannot come back from

    foreign = tmp_path / "foreign.onnx"
    foreign.write_bytes(b"not a graph")
    for opener, cannot in ((load_model, "onnxruntime cannot load"), (recover, "not an exported")):
        with pytest.raises(CheckpointError, match=cannot):
            opener(foreign)
        with pytest.raises(CheckpointError, match="does not exist"):
            opener(tmp_path / "missing.onnx")


def test_weights_come_back_from_an_exported_encoder(tmp_path, kitti_images):
    """overlapmamba.train.recover undoes the exporter's rewrites (transposed linear weights, A
    folded from A_log, SPP's batch norm folded into its convolution, int8 storage): the
    recovered network gives onnxruntime's descriptors, its unfolded weights are the
    original's, and a graph that does not give every parameter back is refused."""
    from overlapmamba.train.recover import TOLERANCE, recover

    model = tiny_model(seed=3)
    with torch.no_grad():  # batch norm with statistics and affine terms worth folding
        for bn in (model.spp.cv1[1], model.spp.cv2[1]):
            bn.running_mean.uniform_(-0.5, 0.5)
            bn.running_var.uniform_(0.5, 2.0)
            bn.weight.uniform_(0.5, 1.5)
            bn.bias.uniform_(-0.2, 0.2)
        model.blocks[0].A_log.add_(0.1 * torch.randn_like(model.blocks[0].A_log))
    res = export_onnx(model, PROFILE, tmp_path / "m.onnx", weight_format="int8", int8_min_size=2000)
    back, profile, check = recover(res.path, kitti_images[:4])
    assert profile == PROFILE and back.cfg == model.cfg and not back.training
    assert check["descriptor_max_abs"] <= TOLERANCE and check["scans"] == 4
    d, _ = run_onnx(res.path, kitti_images[:4])
    ref, _ = torch_out(back, kitti_images[:4])
    np.testing.assert_allclose(ref, d, rtol=0, atol=TOLERANCE)
    ours, theirs = back.state_dict(), model.state_dict()
    for key in ("blocks.0.in_proj.weight", "blocks.0.main.x_proj.weight", "vlad.assign.weight"):
        torch.testing.assert_close(ours[key], theirs[key], rtol=0, atol=0)
    torch.testing.assert_close(ours["blocks.0.A_log"], theirs["blocks.0.A_log"])
    assert not torch.equal(ours["spp.cv1.0.weight"], theirs["spp.cv1.0.weight"])  # folded

    proto = onnx.load(str(res.path))  # without the nodes' module records: nothing to map
    for node in proto.graph.node:
        del node.metadata_props[:]
    stripped = tmp_path / "stripped.onnx"
    onnx.save(proto, str(stripped))
    with pytest.raises(CheckpointError, match=r"does not give back \d+ parameter"):
        recover(stripped)


def test_a_bev_network_is_verified_on_images_of_its_own_input():
    """A network on the bev input sees cells of 1 and empty, never a range: verified on
    random ranges, a trained one's activations grow far past the float tolerance's scale
    (runs/bev-long's export failed so). Export and recover take the network's own input's
    images (an export of a tiny bev network costs half a minute of `make test`: the real
    export is the check, CHANGELOG.md)."""
    images = verification_images(PROFILE, count=2, seed=3, sensor_input="bev")
    assert images.shape == (2, 1, PROFILE.height, PROFILE.width)
    assert set(np.unique(images)) == {PROFILE.empty_value, 1.0}
    assert 0.05 < (images == 1.0).mean() < 0.15
    ranges = verification_images(PROFILE, count=2, seed=3)
    assert ranges.max() > 1.0 and set(np.unique(ranges)) != {PROFILE.empty_value, 1.0}
    soft = verification_images(PROFILE, count=2, seed=3, sensor_input="bev-soft")
    shared = soft[soft != PROFILE.empty_value]
    assert 0.05 < shared.size / soft.size < 0.15 and PROFILE.empty_value < shared.min()
    assert shared.max() <= 1.0 and len(np.unique(shared)) > 100  # shares, not just 1
    span = verification_images(PROFILE, count=2, seed=3, sensor_input="bev-span")
    np.testing.assert_array_equal(span, soft)
