"""The settings of a recognition answer that a model file may calibrate: when a loop closure
is accepted (``loop_closure``), how the shortlist is re-ranked (``rerank``) and how candidates
are verified by registration (``verify``); and the base every settings section shares.

Their defaults are the shipped model's, each with the command that chose it; a model file
that carries its own calibration replaces them, and a value an operator sets replaces that
(overlapmamba.service.calibration). The tree they belong to: overlapmamba.service.settings.
"""

from __future__ import annotations

from typing import Any, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from overlapmamba.core.renamed import RENAMED, renamed
from overlapmamba.core.rerank import Rerank


class Section(BaseModel):
    # inf is a TOML literal (and an env value): a bound of inf would reach /readyz's JSON,
    # which cannot hold it, and timeouts that are cast to integers; refused at start-up
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class RenamedSection(Section):
    """A section with fields renamed (overlapmamba.core.renamed): old names still accepted,
    with a warning, until they go."""

    _where: ClassVar[str]

    @model_validator(mode="before")
    @classmethod
    def _old_names(cls, data: Any) -> Any:
        if isinstance(data, dict) and set(data) & set(RENAMED[cls._where]):
            return renamed(data, cls._where, stacklevel=4)
        return data


class LoopClosureSettings(RenamedSection):
    _where = "loop_closure"

    # Calibrated for the shipped model on the validation town (benchmarks/loop_threshold.py):
    # the L2 distance at F1max, where precision is 0.83 and recall 0.88. Recalibrate for
    # another model. It decides only unverified answers (verify=false, descriptor queries,
    # keyframes without geometry); verification decides the others (VerifySettings).
    accept_distance: float = Field(
        0.1794,
        gt=0,
        le=2,
        description="accept a loop closure when the top-1 descriptor L2 distance is below",
    )
    # The same point for a re-ranked answer (RerankSettings): the top-1's score at F1max on
    # the validation town (benchmarks/loop_threshold.py, the keyframes' yaw features in
    # float16 as maps store them), where precision is 0.93 and recall 0.87.
    max_score: float = Field(
        -0.0461,
        ge=-10,  # a score is d² − weight · c: d² in [0, 4], weight ≤ 10, c in [−1, 1]
        le=14,
        description="accept a loop closure when the re-ranked top-1's score is at most this "
        "(when the answer was re-ranked; else accept_distance decides)",
    )
    min_margin: float = Field(
        0.0,
        ge=0,
        description="and the top-2 distance (score, when re-ranked) exceeds the top-1's by at "
        "least this",
    )


class RerankSettings(RenamedSection):
    _where = "rerank"

    # Chosen on the validation town and its second session (benchmarks/rerank.py): the
    # mean of F1max and Recall@1 on the three subsets and AR@1 across sessions. The
    # defaults are overlapmamba.core.rerank.Rerank's, which evaluation uses too.
    shortlist: int = Field(
        Rerank().shortlist,
        ge=1,
        le=200,
        description="scan queries: re-rank this many nearest descriptors by d² − weight · "
        "aligned yaw-feature correlation (1: descriptor order only). A long shortlist wants "
        "index.row_cache_mb to hold each busy robot's: about robots × shortlist × 115 kB",
    )
    weight: float = Field(
        Rerank().weight, ge=0, le=10, description="the correlation's weight in the score (0: off)"
    )
    score: Literal["stage", "network"] = Field(
        "stage",
        description="what the score's d² is measured between: 'stage', the vectors the "
        "shortlist was ranked by; 'network', the network's own descriptor inside a mixed first "
        "stage (the model's first_stage mixed:…; overlapmamba.core.yaw_spectrum.score_part)",
    )


class VerifySettings(RenamedSection):
    _where = "verify"

    # Calibrated for the shipped model on the validation town (benchmarks/verify_threshold.py
    # --calibrate), registering the first k of the two-stage order (RerankSettings): the
    # strictest thresholds at the highest recall with every accepted closure's pose right
    # (≤ 1 m, 2°): fitness 0.56, rmse 0.7 m (recall 0.883; any fitness from 0.32 to 0.56,
    # with or without the rmse bound, gives the same). The descriptor gate: the nearest that
    # costs at most 0.005 of recall, 0.29 (3.6 registrations a query, not 5, registering every
    # candidate; 2.0 stopping at the first verified, stop_at_first). Recalibrated
    # for the model's three sub-column views (one view: fitness 0.54, gate 0.30).
    # In descriptor order, with one view, the same procedure gave 0.46, no rmse bound and
    # 0.29 (recall 0.876).
    candidates: int = Field(
        5,
        ge=0,
        le=50,
        description="scan queries: register up to this many top candidates against their "
        "keyframe's geometry, in order until one verifies (stop_at_first) (0: never; a "
        "request's verify=false skips it too)",
    )
    min_fitness: float = Field(
        0.56,
        ge=0,
        le=1,
        description="verified: at least this share of the query's steep grid points lies "
        "within radius_m of the keyframe's geometry after alignment",
    )
    max_rmse_m: float = Field(0.7, gt=0, description="verified: and their rmse is at most")
    gate_distance: float | None = Field(
        0.29,
        gt=0,
        le=2,
        description="candidates with a descriptor L2 distance above this are not registered "
        "(verified: false, with the reason); null: every candidate is",
    )
    stop_at_first: bool = Field(
        True,
        description="stop registering a query's candidates once one verifies: the later ones "
        "answer verified: null with the reason, and the loop closure is that first verified "
        "candidate (chosen on val: as many closures, all right, with fewer registrations a "
        "query); "
        "false: register every candidate and close on the best-fitting verified one",
    )
    ambiguity_margin: float | None = Field(
        None,
        ge=0,
        le=1,
        description="a candidate that verifies is seeded again from its seed yaw turned by "
        "90°, 180° and 270° (registered where the seed could rival); if a pose more than 20° "
        "from its own fits within this much of its fitness, it is refused as ambiguous (a "
        'place that looks like another turned by a quarter: a crossing). null or "off": not '
        "checked (a model file calibrated without it, or an operator who spends no more "
        "registrations on it)",
    )
    radius_m: float = Field(1.0, gt=0, le=5, description="the fitness radius")
    min_constraint: float | None = Field(
        None,
        ge=0,
        le=1,
        description="verified: and the geometry pins the translation in every direction, "
        "the smallest over the largest eigenvalue of the translation block of GICP's final "
        "Hessian at least this (a corridor, a road cut or a tunnel slides along itself at "
        "full fitness: docs/service.md). null: not checked",
    )

    @field_validator("ambiguity_margin", mode="before")
    @classmethod
    def _margin_off(cls, value: Any) -> Any:
        """``"off"`` (or ``"null"``, ``"none"``): the check off, where null cannot be written
        (TOML, an ``OVERLAPMAMBA_VERIFY__AMBIGUITY_MARGIN`` variable)."""
        if isinstance(value, str) and value.strip().lower() in ("off", "null", "none"):
            return None
        return value

    voxel_m: float = Field(
        2.0,
        ge=0.5,
        le=5,
        description="grid of the geometry kept per keyframe and of the query's registration",
    )
    max_iterations: int = Field(30, ge=1, le=200, description="GICP stops here (bounded time)")
    threads: int = Field(
        1,
        ge=1,
        le=64,
        description="GICP's threads a registration (OpenMP). 1: under load the other cores "
        "are encoding, and a registration on more threads waits for them (docs/deploy.md, sizing)",
    )
    processes: int = Field(
        1,
        ge=0,
        le=64,
        description="registration (preparing queries, packing keyframe geometry, GICP) in this "
        "many child processes; 0: in the server's own threads, where small_gicp holds "
        "Python's lock for each call and every other request's Python waits (docs/deploy.md, "
        "sizing)",
    )


class CovarianceSettings(Section):
    """The covariance a verified closure's relative pose carries (overlapmamba.core.posecov):
    ``scale`` · A⁻¹, A the registration's information under ``estimator``. Both null: closures
    carry no covariance (a model file not calibrated for it; the defaults are null because
    the scale is the registration's on a model's own loops, which
    ``benchmarks/pose_covariance.py --calibrate --write-calibration`` measures on the
    validation town)."""

    estimator: Literal["hessian", "residual"] | None = Field(
        None,
        description="hessian: A is GICP's final Hessian; residual: the Hessian over the "
        "registration's cost per inlier pair; null: no covariance",
    )
    scale: float | None = Field(
        None,
        gt=0,
        le=1e6,
        description="Σ = scale · A⁻¹ (chosen so that 95% of the validation town's right "
        "closures lie inside their 95% ellipsoid); null: no covariance",
    )

    @model_validator(mode="after")
    def _both_or_neither(self) -> CovarianceSettings:
        if (self.estimator is None) != (self.scale is None):
            raise ValueError(
                "covariance.estimator and covariance.scale go together: set both (a "
                "calibration of benchmarks/pose_covariance.py) or neither (no covariance); got "
                f"estimator {self.estimator!r}, scale {self.scale!r}"
            )
        return self
