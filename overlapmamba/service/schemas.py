"""Request and response models of the HTTP API: the routes' shapes, used by nothing below
the routes (the use cases answer in :mod:`overlapmamba.service.answers` and
:mod:`overlapmamba.service.domain` types)."""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from overlapmamba.service.domain import POSE_FORMAT
from overlapmamba.service.settings import IndexKind

# No ":" in names: observe keyframes are named robot:session:timestamp, which stays unique
# and within the 256 characters of a keyframe id.
NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.@-]{0,99}$"
# "+": observe's ids robot:session:timestamp write a large timestamp as 1.7e+18
KEYFRAME_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.:@+-]{0,255}$"
SENSOR_PATTERN = r"^[a-z0-9][a-z0-9._-]{0,63}$"  # overlapmamba.core.sensors.catalogue.NAME_PATTERN


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Timings(BaseModel):
    """Milliseconds per stage of this request, as the server measured them."""

    decode: float | None = Field(None, description="decompress and parse the scan (or JSON)")
    project: float | None = Field(None, description="the model's range projection")
    encode: float | None = Field(None, description="waiting for a micro-batch, then the encoder")
    search: float | None = Field(None, description="the map search, filters and yaw")
    verify: float | None = Field(
        None, description="registering the top candidates against their keyframes' geometry"
    )
    total: float | None = Field(
        None, description="from the request body in hand to the answer (not the network)"
    )


class DescriptorOut(BaseModel):
    descriptor: list[float] = Field(description="unit-norm descriptor")
    model_id: str
    timings_ms: Timings

    model_config = ConfigDict(
        protected_namespaces=(),
        json_schema_extra={
            "examples": [
                {
                    "descriptor": [0.0625] * 4 + ["…256 values"],
                    "model_id": "om-18fea85287536f08",
                    "timings_ms": {"decode": 0.4, "project": 6.1, "encode": 92.0},
                }
            ]
        },
    )


class DescriptorBatchOut(BaseModel):
    model_config = ConfigDict(protected_namespaces=())
    descriptors: list[list[float]]
    model_id: str
    timings_ms: list[Timings]


class MapSettingsIn(_Model):
    index: IndexKind | None = Field(
        None, description="'flat' (exact), 'ivf' (approximate) or 'auto' (flat until large)"
    )
    keep_geometry: bool | None = Field(
        None,
        description="keyframes inserted from scans keep a compact copy of their geometry "
        "(≈ 7 KB) so that queries can verify them and return a relative pose; default true. "
        "false: a descriptor-only map (≈ 1 KB per keyframe), matches carry verified: null",
    )
    sensor: str | None = Field(
        None,
        pattern=SENSOR_PATTERN,
        description="the sensor of the scans sent to this map that name none (GET "
        "/v1/sensors lists them); default: the model's own. Scans of other sensors say so "
        "with their `sensor` parameter: a map holds keyframes of any sensor",
    )
    mount: str | None = Field(
        None,
        max_length=64,
        description="where the sensor of scans sent to this map that name no `mount` sits: "
        "HEIGHT[,PITCH[,ROLL]] (m above the ground, degrees; pitch + looks down ahead, roll + "
        "raises the left side), as the scan routes' `mount` parameter takes it; default: "
        "none, scans taken as the model's own mount (1.73 m, level)",
    )

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {"index": "auto", "keep_geometry": True, "sensor": "os1-64"},
                {"sensor": "os0-128", "mount": "0.35"},
            ]
        },
    )


class MapOut(BaseModel):
    model_config = ConfigDict(protected_namespaces=())
    map_id: str
    model_id: str
    backend: str = Field("faiss", description="faiss (embedded) or qdrant")
    index: dict[str, Any]
    keyframes: int
    keep_geometry: bool = Field(True, description="keyframes from scans keep their geometry")
    sensor: str | None = Field(
        None, description="the sensor of scans that name none; null: the model's own"
    )
    mount: dict[str, float] | None = Field(
        None,
        description="where the sensor of scans that name no mount sits (height, pitch_deg, "
        "roll_deg); null: none declared",
    )
    seq: int | None = Field(None, description="faiss: the store's last write sequence number")
    snapshot_seq: int | None = Field(None, description="faiss: the seq the snapshot holds")
    created_at: float
    created: bool | None = None


class MapList(BaseModel):
    maps: list[MapOut]


class KeyframeOut(BaseModel):
    keyframe_id: str
    robot_id: str
    session_id: str
    timestamp: float
    pose: list[float] | None
    sensor: str | None = Field(
        None,
        description="the sensor of the scan it came from (a catalogue name: GET /v1/sensors); "
        "null: not recorded (a precomputed descriptor that named none, or a keyframe older "
        "than sensors)",
    )
    created: bool | None = Field(
        None, description="false when this keyframe id was already stored with this content"
    )


def _finite(values: list[float], what: str) -> list[float]:
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"{what} has NaN or infinite values; allowed: finite numbers")
    return values


class KeyframeIn(_Model):
    keyframe_id: str = Field(pattern=KEYFRAME_ID_PATTERN)
    robot_id: str = Field("unknown", pattern=NAME_PATTERN)
    session_id: str = Field("default", pattern=NAME_PATTERN)
    timestamp: float = Field(allow_inf_nan=False)
    pose: list[float] | None = Field(None, min_length=7, max_length=7, description=POSE_FORMAT)
    descriptor: list[float] = Field(description="the model's descriptor (unit norm)")
    yaw_features: list[list[float]] | None = Field(
        None, description="(C, W) yaw features; without them matches carry no yaw"
    )
    sensor: str | None = Field(
        None,
        pattern=SENSOR_PATTERN,
        description="the sensor of the scan the descriptor came from, recorded with it "
        "(a known name: GET /v1/sensors)",
    )

    @field_validator("descriptor")
    @classmethod
    def _desc(cls, v: list[float]) -> list[float]:
        return _finite(v, "descriptor")

    @field_validator("pose")
    @classmethod
    def _pose(cls, v: list[float] | None) -> list[float] | None:
        return None if v is None else _finite(v, "pose")


class KeyframeBatchIn(_Model):
    model_id: str = Field(description="the model that computed the descriptors; must match")
    keyframes: list[KeyframeIn] = Field(min_length=1)

    model_config = ConfigDict(
        extra="forbid",
        protected_namespaces=(),
        json_schema_extra={
            "examples": [
                {
                    "model_id": "om-18fea85287536f08",
                    "keyframes": [
                        {
                            "keyframe_id": "drive1-000042",
                            "robot_id": "mapper-1",
                            "session_id": "drive1",
                            "timestamp": 1700000042.5,
                            "pose": [12.0, -3.5, 0.0, 0.0, 0.0, 0.0, 1.0],
                            "descriptor": [0.0625, "…256 values"],
                        }
                    ],
                }
            ]
        },
    )


class KeyframeBatchOut(BaseModel):
    inserted: int
    existing: int
    keyframes: list[KeyframeOut]


class DescriptorQueryIn(_Model):
    descriptor: list[float]

    @field_validator("descriptor")
    @classmethod
    def _desc(cls, v: list[float]) -> list[float]:
        return _finite(v, "descriptor")


class MatchOut(BaseModel):
    keyframe_id: str
    distance: float = Field(description="L2 distance between unit descriptors, in [0, 2]")
    similarity: float = Field(description="cosine similarity, in [-1, 1]")
    robot_id: str
    session_id: str
    timestamp: float
    pose: list[float] | None
    sensor: str | None = Field(
        None,
        description="the sensor of the scan it came from (a catalogue name: GET /v1/sensors); "
        "null: not recorded (a precomputed descriptor that named none, or a keyframe older "
        "than sensors)",
    )
    yaw_deg: float | None = Field(
        description="yaw of the match's sensor frame in the query's, degrees (−180, 180]"
    )
    yaw_confidence: float | None = Field(description="feature correlation at that yaw, [-1, 1]")
    score: float | None = Field(
        None,
        description="the re-ranking score distance² − rerank.weight · yaw_confidence (lower "
        "is better) by which the first rerank.shortlist matches are ordered; null when the answer "
        "is in descriptor order (a descriptor query, a keyframe without yaw features, "
        "rerank off, or beyond the first rerank.shortlist)",
    )
    relative_pose: list[float] | None = Field(
        None,
        description="4×4 row-major T_keyframe←query from registration (maps points of the "
        "query scan into the keyframe's sensor frame); null when not registered",
    )
    verification: VerificationOut | None = Field(
        None,
        description="null when not verified (verify=false, a descriptor query, or "
        "beyond the first verify.candidates)",
    )


class VerificationOut(BaseModel):
    verified: bool | None = Field(
        description="registration passed the calibrated thresholds; null: not registered, "
        "because the keyframe keeps no geometry (inserted as a descriptor, or its map keeps "
        "none) or an earlier candidate verified first (verify.stop_at_first); reason says which"
    )
    fitness: float | None = Field(
        description="share of the query's grid points within verify.radius_m (1 m) of the "
        "keyframe's geometry after alignment, [0, 1]"
    )
    rmse: float | None = Field(description="rmse of those points' distances, metres")
    reason: str | None = Field(description="why it is not verified, when it is not")
    rival_fitness: float | None = Field(
        None,
        description="the best fitness of the same pair registered from the seed yaw turned "
        "by 90°, 180° and 270° (poses more than 20° from this one's); verified needs fitness "
        "at least verify.ambiguity_margin above it. null: not checked (the candidate did not "
        "pass the thresholds, or the margin is off); on a refusal it may stop at the first "
        "turn that fits well enough",
    )


class LoopClosureOut(BaseModel):
    accepted: bool
    threshold: float = Field(
        description="an unverified call's threshold: loop_closure.max_score on the top-1's "
        "score (a re-ranked answer) or loop_closure.accept_distance on its distance (see rule)"
    )
    rule: Literal["score", "distance"] = Field(
        "distance", description="what threshold and margin_top1_top2 compare"
    )
    margin_top1_top2: float | None
    keyframe_id: str | None = Field(None, description="the revisited keyframe, when accepted")
    verified: bool | None = Field(
        None,
        description="true: accepted after registration; false: candidates were judged "
        "(registered, or beyond the descriptor gate verify.gate_distance) and none passed; "
        "null: the call is the descriptor distance alone",
    )
    relative_pose: list[float] | None = Field(
        None, description="4×4 row-major T_keyframe←query of the accepted, verified closure"
    )
    fitness: float | None = None
    covariance: list[float] | None = Field(
        None,
        min_length=36,
        max_length=36,
        description="6×6 row-major covariance of relative_pose: its error δ = (x, y, z, rx, "
        "ry, rz), metres then the rotation vector in radians, with T_true = relative_pose · "
        "Exp(δ) (on the right, in the query's frame; GTSAM's Pose3 orders rotation first, "
        "g2o's EDGE_SE3:QUAT takes half the rotation: docs/service.md). From the "
        "registration's information scaled as the model's calibration says (covariance.*); "
        "null: not verified, no covariance calibration, or a direction the registration "
        "left unconstrained",
    )


class QueryOut(BaseModel):
    matches: list[MatchOut]
    loop_closure: LoopClosureOut
    timings_ms: Timings

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "matches": [
                        {
                            "keyframe_id": "drive1-000042",
                            "distance": 0.21,
                            "similarity": 0.978,
                            "robot_id": "mapper-1",
                            "session_id": "drive1",
                            "timestamp": 1700000042.5,
                            "pose": [12.0, -3.5, 0.0, 0.0, 0.0, 0.0, 1.0],
                            "yaw_deg": 178.6,
                            "yaw_confidence": 0.83,
                            "score": -0.1219,
                            "relative_pose": [
                                *(-0.9996, -0.0244, 0.0011, 1.32),
                                *(0.0244, -0.9996, 0.0006, -0.41),
                                *(0.0011, 0.0006, 1.0, 0.02),
                                *(0.0, 0.0, 0.0, 1.0),
                            ],
                            "verification": {
                                "verified": True,
                                "fitness": 0.87,
                                "rmse": 0.31,
                                "reason": None,
                            },
                        }
                    ],
                    "loop_closure": {
                        "accepted": True,
                        "threshold": -0.0461,
                        "rule": "score",
                        "margin_top1_top2": 0.12,
                        "keyframe_id": "drive1-000042",
                        "verified": True,
                        "relative_pose": [
                            *(-0.9996, -0.0244, 0.0011, 1.32),
                            *(0.0244, -0.9996, 0.0006, -0.41),
                            *(0.0011, 0.0006, 1.0, 0.02),
                            *(0.0, 0.0, 0.0, 1.0),
                        ],
                        "fitness": 0.87,
                    },
                    "timings_ms": {
                        "decode": 0.3,
                        "project": 1.9,
                        "encode": 21.0,
                        "search": 0.6,
                        "verify": 19.5,
                    },
                }
            ]
        }
    )


class ObserveOut(QueryOut):
    inserted: bool
    keyframe_id: str | None = Field(
        description="the keyframe this scan became: inserted now, or already (a retry: "
        "insert_reason existing)"
    )
    insert_reason: Literal[
        "first", "distance", "time", "always", "never", "not_due", "existing"
    ] = Field(
        description="why it was inserted (first, distance, time, always), or why not: never, "
        "not_due, existing (its keyframe robot:session:timestamp is already in the map: a "
        "retry whose first answer was lost; keyframe_id names it)"
    )


class SensorOut(BaseModel):
    name: str
    title: str
    beams: int
    elevations_deg: list[float] = Field(description="one per beam, highest first")
    columns: int = Field(description="firings per turn")
    min_range: float
    max_range: float
    source: str = Field(description="the manual its figures come from")
    projection: str = Field(
        description="how its scans enter this model: native (the model's own sensor), "
        "elevation (each row the beam nearest its elevation; rows it has no beam for stay "
        "empty) or rows (its beams stretched over the rows)"
    )
    descriptor_map: str | None = Field(
        None,
        description="how this model file maps its scans' descriptors into the model "
        "sensor's (shift or linear: overlapmamba.core.sensormaps); none: used as the network "
        "gives them",
    )


class SensorList(BaseModel):
    model_sensor: str = Field(description="the sensor of scans and maps that name none")
    sensors: list[SensorOut]


class SnapshotOut(BaseModel):
    backend: str = "faiss"
    bytes: int | None = Field(None, description="the snapshot's size")
    seq: int | None = Field(None, description="faiss: the store seq the snapshot holds")
    purged_tombstones: int | None = Field(None, description="faiss: deletes now compacted")
    name: str | None = Field(None, description="qdrant: the collection snapshot's name")


class Health(BaseModel):
    status: str
    detail: dict[str, Any] = Field(default_factory=dict)
