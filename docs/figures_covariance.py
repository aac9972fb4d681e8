"""Figures of the covariance a verified closure carries (docs/service.md): its calibration
and its score on the test towns (``benchmarks/pose_covariance.py``), and what it buys a pose
graph (``benchmarks/pose_graph.py``)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from figures_kit import load, source, table, when
from scipy.stats import chi2

COVARIANCE = "reports/service/pose-covariance-test.json"
COVARIANCE_VAL = "reports/service/pose_covariance.json"


COVARIANCE_ANY = "reports/service/pose-covariance-test-any-sensor.json"
COVARIANCE_ANY_VAL = "reports/service/pose_covariance-any-sensor.json"


def covariance(test: str = COVARIANCE, val: str = COVARIANCE_VAL) -> str:
    """The served covariance against one ellipsoid for all, on the test towns; the fit on the
    validation towns."""
    r, cal = load(test), load(val)
    if r["model_id"] != cal["model_id"]:
        raise ValueError(f"{test} is of model {r['model_id']}, {val} of {cal['model_id']}")
    fits = cal["val"]["fits"]
    chosen = cal["val"]["chosen"]
    towns = ", ".join(f"`{Path(t.strip()).name}`" for t in cal["val"]["town"].split(","))
    out = source(val, cal["command"], when(cal))
    out += source(test, r["command"], when(r))
    out += (
        f"\nModel {r['model_id']}. Chosen on {towns} ({fits[chosen]['closures']} right closures): "
        f"`{chosen}`, scale {fits[chosen]['scale']:.3g}, the one of lower mean negative "
        "log-likelihood there ("
        + ", ".join(f"{n} {f['nll']:.2f}" for n, f in fits.items() if n != "constant")
        + "; one ellipsoid for all, fitted there, "
        f"{fits['constant']['nll']:.2f}). On the test towns, each verified closure whose pose is "
        "right (within 1 m and 2°): the share inside its ellipsoid of each level (a right "
        "covariance puts that share inside), the mean negative log-likelihood (nats, lower is "
        "better), the median predicted σ and the observed RMS error along x and yaw; wrong "
        "closures are counted apart.\n\n"
    )
    rows = []
    for t in r["towns"]:
        for label in ("served", "constant"):
            if label not in t:
                continue
            s = t[label]
            name = f"served ({s['estimator']})" if label == "served" else "one ellipsoid (val)"
            rows.append(
                [
                    Path(t["town"]).name,
                    name,
                    s["closures"],
                    t["wrong"],
                    " / ".join(f"{x:.3f}" for x in s["inside"].values()),
                    f"{s['nll']:.2f}",
                    f"{100 * s['sigma_median']['x_m']:.1f} / {100 * s['error_rms']['x_m']:.1f}",
                    f"{s['sigma_median']['yaw_deg']:.3f} / {s['error_rms']['yaw_deg']:.3f}",
                ]
            )
    return (
        out
        + table(
            [
                "town",
                "covariance",
                "right closures",
                "wrong",
                "inside 50 / 90 / 95 / 99 %",
                "NLL",
                "x σ / RMS (cm)",
                "yaw σ / RMS (°)",
            ],
            rows,
        )
        + _covariance_reading(r["towns"])
    )


def _share(inside: float, level: float, n: int) -> str:
    """Whether ``inside`` of ``n`` closures is the share ``level`` promises, within two
    binomial standard errors: "about", "fewer" or "more"."""
    band = 2 * (level * (1 - level) / max(n, 1)) ** 0.5
    return "about" if abs(inside - level) <= band else ("fewer" if inside < level else "more")


def _covariance_reading(towns: list[dict]) -> str:
    """What the table says, from its numbers: where the served covariance wins in
    likelihood, where its 95% ellipsoids hold their share, where its tails are heavy."""
    served = [
        (Path(t["town"]).name, t["served"], t.get("constant")) for t in towns if "served" in t
    ]
    better = [n for n, s, c in served if c is not None and s["nll"] < c["nll"]]
    at = {
        k: [n for n, s, _ in served if _share(s["inside"]["0.95"], 0.95, s["closures"]) == k]
        for k in ("about", "fewer", "more")
    }
    heavy = [n for n, s, _ in served if _heavy_tailed(s["inside"], s["closures"])]

    def names(xs: list[str]) -> str:
        return ", ".join(f"`{x}`" for x in xs) if xs else "none"

    said = {"about": "about their share", "fewer": "fewer", "more": "more"}
    return (
        f"\nThe served covariance has the lower NLL on {len(better)} of {len(served)} test "
        f"towns ({names(better)}). Against 0.95, give or take two binomial standard errors, its "
        "95 % ellipsoids hold "
        + "; ".join(f"{said[k]} on {names(v)}" for k, v in at.items() if v)
        + ". "
        + (
            f"The errors have heavier tails than a Gaussian's on {names(heavy)}: fewer of "
            "them lie inside the 95 % ellipsoid than a Gaussian with the share seen inside "
            "the 50 % one would put there (by more than two binomial standard errors).\n"
            if heavy
            else "On no town do the errors show heavier tails than a Gaussian's (the 95 % "
            "share against a Gaussian with the share seen inside the 50 % ellipsoid).\n"
        )
    )


def _heavy_tailed(inside: dict[str, float], n: int) -> bool:
    """Whether fewer of ``n`` errors lie inside the 95% ellipsoid than a Gaussian would put
    there that holds the share seen inside the 50% one (the covariance rescaled to fit the
    bulk), by more than two binomial standard errors: tails heavier than a Gaussian's, told
    apart from a Gaussian only too wide or too narrow."""
    half = min(max(inside["0.5"], 0.5 / n), 1 - 0.5 / n)  # a share of 0 or 1 fits no scale
    k = chi2.ppf(0.5, 6) / chi2.ppf(half, 6)  # δᵀ Σ⁻¹ δ / k is χ²₆ for that Gaussian
    expected = float(chi2.cdf(chi2.ppf(0.95, 6) / k, 6))
    band = 2 * (expected * (1 - expected) / n) ** 0.5
    return inside["0.95"] < expected - band


POSE_GRAPH = "reports/service/pose-graph-test.json"


def pose_graph() -> str:
    """A drifting drive's pose graph optimised with the served covariance on its loop edges,
    beside one ellipsoid for every closure and dead reckoning."""
    r = load(POSE_GRAPH)
    odo = r["odometry_sigma"]
    out = source(POSE_GRAPH, r["command"], when(r))
    out += (
        f"\nModel {r['model_id']}; odometry noise a step σ = "
        + " / ".join(f"{x:g}" for x in odo["m"])
        + " m (x / y / z) and "
        + " / ".join(f"{x:g}" for x in odo["deg"])
        + f"° (roll / pitch / yaw), {r['seeds']} draws a town (the mean shown); the served "
        f"covariance is `{r['served']['estimator']}` at scale {r['served']['scale']:.3g}, the "
        "one ellipsoid the validation closures' (scale "
        f"{r['constant']['scale']:.3g}). After optimisation, against the truth: each scan's "
        "position and rotation (scan 0 held at its true pose), and at revisits (every pair "
        "of the town's ground-truth loops, "
        + " / ".join(str(t["revisit_pairs"]) for t in r["towns"])
        + "), the error of the pair's relative pose, which a map shows as a doubled wall:\n\n"
    )
    rows, better = [], []
    names = {
        "dead_reckoning": "none (dead reckoning)",
        "served": "served",
        "constant": "one ellipsoid",
    }
    for t in r["towns"]:
        m = t["mean"]
        if m["served"]["position_rms_m"] < m["constant"]["position_rms_m"]:
            better.append(Path(t["town"]).name)
        for way, label in names.items():
            rows.append(
                [
                    Path(t["town"]).name,
                    t["loop_edges"] if way != "dead_reckoning" else 0,
                    t["wrong_loop_edges"] if way != "dead_reckoning" else 0,
                    label,
                    f"{m[way]['position_rms_m']:.3f} / {m[way]['position_max_m']:.3f}",
                    f"{m[way]['within_0.1m']:.3f}",
                    f"{m[way]['rotation_rms_deg']:.3f}",
                    f"{m[way]['revisit_rms_m']:.3f} / {m[way]['revisit_rotation_rms_deg']:.3f}",
                ]
            )
    out += table(
        [
            "town",
            "loop edges",
            "wrong",
            "loop weights",
            "position RMS / max (m)",
            "within 0.1 m",
            "rotation RMS (°)",
            "at revisits: RMS (m / °)",
        ],
        rows,
    )

    def listed(xs: list[str]) -> str:
        return ", ".join(f"`{x}`" for x in xs) if xs else "none"

    tighter = [
        Path(t["town"]).name
        for t in r["towns"]
        if t["mean"]["served"]["revisit_rms_m"] < t["mean"]["constant"]["revisit_rms_m"]
    ]
    n = len(r["towns"])
    paired = [
        s["revisit_rms_m"] < c["revisit_rms_m"]
        for t in r["towns"]
        for s, c in zip(t["runs"]["served"], t["runs"]["constant"], strict=True)
    ]
    return out + (
        f"\nThe served covariance leaves the map tighter where the drive comes back than one "
        f"ellipsoid on {len(tighter)} of {n} test towns ({listed(tighter)}; on {sum(paired)} of "
        f"{len(paired)} odometry draws, each weighting given the same draw), and a lower "
        f"position RMS on {len(better)} of {n} ({listed(better)}).\n"
    )


RENDERERS: dict[str, Callable[[], str]] = {
    "covariance": covariance,
    "covariance-any-sensor": lambda: covariance(COVARIANCE_ANY, COVARIANCE_ANY_VAL),
    "pose-graph": pose_graph,
}
