"""Figures of the covariance a verified closure carries (docs/service.md): its calibration
and its score on the test towns (``benchmarks/pose_covariance.py``), and what it buys a pose
graph (``benchmarks/pose_graph.py``)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from figures_kit import load, source, table, when
from scipy.stats import binomtest, chi2

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
    rows = [[Path(t["town"]).name, *cells] for t in r["towns"] for cells in _rows(t, t["wrong"])]
    head = ["town", *HEAD[:2], "wrong", *HEAD[2:]]
    return out + table(head, rows) + _covariance_reading(r["towns"])


HEAD = ["covariance", "right closures", "inside 50 / 90 / 95 / 99 %", "NLL"]
HEAD += ["x σ / RMS (cm)", "yaw σ / RMS (°)"]


def _rows(scores: dict, wrong: int | None = None) -> list[list]:
    """A table's cells (:data:`HEAD`) for each covariance ``scores`` holds: the served one,
    then the one ellipsoid; one that no closure had says so. ``wrong``: the wrong
    closures' count, after the right ones'."""
    rows = []
    for label in ("served", "constant"):
        s = scores.get(label)
        if s is None:
            continue
        name = f"served ({s['estimator']})" if label == "served" else "one ellipsoid (val)"
        if not s["closures"]:
            rows.append([name, 0, *([] if wrong is None else [wrong]), "no right closure"])
            rows[-1] += [""] * (len(HEAD) + (wrong is not None) - len(rows[-1]))
            continue
        rows.append(
            [
                name,
                s["closures"],
                *([] if wrong is None else [wrong]),
                " / ".join(f"{x:.3f}" for x in s["inside"].values()),
                f"{s['nll']:.2f}",
                f"{100 * s['sigma_median']['x_m']:.1f} / {100 * s['error_rms']['x_m']:.1f}",
                f"{s['sigma_median']['yaw_deg']:.3f} / {s['error_rms']['yaw_deg']:.3f}",
            ]
        )
    return rows


VERIFY_ACROSS = "reports/service/verify-across-any-sensor.json"


def covariance_across(path: str = VERIFY_ACROSS) -> str:
    """The covariance of verified closures across sensors (``benchmarks/verify_across.py``
    with the file's calibration): pooled over the pairs across sensors and the same-sensor
    pairs, then pair by pair, and what it says."""
    from figures_pairs import NAMES

    r = load(path)
    cov = r.get("covariance", {}).get("scored")
    if not cov or "served" not in cov or "test" not in r:
        raise ValueError(f"{path} scored no served covariance on test: run verify_across.py")
    out = source(path, r["command"], when(r))
    summary = r["test"]["summary"]
    fitted = r["covariance"].get("fit_towns", "")
    towns = ", ".join(f"`{Path(t.strip()).name}`" for t in fitted.split(",") if t.strip())
    out += (
        f"\nModel {r['model_id']}, the covariance it serves (`{cov['served']['estimator']}`, "
        f"scale {cov['served']['scale']:.3g})"
        + (
            f", calibrated on the right closures within each drive of {towns}, and the one "
            f"ellipsoid fitted there (from `{r['covariance']['fit_from']}`)"
            if towns
            else ""
        )
        + ", on the right verified closures of the sensor test town's pairs above, pooled:\n\n"
    )
    names = {"across": "across sensors", "same": "same sensor"}
    rows = [
        [f"{names[k]} ({x['pairs']} pairs)", *cells]
        for k, x in summary.items()
        for cells in _rows(x["covariance"])
    ]
    out += table(["pairs", *HEAD], rows)
    pairs = r["test"]["pairs"]
    cells = {(p["queries_sensor"], p["map_sensor"]): p["covariance"] for p in pairs}

    def cell(c: dict) -> str:
        s, k = c["served"], c.get("constant")
        if not s["closures"]:
            return "no right closure"
        text = f"{s['inside']['0.95']:.3f} of {s['closures']}, {s['nll']:.1f}"
        return text + (f" ({k['nll']:.1f})" if k is not None and k["closures"] else "")

    sensors = list(dict.fromkeys(q for q, _ in cells))
    out += (
        "\nPair by pair: the served covariance's share inside its 95 % ellipsoid of the pair's "
        "right closures, and its mean NLL"
        + (" (in brackets one ellipsoid's NLL)" if "constant" in cov else "")
        + ":\n\n"
    )
    grid = [[NAMES[q], *(cell(cells[(q, m)]) for m in sensors)] for q in sensors]
    out += table(["queries ↓ map →", *(NAMES[m] for m in sensors)], grid)
    across = [
        (f"{NAMES[p['queries_sensor']]} → {NAMES[p['map_sensor']]}", p["covariance"])
        for p in pairs
        if p["queries_sensor"] != p["map_sensor"] and p["covariance"]["served"]["closures"]
    ]
    val = r.get("val", {}).get("summary", {}).get("across", {}).get("covariance")
    return out + _across_reading(across, summary) + ("" if val is None else _val_reading(val))


def _held(s: dict) -> str:
    """How the 95 % ellipsoids of scores ``s`` hold their share (:func:`_share`), said."""
    if not s["closures"]:
        return "nothing (no right closure)"
    return SAID[_share(s["inside"]["0.95"], 0.95, s["closures"])]


def _val_reading(val: dict) -> str:
    """Where a scale of its own for closures across sensors would be chosen: the run's
    calibration-town pairs (validation data, said as such)."""
    s = val["served"]
    return (
        f"On the calibration town's pairs across sensors (the same run's `val`, {s['closures']} "
        "right closures: where a scale of their own for closures across sensors would be "
        f"chosen, validation data and not a result) its 95 % ellipsoids hold {_held(s)}.\n"
    )


def _across_reading(across: list[tuple[str, dict]], summary: dict) -> str:
    """What the tables say across sensors, from their numbers: pooled, and pair by pair
    (each NLL compared where both covariances scored the same closures)."""
    pooled = {k: _held(x["covariance"]["served"]) for k, x in summary.items()}
    n = len(across)
    alike = [
        (k, c)
        for k, c in across
        if c.get("constant", {}).get("closures") == c["served"]["closures"]
    ]
    better = [k for k, c in alike if c["served"]["nll"] < c["constant"]["nll"]]
    share = {
        p: _share(c["served"]["inside"]["0.95"], 0.95, c["served"]["closures"]) for p, c in across
    }
    at = {k: [p for p, x in share.items() if x == k] for k in ("about", "fewer", "more")}
    return (
        f"\nAgainst 0.95 ({TEST}, as if the closures were independent: those of one drive "
        "are not quite, as neighbouring scans see the same place), the served covariance's "
        f"95 % ellipsoids hold {pooled['across']} across sensors, pooled, and "
        f"{pooled['same']} on the same sensor's second drive. Across sensors, pair by pair "
        f"(queries → map), on the {n} pairs with a right closure: its NLL is lower than one "
        f"ellipsoid's on {len(better)}"
        + (f" of the {len(alike)} where both scored the same closures" if len(alike) < n else "")
        + ", and its 95 % ellipsoids hold "
        + "; ".join(f"{SAID[k]} on {len(v)}" for k, v in at.items() if v)
        + (f" (fewer: {', '.join(at['fewer'])})" if at["fewer"] else "")
        + ".\n"
    )


SAID = {"about": "about their share", "fewer": "fewer", "more": "more"}  # _share's answer, said


def _share(inside: float, level: float, n: int) -> str:
    """Whether ``inside`` of ``n`` closures is the share ``level`` promises: "about" unless
    an exact two-sided binomial test tells them apart at 5 % (:data:`TEST`), else "fewer"
    or "more". A handful of closures is "about" any share it can be."""
    k = round(inside * n)
    if n == 0 or binomtest(k, n, level).pvalue >= 0.05:
        return "about"
    return "fewer" if inside < level else "more"


TEST = "an exact two-sided binomial test at 5 %"


def _covariance_reading(towns: list[dict]) -> str:
    """What the table says, from its numbers: where the served covariance wins in
    likelihood, where its 95% ellipsoids hold their share, where its tails are heavy."""
    served = [
        (Path(t["town"]).name, t["served"], t.get("constant"))
        for t in towns
        if "served" in t and t["served"]["closures"]
    ]
    better = [
        n
        for n, s, c in served
        if c is not None and c["closures"] == s["closures"] and s["nll"] < c["nll"]
    ]
    at = {
        k: [n for n, s, _ in served if _share(s["inside"]["0.95"], 0.95, s["closures"]) == k]
        for k in ("about", "fewer", "more")
    }
    heavy = [n for n, s, _ in served if _heavy_tailed(s["inside"], s["closures"])]

    def names(xs: list[str]) -> str:
        return ", ".join(f"`{x}`" for x in xs) if xs else "none"

    return (
        f"\nThe served covariance has the lower NLL on {len(better)} of {len(served)} test "
        f"towns ({names(better)}). Against 0.95 ({TEST}), its "
        "95 % ellipsoids hold "
        + "; ".join(f"{SAID[k]} on {names(v)}" for k, v in at.items() if v)
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


G2O_CHECK = "reports/client/g2o-check.json"


def g2o_check() -> str:
    """g2o and GTSAM themselves on the client's pose graph, each file written for one of
    them, against the optimum of the covariance's convention (``benchmarks/g2o_check.py``)."""
    r = load(G2O_CHECK)
    g = r["graph"]
    names = {"g2o": "g2o", "gtsam": "GTSAM"}
    versions = {
        "g2o": lambda x: f"g2o-python {x['g2o-python']} (numpy {x['numpy']})",
        "gtsam": lambda x: f"gtsam {x['gtsam']}",
    }
    rows, used = [], []
    for backend, files in r["solvers"].items():
        used.append(versions[backend](next(iter(files.values()))["said"]))
        for reader, x in files.items():
            d = x["gap_to_graph_kit"]
            rows.append(
                [
                    names[backend],
                    f"`--g2o-for {reader}`" + (" (its own)" if reader == backend else ""),
                    f"{1000 * d['position_max_m']:.3g} / {1000 * d['position_rms_m']:.3g}",
                    f"{d['rotation_max_deg']:.2g}",
                    f"{x['said']['chi2']:.4f}",
                ]
            )
    head = ["read and optimised by", "file written with", "gap: max / RMS (mm)", "max (°)"]
    head += ["χ² as that back end computes it"]
    return (
        source(G2O_CHECK, r["command"], when(r))
        + f"\n{' and '.join(used)} on the client's files of a drifting drive ({g['scans']} "
        f"scans, {g['loop_edges']} loop edges with correlated covariances, odometry σ "
        f"{g['odometry_sigma']['m']:g} m and {g['odometry_sigma']['deg']:g}° per axis), "
        "against the poses that minimise the error in the covariance's own convention (χ² "
        f"{r['graph_kit']['chi2']:.4f}); g2o's error takes the relative pose's translation as "
        "it is, the convention's the translation of the SE(3) logarithm, which differ at "
        "second order:\n\n" + table(head, rows)
    )


RENDERERS: dict[str, Callable[[], str]] = {
    "g2o-check": g2o_check,
    "covariance": covariance,
    "covariance-any-sensor": lambda: covariance(COVARIANCE_ANY, COVARIANCE_ANY_VAL),
    "pose-graph": pose_graph,
    "covariance-across-any-sensor": covariance_across,
    "covariance-across": lambda: covariance_across("reports/service/verify-across.json"),
}
