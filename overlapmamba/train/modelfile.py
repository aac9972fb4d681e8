"""An exported encoder file's metadata (:class:`overlapmamba.core.modelmeta.EncoderMetadata`): read,
and rewritten in place with the graph and weights byte for byte. Needs onnx, never torch, so
the service's benchmarks write a model's calibration without the training stack."""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import onnx

from overlapmamba.core.calibration import Calibrated, check_calibration
from overlapmamba.core.modelmeta import EncoderMetadata, identity
from overlapmamba.core.sensormaps import SensorMap, maps_digest
from overlapmamba.core.sensors.input import Mode, check_mode
from overlapmamba.core.views import check_column_phase, check_views
from overlapmamba.train.errors import ExportError


def read_metadata(path: Path | str) -> EncoderMetadata:
    """The metadata of an exported model, read without building an inference session;
    :class:`ExportError` when the file is not ONNX (a corrupt download, a .pt renamed)."""
    try:
        proto = onnx.load(str(path), load_external_data=False)
    except FileNotFoundError:
        raise ExportError(f"model {path} does not exist") from None
    except Exception as err:  # protobuf raises its own classes
        raise ExportError(f"{path} is not an ONNX file ({type(err).__name__}: {err})") from None
    return metadata_of(proto)


def metadata_of(proto: onnx.ModelProto, *, check_maps: bool = True) -> EncoderMetadata:
    """The metadata of a loaded exported model; ``check_maps``: as
    :meth:`EncoderMetadata.from_props` takes it."""
    props = {p.key: p.value for p in proto.metadata_props}
    return EncoderMetadata.from_props(props, check_maps=check_maps)


def with_views(src: Path | str, out: Path | str, views: int) -> EncoderMetadata:
    """Write ``src``'s encoder to ``out`` described by ``views`` sub-column views
    (:mod:`overlapmamba.core.views`): the graph and weights byte for byte, the metadata with the new
    count and the model id that goes with it; every other field as it was. Atomic like
    :func:`export_onnx`. Returns the new metadata."""
    try:
        views = check_views(views)
    except ValueError as err:
        raise ExportError(str(err)) from None

    def update(meta: EncoderMetadata) -> dict[str, Any]:
        _maps_stay_valid(meta, "views", meta.views, views)
        ids = identity(meta.graph, views, meta.sensor_input, meta.maps_digest, meta.column_phase)
        return ids | _calibration_of(meta, meta.views, views)

    return rewrite_metadata(src, out, update)


def with_sensor_input(path: Path | str, mode: Mode) -> EncoderMetadata:
    """The model takes other sensors' scans by ``mode`` (:mod:`overlapmamba.core.sensors.input`):
    the graph stays byte for byte; the model id changes with the mode (other descriptors for
    those sensors' scans must not share a map), as it does with the views."""
    try:
        mode = check_mode(mode)
    except ValueError as err:
        raise ExportError(str(err)) from None

    def update(meta: EncoderMetadata) -> dict[str, Any]:
        _maps_stay_valid(meta, "sensor_input", meta.sensor_input, mode)
        ids = identity(meta.graph, meta.views, mode, meta.maps_digest, meta.column_phase)
        return ids | _calibration_of(meta, meta.sensor_input, mode)

    return rewrite_metadata(path, path, update)


def with_sensor_maps(
    src: Path | str, out: Path | str, maps: dict[str, SensorMap]
) -> EncoderMetadata:
    """Write ``src``'s encoder to ``out`` carrying ``maps`` (:mod:`overlapmamba.core.sensormaps`;
    they replace any it had, none removes them): the graph and weights byte for byte, the
    model id the one that goes with the maps (other sensors' descriptors change with them),
    and no calibration where the maps change (its thresholds were chosen on the descriptors
    the old maps gave). Atomic. Returns the new metadata."""
    digest = maps_digest(maps) if maps else ""
    return rewrite_metadata(
        src,
        out,
        lambda meta: {
            "sensor_maps": maps,
            **identity(meta.graph, meta.views, meta.sensor_input, digest, meta.column_phase),
            **_calibration_of(meta, meta.maps_digest, digest),
        },
        check_maps=False,  # the old maps go: a file refused for one of them is repaired here
    )


def with_column_phase(path: Path | str, phase: str) -> EncoderMetadata:
    """The model's scans start their columns at ``phase`` (:mod:`overlapmamba.core.views`:
    ``sensor`` or ``aligned``): the graph stays byte for byte; the model id changes with it
    (aligned images give other descriptors, which must not share a map with the others')."""
    try:
        phase = check_column_phase(phase)
    except ValueError as err:
        raise ExportError(str(err)) from None

    def update(meta: EncoderMetadata) -> dict[str, Any]:
        _maps_stay_valid(meta, "column_phase", meta.column_phase, phase)
        ids = identity(meta.graph, meta.views, meta.sensor_input, meta.maps_digest, phase)
        return ids | _calibration_of(meta, meta.column_phase, phase)

    return rewrite_metadata(path, path, update)


def _calibration_of(meta: EncoderMetadata, old: object, new: object) -> dict[str, Any]:
    """The calibration the rewritten file keeps: none where the value changes, since its
    thresholds and re-rank setting were chosen on the old descriptors (the benchmarks choose
    them again for the new file, as for a file recovered with other token views)."""
    return {"calibration": {}} if old != new and meta.calibration else {}


def _maps_stay_valid(meta: EncoderMetadata, field: str, old: object, new: object) -> None:
    """Sensor maps are fitted on the descriptors of one views/sensor_input: another value
    would leave them mapping descriptors they were not fitted on."""
    if meta.sensor_maps and old != new:
        raise ExportError(
            f"the model carries sensor maps fitted with {field} = {old}; with {new} they "
            "would map other descriptors than they were fitted on: write the file without "
            "them first (with_sensor_maps(..., {})), then fit them again"
        )


def with_calibration(path: Path | str, section: str, entry: Calibrated) -> EncoderMetadata:
    """Record ``entry`` as the model's calibrated ``section`` (:mod:`overlapmamba.core.calibration`)
    in the file itself: its other sections, the graph, the weights and the model id stay as
    they are. Atomic. Returns the new metadata."""
    try:
        check_calibration({section: entry})
    except ValueError as err:
        raise ExportError(str(err)) from None
    return rewrite_metadata(
        path, path, lambda meta: {"calibration": {**meta.calibration, section: entry}}
    )


def load_encoder(
    src: Path | str, *, check_maps: bool = True
) -> tuple[onnx.ModelProto, EncoderMetadata]:
    """An exported encoder file and its metadata; :class:`ExportError` naming what is wrong
    when it is missing, not ONNX, or not ours (``check_maps``: :func:`metadata_of`)."""
    src = Path(src)
    if not src.is_file():
        raise ExportError(f"model {src} does not exist")
    try:
        proto = onnx.load(str(src))
    except Exception as err:  # protobuf raises its own classes
        raise ExportError(f"{src} is not an ONNX file ({type(err).__name__}: {err})") from None
    try:
        return proto, metadata_of(proto, check_maps=check_maps)
    except ValueError as err:
        raise ExportError(f"{src}: {err}") from None


def rewrite_metadata(
    src: Path | str,
    out: Path | str,
    update: Callable[[EncoderMetadata], dict[str, Any]],
    *,
    check_maps: bool = True,
) -> EncoderMetadata:
    """``src``'s graph and weights byte for byte into ``out``, its metadata updated by
    ``update(metadata)`` (the fields to change); written atomically. The new metadata is
    checked whole; ``check_maps=False`` reads ``src`` as :func:`load_encoder` does then."""
    src, out = Path(src), Path(out)
    proto, meta = load_encoder(src, check_maps=check_maps)
    try:
        new = EncoderMetadata.model_validate(
            {**meta.model_dump(by_alias=True), **update(meta)}, by_alias=True
        )
    except ValueError as err:  # pydantic's ValidationError: say which field and why
        raise ExportError(f"{src}: the new metadata is invalid: {err}") from None
    save_encoder(proto, new, out)
    return new


def graph_id(proto: onnx.ModelProto) -> str:
    """The graph and weights' content hash, as :func:`overlapmamba.train.export.export_onnx`
    names a graph: taken before the metadata is attached (call it on a proto without any)."""
    return "om-" + hashlib.sha256(proto.SerializeToString(deterministic=True)).hexdigest()[:16]


def save_encoder(proto: onnx.ModelProto, meta: EncoderMetadata, out: Path | str) -> None:
    """``proto`` with ``meta`` as its only metadata, written to ``out`` atomically (a crash
    mid-way leaves no half-written model behind)."""
    out = Path(out)
    del proto.metadata_props[:]
    for key, value in meta.to_props().items():
        proto.metadata_props.add(key=key, value=value)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp{os.getpid()}")
    try:
        onnx.save(proto, tmp)
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
