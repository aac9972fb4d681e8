"""Export OverlapMamba to a self-describing ONNX encoder, verified against PyTorch.

    checkpoint → model (scan backend "onnx") → torch.onnx.export(dynamo=True)
      → each block's scan is one overlapmamba.SelectiveScan[Ring] node; its body (Scan
        loops) is attached as a model-local function (overlapmamba.train.scan_onnx)
      → checks: batch axis symbolic, the scan present as ONNX Scan loops (not unrolled)
      → large matrices stored int8 (optional) → metadata_props → onnx.checker (full)
      → onnxruntime vs PyTorch on the verification images → atomic rename into place

The graph: ``range_image`` (B, 1, H, W) float32 → ``descriptor`` (B, D) unit norm and
``yaw_features`` (B, C, W). The selective scan is
:func:`overlapmamba.train.scan.selective_scan_loop`:
three ``Scan`` operators per block (chunks, carry, correction), circular mode included, inside
one model-local function per block's node, so any ONNX runtime runs it (it inlines the
function) and a runtime with a kernel for the node can bind it instead.

**int8 storage.** NetVLAD's reduction matrix (clusters · conv_last2 × out_dim, 16.8M values
in the reference head) is 93% of the weights. It is stored as int8 with one float scale per
output column, followed by ``Cast`` and ``Mul``: both have constant inputs only, so
onnxruntime folds them into a float32 matrix when it loads the model, and inference runs
at float32 speed. Everything else stays float32.
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import torch
from onnx import helper, numpy_helper

from overlapmamba.core.modelmeta import INPUT, OUTPUTS, EncoderMetadata, identity
from overlapmamba.core.sensors import SensorProfile
from overlapmamba.core.sensors.input import BEV_MODES, check_mode
from overlapmamba.core.views import check_views
from overlapmamba.train.errors import ExportError
from overlapmamba.train.model import OverlapMamba
from overlapmamba.train.modelfile import graph_id
from overlapmamba.train.scan_onnx import TRANSLATIONS, attach_functions, quiet_export

WEIGHT_FORMATS = ("int8", "float32")
INT8_MIN_SIZE = 1 << 20  # matrices with at least this many values are stored int8
FLOAT_TOL = 1e-4  # max abs difference, onnxruntime vs PyTorch, float32 weights
COSINE_TOL = 0.999  # min descriptor cosine to PyTorch float32 with int8 weights


@dataclasses.dataclass
class ExportResult:
    path: Path
    metadata: EncoderMetadata
    size_bytes: int
    nodes: int  # all nodes, loop bodies included
    scan_nodes: int
    verification: dict[str, float]
    seconds: float


def source_commit() -> str:
    """The exporting code's git commit, '-dirty' when it has uncommitted changes."""
    root = Path(__file__).resolve().parents[2]
    try:
        res = subprocess.run(
            ["git", "-C", str(root), "describe", "--always", "--dirty", "--abbrev=12"],
            capture_output=True,
            text=True,
            timeout=10,
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return res.stdout.strip() if res.returncode == 0 and res.stdout.strip() else "unknown"


def all_nodes(graph: onnx.GraphProto | onnx.ModelProto) -> Iterator[onnx.NodeProto]:
    """Every node, those inside loop bodies and local functions included (in place)."""
    nodes = list(graph.graph.node) if isinstance(graph, onnx.ModelProto) else list(graph.node)
    if isinstance(graph, onnx.ModelProto):
        nodes += [n for fn in graph.functions for n in fn.node]
    for node in nodes:
        yield node
        for attr in node.attribute:
            if attr.type == onnx.AttributeProto.GRAPH:
                yield from all_nodes(attr.g)


def count_nodes(graph: onnx.GraphProto | onnx.ModelProto) -> tuple[int, int]:
    """(all nodes including those inside loop bodies and local functions, Scan/Loop nodes)."""
    kinds = [node.op_type for node in all_nodes(graph)]
    return len(kinds), sum(k in ("Scan", "Loop") for k in kinds)


def _trace(model: OverlapMamba) -> onnx.ModelProto:
    cfg = model.cfg.model_copy(update={"scan_backend": "onnx"})
    export_model = OverlapMamba(cfg)
    export_model.load_state_dict(model.state_dict())
    export_model.eval()
    # Batch 2, not 1: the exporter specialises a size-1 example axis to a constant. With
    # token_views V the input holds V images a scan: its batch axis is V × the scans.
    views = cfg.token_views
    example = torch.rand(2 * views, 1, cfg.height, cfg.width)
    scans = torch.export.Dim("batch", min=1, max=4096)
    batch = scans if views == 1 else views * scans
    try:
        proto = quiet_export(
            export_model,
            (example,),
            input_names=[INPUT],
            output_names=list(OUTPUTS),
            dynamic_shapes={"image": {0: batch}},
            custom_translation_table=TRANSLATIONS,
        )
        attach_functions(proto, cfg.width, cfg.d_inner, cfg.d_state, cfg.scan_chunk)
        _drop_stack_traces(proto)
    except Exception as err:  # the exporter raises many kinds; say which step failed
        notes = "\n".join(getattr(err, "__notes__", []))
        raise ExportError(
            f"torch.onnx.export failed: {type(err).__name__}: {str(err)[:2000]}\n{notes}"
        ) from None
    return proto


# The exporter's note on every node of the Python line that made it: an absolute path and a
# line number, so the graph's hash (the model id) changed with the checkout's folder and any
# edit above the line. The other notes (module scopes, which recover.py reads) stay.
_STACK_TRACE = "pkg.torch.onnx.stack_trace"


def _drop_stack_traces(proto: onnx.ModelProto) -> None:
    for node in all_nodes(proto):
        keep = [p for p in node.metadata_props if p.key != _STACK_TRACE]
        if len(keep) != len(node.metadata_props):
            del node.metadata_props[:]
            node.metadata_props.extend(keep)


def _check_interface(
    proto: onnx.ModelProto, height: int, width: int, scans: bool, views: int = 1
) -> None:
    (inp,) = proto.graph.input
    dims = inp.type.tensor_type.shape.dim
    if inp.name != INPUT or len(dims) != 4:
        raise ExportError(f"exported input is {inp.name!r} with {len(dims)} axes; want {INPUT}")
    if not dims[0].dim_param:
        raise ExportError(
            f"the exported batch axis is fixed to {dims[0].dim_value}; it must be symbolic"
        )
    dims[0].dim_param = "batch"
    if [d.dim_value for d in dims[1:]] != [1, height, width]:
        raise ExportError(f"exported input shape {dims} is not (batch, 1, {height}, {width})")
    names = [o.name for o in proto.graph.output]
    if names != list(OUTPUTS):
        raise ExportError(f"exported outputs are {names}; want {list(OUTPUTS)}")
    for out in proto.graph.output:  # with token_views, views images make one scan's outputs
        d0 = out.type.tensor_type.shape.dim[0]
        d0.dim_param = "batch" if views == 1 else "scans"
    total, loops = count_nodes(proto)
    if scans and loops == 0:
        raise ExportError("the exported graph has no Scan/Loop node: the scan was unrolled")
    if total > 2000:
        raise ExportError(f"the exported graph has {total} nodes: the scan looks unrolled")


def quantize_int8(proto: onnx.ModelProto, min_size: int = INT8_MIN_SIZE) -> list[str]:
    """Store matrices of MatMul/Gemm weights with ≥ min_size values as int8 + per-column
    float scales; a Cast and a Mul (constant-folded at load) rebuild the float matrix."""
    graph = proto.graph
    inits = {t.name: t for t in graph.initializer}
    done: list[str] = []
    new_nodes = []
    for node in graph.node:
        if node.op_type not in ("MatMul", "Gemm") or len(node.input) < 2:
            continue
        name = node.input[1]
        t = inits.get(name)
        if t is None or t.data_type != onnx.TensorProto.FLOAT or name in done:
            continue
        w = numpy_helper.to_array(t)
        if w.ndim != 2 or w.size < min_size:
            continue
        trans_b = any(a.name == "transB" and a.i for a in node.attribute)
        axis = 1 if trans_b else 0  # reduce over the input axis: one scale per output
        scale = np.abs(w).max(axis=axis, keepdims=True).astype(np.float32) / 127.0
        scale[scale == 0] = 1.0
        q = np.clip(np.rint(w / scale), -127, 127).astype(np.int8)
        graph.initializer.remove(t)
        graph.initializer.extend(
            [
                numpy_helper.from_array(q, f"{name}_int8"),
                numpy_helper.from_array(scale, f"{name}_scale"),
            ]
        )
        new_nodes += [
            helper.make_node("Cast", [f"{name}_int8"], [f"{name}_f"], to=onnx.TensorProto.FLOAT),
            helper.make_node("Mul", [f"{name}_f", f"{name}_scale"], [name]),
        ]
        done.append(name)
    if new_nodes:  # producers go first: the graph stays topologically sorted
        nodes = list(graph.node)
        del graph.node[:]
        graph.node.extend(new_nodes + nodes)
    return done


def run_onnx(path: Path | str, images: np.ndarray, threads: int = 1) -> tuple[np.ndarray, ...]:
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    sess = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    desc, yaw = sess.run(list(OUTPUTS), {INPUT: images.astype(np.float32)})
    return desc, yaw


def compare(path: Path | str, model: OverlapMamba, images: np.ndarray) -> dict[str, float]:
    """onnxruntime vs PyTorch eval on the same images: max abs errors, min cosine."""
    with torch.no_grad():
        ref_desc, ref_yaw = (t.numpy() for t in model.eval()(torch.from_numpy(images).float()))
    desc, yaw = run_onnx(path, images)
    cos = (desc * ref_desc).sum(1) / (
        np.linalg.norm(desc, axis=1) * np.linalg.norm(ref_desc, axis=1)
    )
    return {
        "descriptor_max_abs": float(np.abs(desc - ref_desc).max()),
        "yaw_features_max_abs": float(np.abs(yaw - ref_yaw).max()),
        "descriptor_min_cosine": float(cos.min()),
        "descriptor_max_norm_error": float(np.abs(np.linalg.norm(desc, axis=1) - 1).max()),
    }


def verification_images(
    profile: SensorProfile, count: int = 3, seed: int = 0, sensor_input: str = "elevation"
) -> np.ndarray:
    """Random images with empty pixels, the value range of the model's real inputs: ranges
    for a range image, occupied cells for the bird's-eye inputs (1; ``bev-soft``,
    ``bev-span``: a share from empty to 1), whose networks never see a range and amplify one
    far beyond the tolerance's scale."""
    rng = np.random.default_rng(seed)
    shape = (count, 1, profile.height, profile.width)
    if sensor_input in BEV_MODES:
        img = np.ones(shape, np.float32)
        if sensor_input != "bev":  # bev-soft, bev-span: shares of a cell
            img = rng.uniform(profile.empty_value, 1.0, shape).astype(np.float32)
        img[rng.random(shape) < 0.9] = profile.empty_value  # a scan fills a few % of cells
        return img
    img = rng.uniform(profile.min_range, profile.max_range, shape).astype(np.float32)
    img[rng.random(shape) < 0.2] = profile.empty_value
    return img


def export_onnx(
    model: OverlapMamba,
    profile: SensorProfile,
    out: Path | str,
    *,
    checkpoint: dict[str, Any] | None = None,
    weight_format: str = "int8",
    images: np.ndarray | None = None,
    int8_min_size: int = INT8_MIN_SIZE,
    views: int | None = None,
) -> ExportResult:
    """Export, check and verify; the file appears at ``out`` only when all of it passed.
    ``views``: how many sub-column views describe a scan (:mod:`overlapmamba.core.views`);
    None: the network's ``token_views`` (1 unless it averages views itself, and then
    nothing else is allowed)."""
    t0 = time.perf_counter()
    out = Path(out)
    if weight_format not in WEIGHT_FORMATS:
        raise ExportError(
            f"weight format {weight_format!r} is unknown; allowed: {', '.join(WEIGHT_FORMATS)}"
        )
    cfg = model.cfg
    try:
        views = check_views(cfg.token_views if views is None else views)
    except ValueError as err:
        raise ExportError(str(err)) from None
    if cfg.token_views > 1 and views != cfg.token_views:
        raise ExportError(
            f"the network averages {cfg.token_views} views of a scan itself (token_views); "
            f"views must be {cfg.token_views}, got {views}"
        )
    if (profile.height, profile.width) != (cfg.height, cfg.width):
        raise ExportError(
            f"sensor profile {profile.name} makes {profile.height}×{profile.width} images but "
            f"the model takes {cfg.height}×{cfg.width}"
        )
    model = model.eval()
    proto = _trace(model)
    # The OT-style baseline (mixer "transformer") exports too: the encoder benchmark's peer.
    _check_interface(proto, cfg.height, cfg.width, scans=cfg.mixer == "mamba", views=views)
    if weight_format == "int8":
        quantize_int8(proto, int8_min_size)
    ckpt = checkpoint or {}
    train = ckpt.get("train") or {}
    total, loops = count_nodes(proto)
    meta = EncoderMetadata(
        **identity(
            graph_id(proto), views, check_mode(cfg.sensor_input), column_phase=cfg.column_phase
        ),
        profile=profile,
        model_config=cfg.to_dict(),
        descriptor_dim=cfg.out_dim,
        yaw_channels=cfg.yaw_channels,
        # epoch 0 is the initial weights (batch norm recalibrated): not trained
        weights="trained" if any(h["epoch"] > 0 for h in train.get("history", [])) else "random",
        weight_format=weight_format,
        training_data=train.get("data") or {},
        metrics={"val": ckpt.get("metrics") or {}, "best": train.get("best")},
        source_commit=source_commit(),
        exported_at=datetime.now(UTC).isoformat(timespec="seconds"),
        torch_version=torch.__version__,
        opset=next(o.version for o in proto.opset_import if o.domain in ("", "ai.onnx")),
    )
    del proto.metadata_props[:]
    for key, value in meta.to_props().items():
        proto.metadata_props.add(key=key, value=value)
    proto.producer_name = "overlapmamba"
    try:
        onnx.checker.check_model(proto, full_check=True)
    except onnx.checker.ValidationError as err:
        raise ExportError(f"the exported model fails onnx.checker: {str(err)[:2000]}") from None

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp{os.getpid()}")
    try:
        onnx.save(proto, tmp)
        imgs = (
            verification_images(profile, 3 * cfg.token_views, sensor_input=cfg.sensor_input)
            if images is None
            else images
        )
        report = compare(tmp, model, imgs)
        bad = report["yaw_features_max_abs"] > FLOAT_TOL or (
            report["descriptor_max_abs"] > FLOAT_TOL
            if weight_format == "float32"
            else report["descriptor_min_cosine"] < COSINE_TOL
        )
        if bad:
            raise ExportError(
                f"onnxruntime disagrees with PyTorch: {report}; allowed: max abs ≤ {FLOAT_TOL}"
                f" (descriptor cosine ≥ {COSINE_TOL} with int8 weights)",
                **report,
            )
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return ExportResult(
        path=out,
        metadata=meta,
        size_bytes=out.stat().st_size,
        nodes=total,
        scan_nodes=loops,
        verification=report,
        seconds=time.perf_counter() - t0,
    )
