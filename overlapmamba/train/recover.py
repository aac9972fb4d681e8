"""PyTorch weights back from an exported encoder (``.onnx``), so that a shipped model whose
checkpoint is gone can be trained further (``overlapmamba train --init MODEL.onnx``).

The exporter keeps most parameters under their own names. The rest it rewrites, and each
rewrite is undone from the graph itself, never from exporter-assigned names:

- a linear layer's weight becomes the transposed matrix of a ``MatMul`` whose node records
  the layer's module (``pkg.torch.onnx.name_scopes``): the weight is that matrix transposed;
- a Mamba block's ``A = −exp(A_log)`` is folded into one constant, the third input of the
  block's ``SelectiveScanRing``: ``A_log = log(−A)``;
- a batch norm after a convolution (SPP) is folded into the convolution's weight and a new
  bias: the norm comes back as the identity (mean 0, variance 1 − ε, scale 1) with that bias
  as its shift, so the network computes exactly what the file does in eval mode. Its
  running statistics say nothing about any data: a network recovered this way trains with
  batch norm frozen (``TrainConfig.freeze_bn``);
- int8 storage (:func:`overlapmamba.train.export.quantize_int8`): the matrix is ``int8 × scale``,
  the values the file computes with.

The result is then checked against onnxruntime on the same images: :func:`recover` refuses
(``CheckpointError``) when a parameter is left unfilled, a shape disagrees, or the
descriptors differ by more than :data:`TOLERANCE`.
"""

from __future__ import annotations

import ast
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from overlapmamba.core.sensors import SensorProfile
from overlapmamba.train.errors import CheckpointError
from overlapmamba.train.model import OverlapMamba, OverlapMambaConfig, meeting_views

if TYPE_CHECKING:
    from overlapmamba.train.export import ExportResult

TOLERANCE = 1e-5  # max abs descriptor difference to onnxruntime (measured: 8e-8)
_SCOPES = "pkg.torch.onnx.name_scopes"


def _module(node: Any) -> str | None:
    """The innermost module a node was traced in ('blocks.0.in_proj'), from its metadata."""
    for prop in node.metadata_props:
        if prop.key == _SCOPES:
            scopes = ast.literal_eval(prop.value)
            return scopes[-2] if len(scopes) >= 2 else None
    return None


def state_dict_from_onnx(proto: Any, model: OverlapMamba) -> dict[str, torch.Tensor]:
    """``model``'s state dict filled from the graph ``proto`` (see the module's rules)."""
    from onnx import numpy_helper

    inits = {i.name: numpy_helper.to_array(i) for i in proto.graph.initializer}
    for name in [n[: -len("_int8")] for n in inits if n.endswith("_int8")]:
        if f"{name}_scale" in inits:  # int8 storage: the matrix the Cast and Mul rebuild
            inits[name] = inits[f"{name}_int8"].astype(np.float32) * inits[f"{name}_scale"]
    want = model.state_dict()
    got: dict[str, np.ndarray] = {k: inits[k] for k in want if k in inits}
    for node in proto.graph.node:
        module = _module(node)
        if module is None:
            continue
        if node.op_type == "MatMul" and len(node.input) == 2 and node.input[1] in inits:
            key = f"{module}.weight"
            if key in want and key not in got:
                got[key] = inits[node.input[1]].T
        elif node.op_type == "SelectiveScanRing" and node.input[2] in inits:
            key = f"{module}.A_log"
            if key in want and key not in got:
                got[key] = np.log(-inits[node.input[2]])
        elif node.op_type == "Conv" and len(node.input) == 3 and node.input[2] in inits:
            bn = module  # the folded norm's scope: the bias belongs to it
            norm = dict(model.named_modules()).get(bn)
            if isinstance(norm, torch.nn.BatchNorm2d) and f"{bn}.weight" not in got:
                bias = inits[node.input[2]]
                got[f"{bn}.weight"] = np.ones_like(bias)
                got[f"{bn}.bias"] = bias
                got[f"{bn}.running_mean"] = np.zeros_like(bias)
                got[f"{bn}.running_var"] = np.full_like(bias, 1.0 - norm.eps)
                got[f"{bn}.num_batches_tracked"] = np.array(0, np.int64)
    missing = [k for k in want if k not in got]
    if missing:
        raise CheckpointError(
            f"the graph does not give back {len(missing)} parameter(s): {', '.join(missing)}",
            missing=missing,
        )
    out: dict[str, torch.Tensor] = {}
    for key, ref in want.items():
        value = torch.from_numpy(np.array(got[key], order="C")).to(ref.dtype)
        if value.shape != ref.shape:
            raise CheckpointError(
                f"{key}: the graph gives shape {tuple(value.shape)}, the network has "
                f"{tuple(ref.shape)}",
                key=key,
            )
        out[key] = value
    return out


def recover(
    path: str | Path, images: np.ndarray | None = None
) -> tuple[OverlapMamba, SensorProfile, dict[str, Any]]:
    """The network of an exported encoder with its weights (eval mode), its sensor profile
    and the check against onnxruntime on ``images`` ((N, 1, H, W); default: the exporter's
    verification images): :func:`overlapmamba.train.export.compare`'s numbers and ``scans``."""
    import onnx

    from overlapmamba.train.export import compare, verification_images
    from overlapmamba.train.modelfile import metadata_of

    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"model {path} does not exist", path=str(path))
    try:
        proto = onnx.load(str(path))
        meta = metadata_of(proto)
        model = OverlapMamba(OverlapMambaConfig.from_dict(meta.network)).eval()
    except Exception as err:  # protobuf and the metadata parser raise their own classes
        raise CheckpointError(
            f"{path} is not an exported encoder ({type(err).__name__}: {err})", path=str(path)
        ) from None
    model.load_state_dict(state_dict_from_onnx(proto, model))
    if images is None:
        images = verification_images(
            meta.profile, 3 * model.cfg.token_views, sensor_input=meta.sensor_input
        )
    images = np.asarray(images, np.float32)
    check = {**compare(path, model, images), "scans": len(images)}
    if not check["descriptor_max_abs"] <= TOLERANCE:
        raise CheckpointError(
            f"{path}: the recovered weights give descriptors {check['descriptor_max_abs']:.2e} "
            f"from onnxruntime's (allowed: {TOLERANCE:.0e}); the file was not written by this "
            "exporter or the network changed since",
            **check,
        )
    return model, meta.profile, check


def with_token_views(src: str | Path, out: str | Path, views: int) -> ExportResult:
    """Write ``src``'s encoder to ``out`` with its ``views`` sub-column views met at the
    tokens (``OverlapMambaConfig.token_views``): the per-column stem runs once a view, the
    blocks and head once a scan. The weights are ``src``'s, recovered and checked
    (:func:`recover`), the graph traced anew (its input then holds ``views`` images a scan);
    the training record and the sensor input are carried over. The calibration is not: it
    was chosen for other descriptors (the benchmarks write the new file's). ``views`` 1
    writes the plain one-image graph. Returns the export's
    :class:`~overlapmamba.train.export.ExportResult`."""
    from overlapmamba.core.modelmeta import identity
    from overlapmamba.core.views import check_views
    from overlapmamba.train.errors import ExportError
    from overlapmamba.train.export import export_onnx
    from overlapmamba.train.modelfile import load_encoder, rewrite_metadata

    try:
        views = check_views(views)
    except ValueError as err:
        raise ExportError(str(err)) from None
    _, source = load_encoder(src)
    if source.first_stage != "descriptor":  # the graph is traced anew, without it
        raise ExportError(
            f"{src} carries first stage {source.first_stage!r} in its graph, which a new "
            "trace would drop: meet the views at the tokens in the file it was written "
            "from, then write the first stage again (--first-stage)"
        )
    model, profile, _ = recover(src)
    tokens = meeting_views(model, views)
    res = export_onnx(tokens, profile, out, weight_format=source.weight_format, views=views)
    res.metadata = rewrite_metadata(
        out,
        out,
        lambda meta: {
            **identity(meta.graph, views, source.sensor_input, "", source.column_phase),
            "weights": source.weights,
            "training_data": source.training_data,
            "metrics": source.metrics,
        },
    )
    return res
