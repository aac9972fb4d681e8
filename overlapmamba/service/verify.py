"""Geometric verification of a place match: is a candidate the place the query was taken
at? Each candidate is registered (:mod:`overlapmamba.service.registration`) and its fit
judged.

:func:`verify_candidates` is the query's stage: it registers each candidate that has
geometry and lies within the descriptor gate, in order until one verifies when
``verify.stop_at_first`` (the default) says so, and judges each result against the calibrated
thresholds (``verify.min_fitness``, ``verify.max_rmse_m``, ``verify.gate_distance``,
``verify.ambiguity_margin``: ``benchmarks/verify_threshold.py``). The last refuses a closure
that a pose turned by a quarter, a half or three quarters fits nearly as well
(:func:`rival_fitness`): a place that looks like another turned.

A turn is registered only when its seed pose could rival (``rival_fitness``'s ``screen``):
GICP pairs nothing beyond its reach, so a seed that leaves fewer points within reach than
would refuse the closure seldom ends with a fit that does. ``benchmarks/verify_ambiguity.py``
counts the turns that ended above their reach and the checks the screen decided otherwise
(almost none on the validation towns); ``benchmarks/ambiguity_cost.py`` times the check both
ways.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from overlapmamba.core import poses
from overlapmamba.service.registration import Prepared, Registration, RegistrationParams, register
from overlapmamba.service.sensors import FieldOfView
from overlapmamba.service.settings import VerifySettings

NO_GEOMETRY = "the keyframe keeps no geometry (inserted as a descriptor, or its map keeps none)"


@dataclass(frozen=True)
class Verdict:
    """One candidate's verification, as an answer carries it."""

    verified: bool | None  # None: not registered (no geometry, or an earlier one verified)
    fitness: float | None
    rmse: float | None
    reason: str | None  # why it is not verified, when it is not
    relative_pose: np.ndarray | None  # (4, 4) T_keyframe←query, when registration ran
    rival_fitness: float | None = None  # the best other turn's fit (verify.ambiguity_margin)
    # the registration's information about the pose, up to a scale (Registration.hessian,
    # .residual): the answer's covariance (overlapmamba.core.posecov), when registration ran
    hessian: np.ndarray | None = field(default=None, compare=False, repr=False)
    residual: float | None = None

    @property
    def ambiguous(self) -> bool:
        """Refused because a turned pose fits nearly as well (:func:`unambiguous`): the only
        refusal that checked a rival."""
        return self.verified is False and self.rival_fitness is not None

    def public(self) -> dict[str, object]:
        return {
            "verified": self.verified,
            "fitness": self.fitness,
            "rmse": self.rmse,
            "reason": self.reason,
            "rival_fitness": self.rival_fitness,
        }


def params_of(v: VerifySettings) -> RegistrationParams:
    """The service's registration, from its settings (``verify.*``)."""
    return RegistrationParams(
        voxel=v.voxel_m,
        radius=v.radius_m,
        max_iterations=v.max_iterations,
        threads=v.threads,
    )


def judge(reg: Registration, v: VerifySettings) -> Verdict:
    if reg.relative_pose is None or reg.fitness is None:
        return Verdict(False, None, None, reg.reason, None)
    reason = None
    if reg.fitness < v.min_fitness:
        reason = f"fitness {reg.fitness:.3f} is below {v.min_fitness}"
    elif reg.rmse is None or reg.rmse > v.max_rmse_m:
        reason = f"rmse {reg.rmse} m is above {v.max_rmse_m}"
    elif v.min_constraint is not None and (reg.constraint or 0.0) < v.min_constraint:
        reason = (
            f"the geometry pins the translation too weakly (constraint {reg.constraint or 0.0:.4f}"
            f" below verify.min_constraint {v.min_constraint}): it slides along one direction"
            " (a corridor, a road cut, a tunnel), so its position is not known"
        )
    return Verdict(
        reason is None,
        reg.fitness,
        reg.rmse,
        reason,
        reg.relative_pose,
        hessian=reg.hessian,
        residual=reg.residual,
    )


# A grid town's crossings look alike turned by a quarter: the other seeds a verified
# candidate is registered from, and how far (degrees) a pose must turn from the verified one
# to be another fit rather than the same one found again
QUARTER_TURNS = (90.0, 180.0, 270.0)
TURN_APART_DEG = 20.0


def turned(
    query: Prepared, geometry: bytes, seed_yaw_deg: float | None, p: RegistrationParams, **kw: Any
) -> Iterator[Registration]:
    """The pair registered again (:func:`register`, with its ``view`` and ``screen`` in
    ``kw``) from the seed yaw turned by each of :data:`QUARTER_TURNS`, one at a time."""
    for turn in QUARTER_TURNS:
        yield register(query, geometry, (seed_yaw_deg or 0.0) + turn, p, **kw)


def rival_of(reg: Registration, pose_yaw_deg: float) -> float | None:
    """A turned registration's fit as a rival of the verified pose of yaw ``pose_yaw_deg``:
    None when it has no pose or its pose turns no more than :data:`TURN_APART_DEG` from the
    verified one's (the same fit found again); no more than its share within reach when it
    has one (:func:`rival_fitness`)."""
    if reg.relative_pose is None or reg.fitness is None:
        return None
    apart = abs((float(poses.yaw_deg(reg.relative_pose)) - pose_yaw_deg + 180) % 360 - 180)
    if apart <= TURN_APART_DEG:
        return None
    return reg.fitness if reg.reach is None else min(reg.fitness, reg.reach)


def rival_fitness(
    query: Prepared,
    geometry: bytes,
    yaw_deg: float | None,
    pose_yaw_deg: float,
    p: RegistrationParams,
    view: FieldOfView | None = None,
    enough: float | None = None,
    screen: float | None = None,
) -> float:
    """The best rival (:func:`rival_of`) among the pair's turned registrations
    (:func:`turned`), 0.0 when none is one; it stops once one reaches ``enough``. A right
    closure fits its place much better than any turned pose fits it; where a place looks
    like another a quarter turn away (a crossing seen by a short-range sensor), a wrong
    closure fits about as well as the turned one (``benchmarks/verify_ambiguity.py``).

    ``screen``: a turn whose seed pose leaves less than this share of the scored points
    within GICP's reach is not registered and counts its seed pose's fit. GICP pairs no
    points farther apart than its reach, so a turn seldom ends with a fitness above that
    share: the service screens at the fit that would refuse, and a turn that cannot rival
    costs a nearest-neighbour search, not a registration. With ``screen`` 0 every turn is
    registered, and since a turn counts no more than its share within reach, the rival then
    decides as the service's does at any margin (what the benchmarks record)."""
    best = 0.0
    for reg in turned(query, geometry, yaw_deg, p, view=view, screen=screen):
        fit = rival_of(reg, pose_yaw_deg)
        if fit is not None:
            best = max(best, fit)
            if enough is not None and best >= enough:
                break
    return best


def unambiguous(verdict: Verdict, rival: float, margin: float) -> Verdict:
    """A verified candidate whose fitness is not at least ``margin`` above ``rival``'s
    (:func:`rival_fitness`) is refused as ambiguous."""
    assert verdict.fitness is not None
    if verdict.fitness - rival >= margin:
        return replace(verdict, rival_fitness=rival)
    reason = (
        f"ambiguous: registered from the seed turned by a quarter, a half or three quarters, "
        f"another pose fits with fitness {rival:.3f}, within verify.ambiguity_margin {margin:g} "
        f"of this one's {verdict.fitness:.3f}"
    )
    return replace(verdict, verified=False, reason=reason, rival_fitness=rival)


def verify_candidates(
    query: Prepared,
    candidates: list[tuple[bytes | None, float | None, float]],
    v: VerifySettings,
    views: list[FieldOfView | None] | None = None,
    screen: bool = True,
) -> list[Verdict]:
    """The prepared query and its candidates (geometry blob or None, the descriptor's
    relative yaw, the descriptor distance) → one verdict per candidate, in order. A
    candidate farther than ``v.gate_distance`` is not registered: on the validation town no
    true loop lay that far, and a robot in new territory then spends nothing on it. With
    ``v.stop_at_first`` none is registered after the first that verifies. With
    ``v.ambiguity_margin`` one that verifies is seeded again from the other quarter turns
    (each registered where its seed could rival) and refused when another pose fits nearly
    as well (:func:`unambiguous`). ``views``: each
    candidate's keyframe sensor's field of view where it is not the query's sensor
    (:class:`FieldOfView`), else None. ``screen``: the check registers only the turns that
    could rival (:func:`rival_fitness`); False registers every turn, the check it stands for
    (``benchmarks/ambiguity_cost.py`` times both)."""
    p = params_of(v)
    out: list[Verdict] = []
    first: int | None = None  # the first verified candidate, 1-based
    views = views or [None] * len(candidates)
    for (blob, yaw_deg, distance), view in zip(candidates, views, strict=True):
        if v.stop_at_first and first is not None:
            reason = f"not registered: candidate {first} verified first (verify.stop_at_first)"
            out.append(Verdict(None, None, None, reason, None))
        elif blob is None:
            out.append(Verdict(None, None, None, NO_GEOMETRY, None))
        elif v.gate_distance is not None and distance > v.gate_distance:
            reason = (
                f"descriptor distance {distance:.3f} is above verify.gate_distance "
                f"{v.gate_distance}: not registered"
            )
            out.append(Verdict(False, None, None, reason, None))
        else:
            reg = register(query, blob, yaw_deg, p, view)
            verdict = judge(reg, v)
            margin = v.ambiguity_margin
            if verdict.verified and margin is not None:
                assert verdict.fitness is not None and reg.relative_pose is not None
                own = float(poses.yaw_deg(reg.relative_pose))
                enough = verdict.fitness - margin + 1e-9  # a rival this good already refuses
                rival = rival_fitness(
                    query, blob, yaw_deg, own, p, view, enough, enough if screen else None
                )
                verdict = unambiguous(verdict, rival, margin)
            out.append(verdict)
            if first is None and out[-1].verified:
                first = len(out)
    return out
