"""A query's loop closure as the service calls it, from every candidate's registration recorded
once (``verify_threshold.run_town``): each benchmark sweeps or applies thresholds to the same
record without registering again.

A candidate (:func:`candidate`) is the keyframe, its descriptor distance, whether the town's
ground truth calls it a loop, the registration's fitness and rmse, its pose's errors against
the truth, the seed and pose yaws, and what its covariance is computed from (the pose's
error δ, GICP's Hessian and residual: ``benchmarks/pose_covariance.py`` scores it).
:func:`closure` and :func:`score` apply ``verify.min_fitness``, ``verify.max_rmse_m``,
``verify.gate_distance``, ``verify.stop_at_first`` and ``verify.ambiguity_margin``; the last
needs each passing candidate's rival fit (``rival``:
``verify_threshold.run_town(rivals_from=)``, or the service's verdict when it registered with
the margin on).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from overlapmamba.core import posecov
from overlapmamba.core.poses import POSE_RIGHT, pose_error, yaw_deg
from overlapmamba.service.registration import Prepared, Registration, RegistrationParams
from overlapmamba.service.sensors import FieldOfView
from overlapmamba.service.verify import rival_of, turned


def candidate(
    j: int, distance: float, loop: bool, verdict: Any, pose_kf: np.ndarray, pose_q: np.ndarray
) -> dict[str, Any]:
    """One registered candidate as :func:`score` reads it: keyframe ``j``, its descriptor
    distance, whether it is a true loop, fitness, rmse, and its pose's errors against the
    truth T = P_keyframe⁻¹ · P_query; with them ``delta`` (the error as
    ``overlapmamba.core.posecov.error`` writes it), ``hessian`` and ``residual``, what the
    answer's covariance is computed from."""
    c: dict[str, Any] = {
        "keyframe": int(j),
        "distance": distance,
        "loop": bool(loop),
        "fitness": verdict.fitness,
        "rmse": verdict.rmse,
    }
    if verdict.rival_fitness is not None:  # registered with verify.ambiguity_margin on
        c["rival"] = verdict.rival_fitness
    if verdict.relative_pose is not None:
        truth = np.linalg.inv(pose_kf) @ pose_q
        c["t_err"], c["yaw_err"] = pose_error(verdict.relative_pose, truth)
        c["pose_yaw_deg"] = float(yaw_deg(verdict.relative_pose))
        c["delta"] = posecov.error(verdict.relative_pose, truth)
        c["hessian"], c["residual"] = verdict.hessian, verdict.residual
    return c


def rivals_of(regs: list[Registration], verdict: Any) -> dict[str, Any]:
    """A candidate's rival as ``closure_kit`` scores it: every turn registered (``screen``
    0), so the best rival (``rival_of``) decides at any margin as the service's screened
    check does; and each turn's ``reach``, fitness and whether it counts as a rival
    (``verify_ambiguity.py`` counts the turns that ended with a fitness above their reach,
    and the decisions registering every turn would change). ``regs``: the candidate's
    ``overlapmamba.service.verify.turned`` registrations, every turn (``screen`` 0)."""
    own = float(yaw_deg(verdict.relative_pose))
    rivals = [(r, rival_of(r, own)) for r in regs if r.fitness is not None]
    fits = [f for _, f in rivals if f is not None]
    turns = [(r.reach, r.fitness, f is not None) for r, f in rivals]
    return {"rival": max(fits, default=0.0), "turns": turns}


def recorded_rival(
    query: Prepared,
    blob: bytes | None,
    seed_deg: float,
    verdict: Any,
    p: RegistrationParams,
    rivals_from: float | None,
    view: FieldOfView | None = None,
) -> dict[str, Any]:
    """:func:`rivals_of` for a candidate whose fitness reaches ``rivals_from`` (the pair
    registered again from the other quarter turns, every turn), else nothing: what a
    benchmark adds to the candidate's record."""
    if (
        rivals_from is None
        or blob is None
        or verdict.fitness is None
        or verdict.fitness < rivals_from
        or verdict.relative_pose is None
    ):
        return {}
    return rivals_of(list(turned(query, blob, seed_deg, p, view=view, screen=0.0)), verdict)


def passes(c: dict[str, Any], min_fitness: float, max_rmse: float) -> bool:
    return (
        c["fitness"] is not None
        and c["fitness"] >= min_fitness
        and c["rmse"] is not None
        and c["rmse"] <= max_rmse
    )


def closure(
    q: dict[str, Any],
    min_fitness: float,
    max_rmse: float,
    gate_distance: float | None = None,
    stop_at_first: bool = False,
    margin: float | None = None,
) -> tuple[dict[str, Any] | None, int]:
    """One query's closure as the service calls it at these thresholds (see :func:`score`):
    the accepted candidate or None, and how many candidates were registered. ``margin``
    (``verify.ambiguity_margin``): a passing candidate must also fit at least this much
    better than its rival (its recorded ``rival``)."""
    gated = [c for c in q["candidates"] if gate_distance is None or c["distance"] <= gate_distance]
    ok = [
        c
        for c in gated
        if passes(c, min_fitness, max_rmse)
        and (margin is None or c["fitness"] - _rival(c) >= margin)
    ]
    registered = gated.index(ok[0]) + 1 if stop_at_first and ok else len(gated)
    if not ok:
        return None, registered
    return (ok[0] if stop_at_first else max(ok, key=lambda c: c["fitness"])), registered


def score(
    queries: list[dict[str, Any]],
    min_fitness: float,
    max_rmse: float,
    gate_distance: float | None = None,
    stop_at_first: bool = False,
    margin: float | None = None,
) -> dict[str, Any]:
    """The service's call at these thresholds, over every query (a candidate beyond
    ``gate_distance`` is not registered, as in the service): the verified candidate of
    highest fitness, or with ``stop_at_first`` (``verify.stop_at_first``) the first verified
    in the answer's order, none registered after it."""
    accepted = correct = on_loop = found = registered = 0
    t_err, yaw_err = [], []
    for q in queries:
        best, n = closure(q, min_fitness, max_rmse, gate_distance, stop_at_first, margin)
        registered += n
        if best is None:
            continue
        accepted += 1
        right = best["t_err"] <= POSE_RIGHT[0] and best["yaw_err"] <= POSE_RIGHT[1]
        correct += right
        on_loop += best["loop"]
        found += right and best["loop"]
        if best["loop"]:
            t_err.append(best["t_err"])
            yaw_err.append(best["yaw_err"])
    loops = sum(q["has_loop"] for q in queries)
    out: dict[str, Any] = {
        "min_fitness": min_fitness,
        "max_rmse_m": max_rmse,
        "gate_distance": gate_distance,
        "ambiguity_margin": margin,
        "registered_per_query": registered / len(queries) if queries else 0.0,
        "accepted": accepted,
        "correct": correct,
        "precision": correct / accepted if accepted else 1.0,
        "precision_ground_truth_loops": on_loop / accepted if accepted else 1.0,
        "recall": found / loops if loops else 0.0,
    }
    if t_err:
        out["translation_error_m"] = {
            "median": float(np.median(t_err)),
            "p90": float(np.percentile(t_err, 90)),
        }
        out["yaw_error_deg"] = {
            "median": float(np.median(yaw_err)),
            "p90": float(np.percentile(yaw_err, 90)),
        }
    return out


def descriptor_recall(queries: list[dict[str, Any]]) -> dict[str, float]:
    loops = [q for q in queries if q["has_loop"]]
    at = {}
    for n in (1, 5):
        hit = sum(any(c["loop"] for c in q["candidates"][:n]) for q in loops)
        at[f"recall@{n}"] = hit / len(loops) if loops else 0.0
    return at


def _rival(c: dict[str, Any]) -> float:
    if "rival" not in c:
        raise KeyError(
            f"candidate keyframe {c['keyframe']} passed the thresholds but has no rival fit: "
            "register rivals from a fitness no higher than the one scored (run_town's rivals_from)"
        )
    return float(c["rival"])
