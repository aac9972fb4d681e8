"""The rules ``benchmarks/verify_threshold.py --calibrate`` chooses the service's verification
thresholds by, from queries whose every candidate was registered and scored
(``closure_kit.score``): the fitness and rmse thresholds of highest recall that keep precision
at the target, whichever way the service chooses the closure; then the nearest descriptor
gate that costs at most 0.005 of that recall; then the largest ambiguity margin that costs at
most 0.005 more. With ``each`` the target holds on every town and pair of drives, and the
fitness, rmse and margin are chosen together (:func:`joint`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from closure_kit import score

FITNESS = np.round(np.arange(0.20, 0.99, 0.02), 2)  # --calibrate's sweep of verify.min_fitness
MARGINS = np.round(np.arange(0, 0.61, 0.02), 2)  # and of verify.ambiguity_margin


def ambiguity_margin(
    queries: list[dict[str, Any]], gate: dict[str, Any], holds: Callable[..., bool]
) -> dict[str, Any]:
    """``verify.ambiguity_margin``, after the thresholds and the gate (each candidate that may
    pass them carries its rival's fit: ``verify_threshold.run_town(rivals_from=)``): the
    largest of 0, 0.02, … 0.6 that costs at most 0.005 of the gate's recall, precision at the
    target both ways (``chosen``; None: none does), and the ``sweep``. With ``--across`` the
    pairs' candidates carry their rivals too (``verify_across.pair_queries(rivals_from=)``),
    so the margin holds for a map by one sensor and a query by another as well."""
    f, rmse, d = gate["min_fitness"], gate["max_rmse_m"], gate["gate_distance"]
    sweep = [score(queries, f, rmse, d, margin=float(m)) for m in MARGINS]
    fine = [
        s
        for s in sweep
        if holds(s, d, s["ambiguity_margin"]) and s["recall"] >= gate["recall"] - 0.005
    ]
    chosen = max(fine, key=lambda s: s["ambiguity_margin"]) if fine else None
    return {"chosen": chosen, "sweep": sweep}


def by_group(queries: list[dict[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    """The queries of each town and, with ``--across``, of each pair of drives."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for q in queries:
        groups.setdefault(q["group"], []).append(q)
    return groups


def target_holds(queries: list[dict[str, Any]], target: float, each: bool) -> Callable[..., bool]:
    """Whether thresholds scored on ``queries`` (``s``, from :func:`score`, with a ``gate``
    and a ``margin`` to score them at) keep precision at ``target`` whichever way the service
    chooses the closure, over all queries and with ``each`` on every town and pair too."""
    groups = by_group(queries)

    def holds(s: dict[str, Any], gate: float | None = None, margin: float | None = None) -> bool:
        f, rmse = s["min_fitness"], s["max_rmse_m"]
        first = score(queries, f, rmse, gate, stop_at_first=True, margin=margin)
        if s["precision"] < target or first["precision"] < target:
            return False
        return not each or all(
            score(g, f, rmse, gate, stop_at_first=first_, margin=margin)["precision"] >= target
            for g in groups.values()
            for first_ in (False, True)
        )

    return holds


def joint(
    queries: list[dict[str, Any]], sweep: list[dict[str, Any]], holds: Callable[..., bool]
) -> dict[str, Any] | None:
    """With ``--each``: the fitness and rmse thresholds and the ambiguity margin chosen
    together, the triple of highest recall whose precision holds the target on each town and
    pair of drives, both ways of choosing the closure (among equals the strictest); None
    when none does. One after the other, the fitness alone would have to keep every pair at
    the target, and the margin, which refuses a pair's closures that another turn fits
    nearly as well, would come too late to spare recall."""
    combos = [
        score(queries, s["min_fitness"], s["max_rmse_m"], margin=float(m))
        for s in sweep
        if s["accepted"]
        for m in MARGINS
    ]
    combos.sort(
        key=lambda s: (s["recall"], s["min_fitness"], -s["max_rmse_m"], s["ambiguity_margin"]),
        reverse=True,
    )
    return next(
        (s for s in combos if s["accepted"] and holds(s, None, s["ambiguity_margin"])), None
    )


def calibrate(
    queries: list[dict[str, Any]], target: float, each: bool, in_force: dict[str, Any]
) -> dict[str, Any]:
    """The thresholds chosen on ``queries`` (``calibration``: ``chosen``, ``gate``,
    ``ambiguity``, and what the thresholds ``in_force`` and the ones chosen score, over all
    queries and on their worst town or pair of drives) with the sweeps they were chosen from
    (``sweep``, ``gates``, ``ambiguity_sweep``; absent where a step before chose nothing)."""
    sweep = [score(queries, f, r) for f in FITNESS for r in (0.5, 0.6, 0.7, 1e9)]
    # highest recall at the target, whichever way the service chooses the closure; among
    # equals the strictest thresholds (a margin)
    groups = by_group(queries)  # each town, and each pair of drives with --across
    holds = target_holds(queries, target, each)
    if each:  # the margin with the thresholds: joint()
        chosen = joint(queries, sweep, holds)
    else:
        ok = [s for s in sweep if s["accepted"] and holds(s)]
        key = lambda s: (s["recall"], s["min_fitness"], -s["max_rmse_m"])  # noqa: E731
        chosen = max(ok, key=key) if ok else None
    calibration: dict[str, Any] = {
        "target_precision": target,
        "target_on": "each town and pair" if each else "all queries",
        "rule": "fitness, rmse and margin together" if each else "one after the other",
        "chosen": chosen,
    }
    out: dict[str, Any] = {"calibration": calibration, "sweep": sweep}
    if chosen is not None:
        # the descriptor gate: the nearest distance that costs at most 0.005 of recall
        m0 = chosen["ambiguity_margin"]  # None but with --each
        gates = [
            score(queries, chosen["min_fitness"], chosen["max_rmse_m"], float(d), margin=m0)
            for d in np.round(np.arange(0.10, 1.01, 0.01), 2)
        ]
        fine = [
            g
            for g in gates
            if holds(g, g["gate_distance"], m0) and g["recall"] >= chosen["recall"] - 0.005
        ]
        gate = min(fine, key=lambda g: g["gate_distance"]) if fine else None
        calibration["gate"] = gate
        out["gates"] = gates
        if gate is not None:
            margins = ambiguity_margin(queries, gate, holds)
            calibration["ambiguity"] = margins["chosen"]
            out["ambiguity_sweep"] = margins["sweep"]
    # what the file's thresholds in force and the ones chosen do on the same queries, all
    # together and on the worst town or pair of drives (as the service answers)
    final = calibration.get("ambiguity") or calibration.get("gate")
    for name, t in (("in_force", in_force), ("calibrated", final)):
        if t is None:
            continue
        at = (t["min_fitness"], t["max_rmse_m"], t["gate_distance"], True)
        s = score(queries, *at, margin=t["ambiguity_margin"])
        by = {g: score(qs, *at, margin=t["ambiguity_margin"]) for g, qs in groups.items()}
        worst = min(by, key=lambda g: by[g]["precision"])
        s["worst_group"] = {"group": worst, **by[worst]}
        calibration[name] = s
    return out
