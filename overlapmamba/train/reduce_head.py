"""An exported encoder whose descriptor is its first stage reduced to fewer floats.

A first stage that joins the yaw features' spectrum to the network's descriptor
(:mod:`overlapmamba.train.spectrum_head`) answers better than the descriptor alone but is
longer: ``mixed:0.75:32:sqrt`` holds 768 floats where the network's descriptor holds 256.
A map's index, a descriptor query and a map shared as descriptors pay for every float, and
the service's descriptors had 256. This writes a linear map into the graph after the first
stage: the vector's leading principal directions, fitted on the file's own vectors of
validation scans, then unit length again (the service compares unit vectors).

The directions are the covariance's leading eigenvectors (the vectors centred to find them),
but the vectors are projected *uncentred*: every first-stage vector is a unit vector and they
share a large common part, which the projection keeps, so that unit length afterwards moves
the distances little. Centred, each projection's length varies with how far the vector lies
from the mean, and the unit length afterwards distorts the ranking (measured on a second drive
of the validation town, the model card says by how much).

The graph changes, so the file gets a new model id; ``descriptor_dim`` is the new length and
the metadata's ``reduction`` records what was fitted on what. The second stage cannot score by
the network's own distance inside the vector (it is no longer there): such a file takes the
``stage`` score. A file carrying calibration or sensor maps fitted on its old descriptor is
refused, as is a file reduced already. :func:`overlapmamba.train.spectrum_head.without_first_stage`
takes the reduction out with the first stage.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import onnx
from onnx import helper, numpy_helper

from overlapmamba.core.modelmeta import EncoderMetadata, identity
from overlapmamba.core.yaw_spectrum import FirstStage
from overlapmamba.train.errors import ExportError
from overlapmamba.train.modelfile import graph_id, load_encoder, save_encoder

PREFIX = "rd_"  # every tensor the reduction adds (the stage's own output renamed among them)
STAGE_OUTPUT = PREFIX + "stage"
MIN_FIT_ROWS = 4  # fewer vectors than this span nothing worth keeping


def fit_directions(vectors: np.ndarray, dim: int) -> tuple[np.ndarray, float]:
    """(N, D) first-stage vectors → the (D, ``dim``) matrix of their ``dim`` leading principal
    directions (float32, columns by falling variance) and the share of the variance about
    their mean those directions hold. ValueError when ``dim`` is not below D, or when the
    rows are too few or not finite."""
    x = np.asarray(vectors, np.float64)
    if x.ndim != 2:
        raise ValueError(f"vectors must be (N, D); got shape {x.shape}")
    n, d = x.shape
    if not 1 <= dim < d:
        raise ValueError(
            f"a reduction of {d}-float vectors must keep 1 … {d - 1} floats; got {dim}"
        )
    if n < max(MIN_FIT_ROWS, dim):
        raise ValueError(
            f"{n} vectors cannot fit {dim} directions: at least {max(MIN_FIT_ROWS, dim)} needed"
        )
    if not np.isfinite(x).all():
        raise ValueError("the vectors to fit hold NaN or infinite values")
    centred = x - x.mean(axis=0)
    _, s, vt = np.linalg.svd(centred, full_matrices=False)
    power = s**2
    kept = float(power[:dim].sum() / max(power.sum(), 1e-300))
    basis = vt[:dim].T
    # each direction's sign fixed (its largest entry positive) so that a fit is repeatable
    signs = np.sign(basis[np.abs(basis).argmax(axis=0), np.arange(dim)])
    return (basis * np.where(signs == 0, 1.0, signs)).astype(np.float32), kept


def reduce_vectors(vectors: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """What the graph does after its first stage, in numpy: ``vectors @ directions`` at unit
    length (float32; a zero row stays zero)."""
    y = np.asarray(vectors, np.float32) @ np.asarray(directions, np.float32)
    return y / np.maximum(np.linalg.norm(y, axis=1, keepdims=True), np.float32(1e-12))


def parse_reduction(text: str) -> tuple[int, int | None]:
    """``K`` → (K, None): the whole vector's K leading directions; ``K1+K2`` → (K1 + K2,
    K1): the network descriptor's K1 directions ahead of the spectrum's K2, each part of a
    mixed first stage reduced on its own (:func:`split_directions`), so that a second stage
    can still score by the network's distance, approximated by the leading K1 floats."""
    parts = text.strip().split("+")
    try:
        sizes = [int(p) for p in parts]
    except ValueError:
        sizes = []
    if len(sizes) not in (1, 2) or min(sizes, default=0) < 1:
        raise ValueError(
            f"reduction {text!r} is not K or K1+K2 (floats to keep, e.g. 256 or 96+160: the "
            "network descriptor's 96 directions, then the spectrum's 160)"
        )
    return sum(sizes), (sizes[0] if len(sizes) == 2 else None)


def split_directions(
    vectors: np.ndarray, network_dim: int, lead: int, rest: int
) -> tuple[np.ndarray, float]:
    """A mixed first stage's (N, D) vectors, whose first ``network_dim`` floats are the
    network's descriptor → the (D, lead + rest) block matrix of the descriptor part's
    ``lead`` directions and the spectrum part's ``rest`` (:func:`fit_directions` each), and
    the share of the whole variance they hold."""
    x = np.asarray(vectors, np.float64)
    if not 0 < network_dim < x.shape[1]:
        raise ValueError(f"{x.shape[1]}-float vectors hold no {network_dim}-float descriptor part")
    head, _ = fit_directions(x[:, :network_dim], lead)
    tail, _ = fit_directions(x[:, network_dim:], rest)
    out = np.zeros((x.shape[1], lead + rest), np.float32)
    out[:network_dim, :lead], out[network_dim:, lead:] = head, tail
    centred = x - x.mean(axis=0)
    kept = float(((centred @ out) ** 2).sum() / max((centred**2).sum(), 1e-300))
    return out, kept


def refuse_fitted(meta: EncoderMetadata, src: Path | str, instead: str) -> None:
    """:class:`ExportError` for a file carrying sensor maps or calibration: they were fitted
    on its own descriptor and would apply to another vector. ``instead``: what to do to a
    file without them (then fit or calibrate it)."""
    for field in ("sensor_maps", "calibration"):
        if getattr(meta, field):
            raise ExportError(
                f"{src} carries {field} ({', '.join(getattr(meta, field))}) fitted on its own "
                f"descriptor; they would apply to another vector: {instead} without them, "
                "then fit or calibrate that file"
            )


def check_reducible(meta: EncoderMetadata, src: Path | str, dim: int) -> None:
    """Refuse (:class:`ExportError`, saying why) a file that cannot be reduced to ``dim``."""
    if meta.reduction:
        raise ExportError(
            f"{src} is reduced already ({meta.reduction.get('from_dim')} → "
            f"{meta.descriptor_dim} floats); start from the file it was written from"
        )
    refuse_fitted(meta, src, "reduce a file")
    if not 1 <= dim < meta.descriptor_dim:
        raise ExportError(
            f"--reduce {dim}: {src}'s descriptor has {meta.descriptor_dim} floats; allowed: "
            f"1 … {meta.descriptor_dim - 1}"
        )


def with_reduction(
    src: Path | str,
    out: Path | str,
    directions: np.ndarray,
    fitted_on: dict[str, Any],
    variance_kept: float,
    network_part: int | None = None,
) -> EncoderMetadata:
    """Write ``src``'s encoder to ``out`` with its descriptor times ``directions`` (D, K) at
    unit length as its descriptor (see the module's text); ``fitted_on`` and
    ``variance_kept`` go into the metadata's ``reduction``; ``network_part``: the leading
    floats that are the network descriptor's own directions (:func:`split_directions`), by
    which a second stage may score. Atomic. Returns the new metadata."""
    src, out = Path(src), Path(out)
    proto, meta = load_encoder(src)
    directions = np.asarray(directions, np.float32)
    if directions.ndim != 2 or directions.shape[0] != meta.descriptor_dim:
        raise ExportError(
            f"directions of shape {directions.shape} do not take {src}'s "
            f"{meta.descriptor_dim}-float descriptor"
        )
    dim = int(directions.shape[1])
    check_reducible(meta, src, dim)
    if network_part is not None:
        own = int(meta.network["out_dim"])
        if not FirstStage.parse(meta.first_stage).mix or not 0 < network_part < dim:
            raise ExportError(
                f"{src}: a reduction split at {network_part} floats needs a mixed first stage "
                f"(the network's descriptor ahead of the spectrum) and 1 … {dim - 1} floats "
                f"for its part; the file's first stage is {meta.first_stage}"
            )
        if np.any(directions[own:, :network_part]) or np.any(directions[:own, network_part:]):
            raise ExportError(
                f"the directions' first {network_part} columns must read only the network's "
                f"{own}-float descriptor, the others only the spectrum"
            )
    g = proto.graph
    outputs = {o.name: o for o in g.output}
    if set(outputs) != {"descriptor", "yaw_features"}:
        raise ExportError(f"{src}: outputs {sorted(outputs)}, expected descriptor, yaw_features")
    for node in g.node:
        node.output[:] = [STAGE_OUTPUT if o == "descriptor" else o for o in node.output]
        node.input[:] = [STAGE_OUTPUT if i == "descriptor" else i for i in node.input]
    consts = {
        PREFIX + "directions": directions,
        PREFIX + "axis1": np.array([1], dtype=np.int64),
        PREFIX + "eps": np.array(1e-12, dtype=np.float32),
    }
    g.initializer.extend(numpy_helper.from_array(v, k) for k, v in consts.items())
    g.node.extend(
        [
            helper.make_node("MatMul", [STAGE_OUTPUT, PREFIX + "directions"], [PREFIX + "proj"]),
            helper.make_node(
                "ReduceL2", [PREFIX + "proj", PREFIX + "axis1"], [PREFIX + "norm"], keepdims=1
            ),
            helper.make_node("Max", [PREFIX + "norm", PREFIX + "eps"], [PREFIX + "safe"]),
            helper.make_node("Div", [PREFIX + "proj", PREFIX + "safe"], ["descriptor"]),
        ]
    )
    outputs["descriptor"].type.tensor_type.shape.dim[1].dim_value = dim
    try:
        onnx.checker.check_model(proto)
    except onnx.checker.ValidationError as err:
        raise ExportError(f"{src}: the graph with the reduction is invalid: {err}") from None
    del proto.metadata_props[:]  # the graph's id is taken without them, as export_onnx does
    reduction = {
        "method": "principal directions, projected uncentred, then unit length",
        "from_dim": meta.descriptor_dim,
        "dim": dim,
        "variance_kept": round(float(variance_kept), 6),
        **({"network_part": network_part} if network_part is not None else {}),
        "fitted_on": fitted_on,
        "source_model_id": meta.model_id,
    }
    new = EncoderMetadata.model_validate(
        {
            **meta.model_dump(by_alias=True),
            "descriptor_dim": dim,
            "reduction": reduction,
            **identity(graph_id(proto), meta.views, meta.sensor_input, "", meta.column_phase),
        },
        by_alias=True,
    )
    save_encoder(proto, new, out)
    return new


def strip_reduction(g: onnx.GraphProto) -> None:
    """Take a reduction's nodes and constants out of ``g`` in place, the first stage's vector
    the ``descriptor`` again (no-op on a graph without one)."""
    if not any(o == STAGE_OUTPUT for n in g.node for o in n.output):
        return
    own = [
        n
        for n in g.node
        if STAGE_OUTPUT in n.output
        or not any(o.startswith(PREFIX) or o == "descriptor" for o in n.output)
    ]
    del g.node[:]
    g.node.extend(own)
    kept = [t for t in g.initializer if not t.name.startswith(PREFIX)]
    del g.initializer[:]
    g.initializer.extend(kept)
    for node in g.node:
        node.output[:] = ["descriptor" if o == STAGE_OUTPUT else o for o in node.output]
        node.input[:] = ["descriptor" if i == STAGE_OUTPUT else i for i in node.input]


def reduce_file(
    src: Path | str, out: Path | str, spec: str, towns: list[Path], *, shown: str | None = None
) -> EncoderMetadata:
    """Fit the directions ``spec`` names (:func:`parse_reduction`: K, or K1+K2 split
    between a mixed first stage's network descriptor and its spectrum) on ``src``'s own
    descriptors of every scan of ``towns`` (as the file describes a scan: its views, columns
    and input) and write ``src`` reduced to ``out`` (:func:`with_reduction`). The towns go
    into the metadata with their data fingerprints: fit on validation towns, never on the
    test towns a file is reported on."""
    from overlapmamba.core.datasets import open_sequence
    from overlapmamba.train.checkpoint import load_model
    from overlapmamba.train.evaluate import describe_sequence

    src = Path(src)
    name = shown or str(src)  # what messages call the file (the export's own work file is not)
    _, meta = load_encoder(src)
    try:
        dim, lead = parse_reduction(spec)
    except ValueError as err:
        raise ExportError(str(err)) from None
    check_reducible(meta, name, dim)
    if not towns:
        raise ExportError("a reduction is fitted on validation towns: give at least one")
    if lead is not None and not FirstStage.parse(meta.first_stage).mix:
        raise ExportError(  # said before any town is described
            f"--reduce {spec}: a split reduction needs a mixed first stage; {name}'s "
            f"descriptor is {meta.first_stage}"
        )
    sequences = [open_sequence(town) for town in towns]  # every town opens, before the work
    model, profile, _ = load_model(src)
    parts, fitted_on = [], {}
    for town, seq in zip(towns, sequences, strict=True):
        desc, _ = describe_sequence(model, seq, profile)
        parts.append(desc)
        fitted_on[Path(town).name] = {"scans": len(desc), "data_sha256": _fingerprint(town)}
    vectors = np.concatenate(parts)
    if lead is None:
        directions, kept = fit_directions(vectors, dim)
    else:
        own = int(meta.network["out_dim"])
        directions, kept = split_directions(vectors, own, lead, dim - lead)
    return with_reduction(src, out, directions, fitted_on, kept, lead)


def _fingerprint(town: Path) -> str:
    import json

    manifest = Path(town) / "manifest.json"
    if not manifest.is_file():
        return ""
    return str(json.loads(manifest.read_text()).get("data_sha256", ""))
