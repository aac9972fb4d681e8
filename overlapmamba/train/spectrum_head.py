"""An exported encoder whose descriptor carries its yaw features' magnitude spectrum.

:mod:`overlapmamba.core.yaw_spectrum` ranks a shortlist by the yaw features' magnitude
spectrum over azimuth, alone or joined to the network's descriptor. This writes that vector
into the graph as its ``descriptor`` output, so that everything which reads a descriptor (the
service's maps and its search, a descriptor query, a map shared as descriptors, the
benchmarks) takes it without knowing: the network's descriptor output is renamed, and the
spectrum is computed from ``yaw_features`` by one matrix product (every channel of every
scan a row, times the real and imaginary parts of the first ``bins`` DFT frequencies over
the W columns), its magnitude, optionally a square root, and unit length; with a mix
below 1 the network's descriptor at unit length joins it, the two weighted so that a
squared distance is (1 − a) · d²(descriptor) + a · d²(spectrum). ``yaw_features`` is kept
as it was: the second stage and the relative yaw read it.

The graph changes, so the file gets a new graph id and model id (its descriptors must not
share a map with the source's); its ``descriptor_dim`` is the new length, and its
metadata's ``first_stage`` names the stage, so a reader can tell. A file carrying sensor
maps or calibration fitted on its old descriptor is refused: those would apply to a vector
they were not fitted on.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import helper, numpy_helper

from overlapmamba.core.modelmeta import EncoderMetadata, identity
from overlapmamba.core.yaw_spectrum import FirstStage
from overlapmamba.train.errors import ExportError
from overlapmamba.train.modelfile import graph_id, load_encoder, save_encoder
from overlapmamba.train.reduce_head import refuse_fitted, strip_reduction

NETWORK_DESCRIPTOR = "netvlad_descriptor"  # the network's own descriptor, renamed


def dft_matrices(width: int, bins: int) -> tuple[np.ndarray, np.ndarray]:
    """(width, bins) float32 cos and −sin of 2π · w · k / width: x @ them are the real and
    imaginary parts of ``np.fft.rfft(x)[..., :bins]``."""
    angle = 2.0 * np.pi * np.outer(np.arange(width), np.arange(bins)) / width
    return np.cos(angle).astype(np.float32), (-np.sin(angle)).astype(np.float32)


def check_source(meta: EncoderMetadata, src: Path | str, stage: FirstStage) -> None:
    """Refuse (:class:`ExportError`, saying why) a file ``stage`` cannot be written into:
    one carrying a first stage already, or sensor maps or calibration fitted on its own
    descriptor; and the ``descriptor`` stage, which adds nothing."""
    if stage.mix == 0.0:
        raise ExportError("first stage 'descriptor' is the file's own descriptor: nothing to add")
    if meta.first_stage != "descriptor":
        raise ExportError(
            f"{src} already carries first stage {meta.first_stage!r}; start from the file it "
            "was written from (`export FILE --first-stage descriptor` takes it out)"
        )
    refuse_fitted(meta, src, "write the first stage into a file")


def with_first_stage(src: Path | str, out: Path | str, stage: FirstStage) -> EncoderMetadata:
    """Write ``src``'s encoder to ``out`` with ``stage``'s vector as its descriptor (see the
    module's text). Atomic. Returns the new metadata."""
    src, out = Path(src), Path(out)
    proto, meta = load_encoder(src)
    check_source(meta, src, stage)
    g = proto.graph
    outputs = {o.name: o for o in g.output}
    if set(outputs) != {"descriptor", "yaw_features"}:
        raise ExportError(f"{src}: outputs {sorted(outputs)}, expected descriptor, yaw_features")
    width = outputs["yaw_features"].type.tensor_type.shape.dim[2].dim_value
    if stage.bins > width // 2 + 1:
        raise ExportError(
            f"{stage.bins} bins but {width} columns have {width // 2 + 1} frequencies"
        )
    for node in g.node:
        node.output[:] = [NETWORK_DESCRIPTOR if o == "descriptor" else o for o in node.output]
        node.input[:] = [NETWORK_DESCRIPTOR if i == "descriptor" else i for i in node.input]
    cos, sin = dft_matrices(width, stage.bins)
    consts = {
        "fs_dft": np.concatenate([cos, sin], axis=1),  # (W, 2 · bins): real, then imaginary
        "fs_rows": np.array([-1, width], dtype=np.int64),
        "fs_parts": np.array([-1, 2, stage.bins], dtype=np.int64),
        "fs_scans": np.array([-1, meta.yaw_channels * stage.bins], dtype=np.int64),
        "fs_axis1": np.array([1], dtype=np.int64),
        "fs_eps": np.array(1e-12, dtype=np.float32),
    }
    if stage.mix < 1.0:  # (a graph keeps no initializer it does not use)
        consts["fs_w_desc"] = np.array(np.sqrt(1.0 - stage.mix), dtype=np.float32)
        consts["fs_w_spec"] = np.array(np.sqrt(stage.mix), dtype=np.float32)
    g.initializer.extend(numpy_helper.from_array(v, k) for k, v in consts.items())
    mag = "fs_mag"
    nodes = [  # every channel of every scan a row: one product gives both parts
        helper.make_node("Reshape", ["yaw_features", "fs_rows"], ["fs_channels"]),
        helper.make_node("MatMul", ["fs_channels", "fs_dft"], ["fs_parts_flat"]),
        helper.make_node("Mul", ["fs_parts_flat", "fs_parts_flat"], ["fs_squares"]),
        helper.make_node("Reshape", ["fs_squares", "fs_parts"], ["fs_squares3"]),
        helper.make_node("ReduceSum", ["fs_squares3", "fs_axis1"], ["fs_power"], keepdims=0),
        helper.make_node("Sqrt", ["fs_power"], [mag]),
    ]
    if stage.compress == "sqrt":
        nodes.append(helper.make_node("Sqrt", [mag], ["fs_mag_sqrt"]))
        mag = "fs_mag_sqrt"
    nodes.append(helper.make_node("Reshape", [mag, "fs_scans"], ["fs_spec"]))
    joined = ("fs_spec", NETWORK_DESCRIPTOR) if stage.mix < 1.0 else ("fs_spec",)
    for name in joined:  # each at unit length, as the numpy stage
        nodes += [
            helper.make_node("ReduceL2", [name, "fs_axis1"], [f"{name}_norm"], keepdims=1),
            helper.make_node("Max", [f"{name}_norm", "fs_eps"], [f"{name}_safe"]),
            helper.make_node("Div", [name, f"{name}_safe"], [f"{name}_unit"]),
        ]
    if stage.mix == 1.0:
        nodes.append(helper.make_node("Identity", ["fs_spec_unit"], ["descriptor"]))
    else:
        nodes += [
            helper.make_node("Mul", [f"{NETWORK_DESCRIPTOR}_unit", "fs_w_desc"], ["fs_d"]),
            helper.make_node("Mul", ["fs_spec_unit", "fs_w_spec"], ["fs_s"]),
            helper.make_node("Concat", ["fs_d", "fs_s"], ["descriptor"], axis=1),
        ]
    g.node.extend(nodes)
    dim = meta.yaw_channels * stage.bins + (meta.descriptor_dim if stage.mix < 1.0 else 0)
    outputs["descriptor"].type.tensor_type.shape.dim[1].dim_value = dim
    try:
        onnx.checker.check_model(proto)
    except onnx.checker.ValidationError as err:
        raise ExportError(f"{src}: the graph with the first stage is invalid: {err}") from None
    del proto.metadata_props[:]  # the graph's id is taken without them, as export_onnx does
    new = EncoderMetadata.model_validate(
        {
            **meta.model_dump(by_alias=True),
            "first_stage": stage.name,
            "descriptor_dim": dim,
            **identity(graph_id(proto), meta.views, meta.sensor_input, "", meta.column_phase),
        },
        by_alias=True,
    )
    save_encoder(proto, new, out)
    return new


def without_first_stage(src: Path | str, out: Path | str) -> EncoderMetadata:
    """Write ``src``'s encoder to ``out`` with the network's own descriptor again: the first
    stage :func:`with_first_stage` wrote is taken out of the graph (its nodes and constants,
    a reduction of it too (:mod:`overlapmamba.train.reduce_head`), the network's descriptor
    renamed back), so that writing the same stage into the result
    gives the source's graph again, with its graph id and model id. The calibration goes (it
    was chosen on the other vector); a file carrying sensor maps is refused, as with a new
    stage."""
    src, out = Path(src), Path(out)
    proto, meta = load_encoder(src)
    if meta.first_stage == "descriptor":
        raise ExportError(f"{src} carries no first stage: its descriptor is the network's")
    if meta.sensor_maps:
        raise ExportError(
            f"{src} carries sensor_maps ({', '.join(meta.sensor_maps)}) fitted on its first "
            "stage; write the file without them first"
        )
    g = proto.graph
    strip_reduction(g)  # a reduction of the stage goes with it
    added = _stage_outputs(g)
    own = [n for n in g.node if not set(n.output) & added]
    del g.node[:]
    g.node.extend(own)
    kept = [t for t in g.initializer if not t.name.startswith("fs_")]
    del g.initializer[:]
    g.initializer.extend(kept)
    for node in g.node:
        node.output[:] = ["descriptor" if o == NETWORK_DESCRIPTOR else o for o in node.output]
        node.input[:] = ["descriptor" if i == NETWORK_DESCRIPTOR else i for i in node.input]
    dim = int(meta.network["out_dim"])  # the network's own, as its config says
    outputs = {o.name: o for o in g.output}
    outputs["descriptor"].type.tensor_type.shape.dim[1].dim_value = dim
    try:
        onnx.checker.check_model(proto)
    except onnx.checker.ValidationError as err:
        raise ExportError(f"{src}: the graph without its first stage is invalid: {err}") from None
    del proto.metadata_props[:]
    new = EncoderMetadata.model_validate(
        {
            **meta.model_dump(by_alias=True),
            "first_stage": "descriptor",
            "descriptor_dim": dim,
            "calibration": {},
            "reduction": {},
            **identity(graph_id(proto), meta.views, meta.sensor_input, "", meta.column_phase),
        },
        by_alias=True,
    )
    save_encoder(proto, new, out)
    return new


def _stage_outputs(g: onnx.GraphProto) -> set[str]:
    """The tensors the first stage adds: its ``fs_`` tensors, the network descriptor's unit
    length (``netvlad_descriptor_*``) and the ``descriptor`` it joins."""
    added = ("fs_", f"{NETWORK_DESCRIPTOR}_")
    names = {o for n in g.node for o in n.output if o.startswith(added)}
    return names | {"descriptor"}
