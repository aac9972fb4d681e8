"""A query's loop closure as the service calls it, from every candidate's registration recorded
once (``verify_threshold.run_town``): each benchmark sweeps or applies thresholds to the same
record without registering again.

A candidate (:func:`candidate`) is the keyframe, its descriptor distance, whether the town's
ground truth calls it a loop, the registration's fitness and rmse, its pose's errors against
the truth, and the seed and pose yaws. :func:`closure` and :func:`score` apply
``verify.min_fitness``, ``verify.max_rmse_m``, ``verify.gate_distance``,
``verify.stop_at_first`` and ``verify.ambiguity_margin``; the last needs each passing
candidate's rival fit, which :func:`add_rivals` registers (the service's
``overlapmamba.service.verify.rival_fitness``).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from overlapmamba.core.poses import POSE_RIGHT, pose_error, yaw_deg
from overlapmamba.service.verify import RegistrationParams, rival_fitness


def candidate(
    j: int, distance: float, loop: bool, verdict: Any, pose_kf: np.ndarray, pose_q: np.ndarray
) -> dict[str, Any]:
    """One registered candidate as :func:`score` reads it: keyframe ``j``, its descriptor
    distance, whether it is a true loop, fitness, rmse, and its pose's errors against the
    truth T = P_keyframe⁻¹ · P_query."""
    c: dict[str, Any] = {
        "keyframe": int(j),
        "distance": distance,
        "loop": bool(loop),
        "fitness": verdict.fitness,
        "rmse": verdict.rmse,
    }
    if verdict.relative_pose is not None:
        truth = np.linalg.inv(pose_kf) @ pose_q
        c["t_err"], c["yaw_err"] = pose_error(verdict.relative_pose, truth)
        c["pose_yaw_deg"] = float(yaw_deg(verdict.relative_pose))
    return c


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
    better than its rival (``add_rivals`` recorded it)."""
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
            "run add_rivals at thresholds no stricter than the ones scored"
        )
    return float(c["rival"])


def add_rivals(
    r: dict[str, Any],
    params: RegistrationParams,
    min_fitness: float,
    max_rmse: float,
    gate_distance: float | None = None,
) -> list[float]:
    """Each candidate of a town (``run_town(..., keep=True)``) that passes these thresholds
    gets ``rival``: the best fit of the pair registered from its seed turned by a quarter, a
    half and three quarters (``rival_fitness``, every turn, as the service registers an
    accepted candidate). Returns the time each query spent on it, in ms."""
    ms = []
    for q in tqdm(r["queries"], desc=f"rivals {Path(r['town']).name}", unit="query"):
        t0 = time.perf_counter()
        for c in q["candidates"]:
            if gate_distance is not None and c["distance"] > gate_distance:
                continue
            if "rival" in c or not passes(c, min_fitness, max_rmse):
                continue
            c["rival"] = rival_fitness(
                r["prepared"][q["query"]],
                r["blobs"][c["keyframe"]],
                c["seed_deg"],
                c["pose_yaw_deg"],
                params,
            )
        ms.append((time.perf_counter() - t0) * 1e3)
    return ms
