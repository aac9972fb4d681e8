"""What an exported encoder says about itself: one schema for the writer and the readers.

The export (``overlapmamba.train.export``) writes these fields into the ONNX file's
``metadata_props``; the service reads them back (onnxruntime's ``custom_metadata_map``) and
needs nothing else: the sensor profile gives the projection, ``sensor_input`` how scans of
other sensors enter it (:mod:`overlapmamba.core.sensors.input`), ``views`` how many sub-column
views of it make one descriptor (:mod:`overlapmamba.core.views`; where they meet: the graph's
own ``token_views``, or the reader averaging descriptors), ``descriptor_dim`` sizes the
index, ``model_id`` keeps descriptors of different models out of one map, ``calibration``
holds the thresholds the benchmarks chose for it (:mod:`overlapmamba.core.calibration`),
``sensor_maps`` the maps that move other sensors' descriptors into the model sensor's
(:mod:`overlapmamba.core.sensormaps`; part of the model id).

Every value in ``metadata_props`` is a string; structured fields are JSON. The keys are
namespaced ``overlapmamba.*`` so they never collide with a tool's own.
"""

from __future__ import annotations

import hashlib
import json
import logging
from typing import Any

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from overlapmamba.core.calibration import CALIBRATED, Calibrated, check_calibration
from overlapmamba.core.errors import LidarCoreError
from overlapmamba.core.sensormaps import SensorMap, maps_digest
from overlapmamba.core.sensors import SensorProfile
from overlapmamba.core.sensors.catalogue import sensor_of_profile
from overlapmamba.core.sensors.input import Mode
from overlapmamba.core.views import MAX_VIEWS, check_column_phase

FORMAT = "overlapmamba-encoder"
VERSION = 1
PREFIX = "overlapmamba."
INPUT = "range_image"  # (B, 1, H, W) float32
OUTPUTS = ("descriptor", "yaw_features")  # (B, D) unit norm; (B, C, W)
# The selective scan is one node per block in this domain, defined by a model-local function
# inside the file (portable: runtimes inline it); a runtime with its own kernel may bind the
# node instead. circular → op name. Contract: overlapmamba.train.scan_onnx.
SCAN_DOMAIN = "overlapmamba"
SCAN_OPS = {False: "SelectiveScan", True: "SelectiveScanRing"}


class ModelMetadataError(LidarCoreError, ValueError):
    code = "invalid_model_metadata"


class EncoderMetadata(BaseModel):
    """Everything a consumer of the exported encoder needs, besides the graph."""

    model_config = ConfigDict(frozen=True, extra="forbid", protected_namespaces=())

    format: str = FORMAT
    version: int = VERSION
    model_id: str = Field(
        min_length=1, description="content hash of the graph and weights (and of views > 1)"
    )
    profile: SensorProfile = Field(description="sensor profile: every projection parameter")
    network: dict[str, Any] = Field(alias="model_config", description="the network config")
    descriptor_dim: int = Field(gt=0)
    yaw_channels: int = Field(gt=0)
    views: int = Field(
        default=1,
        ge=1,
        le=MAX_VIEWS,
        description="sub-column views a scan is described by (overlapmamba.core.views); "
        "part of the model id",
    )
    graph_id: str = Field(
        default="",
        description="with views > 1, the content hash of the graph and weights alone (the "
        "model id the same file has with one view); empty otherwise",
    )
    column_phase: str = Field(
        default="sensor",
        description="where a scan's columns start (overlapmamba.core.views): 'sensor' (the "
        "sensor's own azimuth) or 'aligned' (the scan's mean bearing at a column centre: a "
        "turned scan's image is the plain one rolled by whole columns); part of the model id",
    )
    sensor_input: Mode = Field(
        default="elevation",
        description="how a scan of another sensor than the profile's becomes this model's input "
        "(overlapmamba.core.sensors.input): elevation, elevation-lerp (the scan made into the "
        "profile's own beams), elevation-fill (elevation, another sensor's one-column gaps "
        "filled), elevation-reach (elevation-fill, every scan cut at 50 m), rows, common (every"
        " sensor, the profile's own too, thinned to common beams), structure (common, above the"
        " ground and within a common range), bev (a polar bird's-eye occupancy of every scan), "
        "bev-soft (bev, each return shared between its two nearest columns) or bev-span (bev, "
        "each cell how much of its column its returns' spans cover); part of the model id",
    )
    calibration: dict[str, Calibrated] = Field(
        default_factory=dict,
        description="thresholds calibrated for this model by the benchmarks "
        "(overlapmamba.core.calibration); the service takes them unless a setting overrides",
    )
    sensor_maps: dict[str, SensorMap] = Field(
        default_factory=dict,
        description="per sensor, the map of its scans' descriptors into the model sensor's "
        "(overlapmamba.core.sensormaps); part of the model id",
    )
    first_stage: str = Field(
        "descriptor",
        description="what the descriptor output is: 'descriptor' (the network's own) or a "
        "first stage of overlapmamba.core.yaw_spectrum written into the graph "
        "(spectrum:BINS:COMPRESS, mixed:A:BINS:COMPRESS; overlapmamba.train.spectrum_head)",
    )
    reduction: dict[str, Any] = Field(
        default_factory=dict,
        description="empty, or how the descriptor was reduced from its first stage's vector "
        "by a linear map in the graph (overlapmamba.train.reduce_head): from_dim, dim, "
        "variance_kept, fitted_on, source_model_id",
    )
    weights: str = Field(description="'trained' or 'random' (an untrained network)")
    weight_format: str = Field(description="storage of the large matrices: float32 or int8")
    training_data: dict[str, Any] = Field(default_factory=dict, description="data fingerprints")
    metrics: dict[str, Any] = Field(default_factory=dict, description="validation summary")
    source_commit: str = Field(description="git commit of the exporting code ('-dirty' if so)")
    exported_at: str = Field(description="UTC time, ISO 8601")
    torch_version: str = ""
    opset: int = Field(gt=0)

    @field_validator("calibration", mode="before")
    @classmethod
    def _known_calibration(cls, v: Any) -> Any:
        """Sections this code does not know (a newer writer's) are left out with a warning,
        so the model still loads; a known section with unknown fields is refused."""
        if not isinstance(v, dict):
            return v
        unknown = sorted(set(v) - set(CALIBRATED))
        if unknown:
            logging.getLogger("overlapmamba").warning(
                "model calibration: sections %s are not known here and are ignored", unknown
            )
        return check_calibration({k: x for k, x in v.items() if k in CALIBRATED})

    @model_validator(mode="after")
    def _known_phase(self) -> EncoderMetadata:
        check_column_phase(self.column_phase)
        return self

    @property
    def aligned(self) -> bool:
        """Each scan's columns start at its own mean bearing (:mod:`overlapmamba.core.views`)."""
        return self.column_phase == "aligned"

    @model_validator(mode="after")
    def _views_in_graph(self) -> EncoderMetadata:
        if self.graph_views > 1 and self.views != self.graph_views:
            raise ValueError(
                f"the graph averages {self.graph_views} views of a scan itself (token_views); "
                f"views must be {self.graph_views}, got {self.views}"
            )
        return self

    @model_validator(mode="after")
    def _maps_fit_the_model(self, info: ValidationInfo) -> EncoderMetadata:
        # the name the service looks the model's own scans up by: a custom profile's is made
        # a catalogue-like name, and one named as a catalogue sensor but built otherwise is
        # "NAME-model", so that the catalogue's NAME is another sensor, which may have a map.
        # Unchecked where a file is read to have its maps replaced (with_sensor_maps: a file
        # written before this check is repaired, not stuck).
        check = self.sensor_maps and (info.context or {}).get("check_maps", True)
        own = sensor_of_profile(self.profile).name if check else None
        if own in self.sensor_maps:
            raise ValueError(
                f"a sensor map for {own!r}, the model's own sensor: its descriptors are the "
                "space the maps lead into and are never mapped; write the file without it "
                "(overlapmamba.train.modelfile.with_sensor_maps with the other maps)"
            )
        wrong = sorted(k for k, v in self.sensor_maps.items() if v.dim != self.descriptor_dim)
        if wrong:
            raise ValueError(
                f"sensor maps {', '.join(wrong)} are not of the descriptor's dimension "
                f"{self.descriptor_dim}"
            )
        return self

    @property
    def maps_digest(self) -> str:
        """The sensor maps' content hash ('' without maps), as :func:`identity` takes it."""
        return maps_digest(self.sensor_maps) if self.sensor_maps else ""

    @property
    def graph_views(self) -> int:
        """How many of a scan's views the graph itself averages (the network's
        ``token_views``): it then takes that many images a scan, scan-major, and returns one
        descriptor a scan. 1: the graph describes every image and the reader averages the
        views' descriptors (:func:`overlapmamba.core.views.combine_views`)."""
        views = self.network.get("token_views", 1)
        if isinstance(views, bool) or not isinstance(views, int | float) or views != int(views):
            raise ValueError(f"model_config.token_views is {views!r}; allowed: an integer ≥ 1")
        if views < 1:
            raise ValueError(f"model_config.token_views is {views!r}; allowed: an integer ≥ 1")
        return int(views)

    @property
    def descriptors_per_scan(self) -> int:
        """How many descriptors the graph returns for one scan's :attr:`views` images, for
        :func:`overlapmamba.core.views.combine_views`."""
        return self.views // self.graph_views

    @property
    def graph(self) -> str:
        """The content hash of the graph and weights, whatever the views."""
        return self.graph_id or self.model_id

    def to_props(self) -> dict[str, str]:
        """String → string pairs for ``metadata_props``."""
        out = {}
        for key, value in self.model_dump(by_alias=True, mode="json").items():
            out[PREFIX + key] = value if isinstance(value, str) else json.dumps(value)
        return out

    @classmethod
    def from_props(cls, props: dict[str, str], *, check_maps: bool = True) -> EncoderMetadata:
        """The inverse of :meth:`to_props`; a model without our metadata is refused.
        ``check_maps=False``: a sensor map for the model's own sensor is let through, for a
        rewrite that replaces the maps."""
        fields = {k[len(PREFIX) :]: v for k, v in props.items() if k.startswith(PREFIX)}
        if fields.get("format") != FORMAT:
            raise ModelMetadataError(
                f"the model has no '{PREFIX}format={FORMAT}' metadata: export it with "
                "`overlapmamba export CHECKPOINT --out model.onnx`",
                found=sorted(props),
            )
        strings = {"format", "model_id", "graph_id", "weights", "weight_format", "source_commit"}
        strings |= {"exported_at", "torch_version", "sensor_input", "first_stage", "column_phase"}
        try:
            values = {k: v if k in strings else json.loads(v) for k, v in fields.items()}
        except json.JSONDecodeError as err:
            raise ModelMetadataError(f"model metadata is not valid JSON: {err}") from None
        if values.get("version") != VERSION:
            raise ModelMetadataError(
                f"model metadata version {values.get('version')!r} is not supported; "
                f"this code reads {VERSION}",
                version=values.get("version"),
                allowed=[VERSION],
            )
        try:
            return cls.model_validate(values, context={"check_maps": check_maps})
        except ValidationError as err:  # one line: the first problem, where and what
            first = err.errors()[0]
            where = ".".join(str(p) for p in first["loc"]) or "metadata"
            more = f" (and {err.error_count() - 1} more)" if err.error_count() > 1 else ""
            raise ModelMetadataError(
                f"model metadata is incomplete or invalid: {where}: {first['msg']}{more}"
            ) from None


DEFAULT_SENSOR_INPUT: Mode = "elevation"


def identity(
    graph_id: str,
    views: int,
    sensor_input: Mode = DEFAULT_SENSOR_INPUT,
    maps: str = "",
    column_phase: str = "sensor",
) -> dict[str, Any]:
    """The metadata fields that name a graph (its content hash, ``om-…``) described by
    ``views`` views, taking other sensors' scans by ``sensor_input`` and mapping their
    descriptors by sensor maps of content hash ``maps`` ('' for none): ``views``,
    ``sensor_input``, ``model_id`` (the graph's own with one view, the default input and no
    maps, as every file before views had; else a hash of them all, since other views,
    another sensor input or other maps give other descriptors, which must not share a map)
    and ``graph_id`` (kept only when it differs from the model id); ``column_phase`` too
    (aligned columns describe scans differently: another id)."""
    check_column_phase(column_phase)
    named = {"views": views, "sensor_input": sensor_input, "column_phase": column_phase}
    plain = sensor_input == DEFAULT_SENSOR_INPUT and column_phase == "sensor"
    if views == 1 and plain and not maps:
        return {**named, "model_id": graph_id, "graph_id": ""}
    key = f"{graph_id}+views={views}"
    if sensor_input != DEFAULT_SENSOR_INPUT:  # the default keeps the ids made before it
        key += f"+sensor_input={sensor_input}"
    if maps:  # none keeps the ids made before maps
        key += f"+sensor_maps={maps}"
    if column_phase != "sensor":  # the sensor's columns keep the ids made before phases
        key += f"+column_phase={column_phase}"
    model_id = "om-" + hashlib.sha256(key.encode()).hexdigest()[:16]
    return {**named, "model_id": model_id, "graph_id": graph_id}


def check_identity(meta: EncoderMetadata) -> None:
    """Refuse metadata whose ``model_id`` is not the one its identity fields give (views,
    sensor input, sensor maps, column phase, over the graph's id): a file edited by hand,
    its views changed and its id kept, would serve other descriptors into the maps made
    under that id, and nothing would notice."""
    want = identity(meta.graph, meta.views, meta.sensor_input, meta.maps_digest, meta.column_phase)
    if want["model_id"] != meta.model_id:
        raise ModelMetadataError(
            f"model_id {meta.model_id} is not the one its metadata gives ({want['model_id']}, "
            f"from graph {meta.graph}, views {meta.views}, sensor_input {meta.sensor_input}, "
            f"column_phase {meta.column_phase}): the file was changed after it was exported; "
            "write it again with `overlapmamba export`"
        )
