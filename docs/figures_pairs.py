"""Issue 40's bar across sensors, pair by pair (``benchmarks/across_pairs.py``): a map made by
one sensor, queries from another, for every ordered pair among five sensors, each model file's
answers beside Scan Context's on the same drives."""

from __future__ import annotations

from typing import Any

from figures_kit import f3, load, source, table, when

SHIPPED = "reports/model/across-pairs.json"
CANDIDATES = (
    "reports/model/across-pairs-bev-long.json",
    "reports/model/across-pairs-bev-span-thin.json",
)
NAMES = {
    "kitti-hdl64": "HDL-64E",
    "os1-128": "OS1-128",
    "vlp16": "VLP-16",
    "os0-128": "OS0-128",
    "xt32": "XT32",
}


def _file_name(r: dict[str, Any]) -> str:
    """A report's model file by its name (a run's ``encoder.onnx`` by the run's)."""
    path = r["model"]
    name = path.split("/")[-2] if path.endswith("/encoder.onnx") else path.split("/")[-1]
    return f"`{name}`"


def _label(r: dict[str, Any]) -> str:
    """A report's model: its file (:func:`_file_name`), model id, input and views."""
    views = f"{r['views']} view{'s' if r['views'] != 1 else ''} a scan"
    return f"{_file_name(r)} (`{r['model_id']}`, input `{r['sensor_input']}`, {views})"


def _matrix(r: dict[str, Any], split: str, cell: Any) -> str:
    """Rows the query sensor, columns the map's; ``cell(pair)`` each pair's text."""
    sensors = r["sensors"]
    at = {(p["queries"], p["map"]): p for p in r[split]["pairs"]}
    rows = [[NAMES[q], *(cell(at[(q, m)]) for m in sensors)] for q in sensors]
    return table(["queries ↓ map →", *(NAMES[m] for m in sensors)], rows)


def _verdict(r: dict[str, Any], split: str) -> str:
    v = r[split]["verdict"]
    n = v["pairs_across"]
    parts = []
    for key, what in (("descriptor", "the descriptor alone"), ("two_stage", "two stages")):
        a = v[key]
        parts.append(
            f"{what}: {a['meeting_bar']} of {n} pairs meet it (AR@1 lowest "
            f"{f3(a['min_ar@1'])}, mean {f3(a['mean_ar@1'])}; above Scan Context on "
            f"{a['above_scan_context']})"
        )
    sc = v["scan_context"]
    parts.append(f"Scan Context: AR@1 lowest {f3(sc['min_ar@1'])}, mean {f3(sc['mean_ar@1'])}")
    return "; ".join(parts) + ".\n"


def pair_tables(r: dict[str, Any], split: str, with_sc: bool) -> str:
    def answers(p: dict[str, Any]) -> str:
        return f"{f3(p['descriptor']['ar@1'])} / {f3(p['two_stage']['ar@1'])}"

    out = f"\n{_label(r)}, AR@1 of the descriptor alone / two stages:\n\n"
    out += _matrix(r, split, answers)
    if with_sc:
        out += "\nScan Context on the same drives, AR@1:\n\n"
        out += _matrix(r, split, lambda p: f3(p["scan_context"]["ar@1"]))
    out += (
        f"\nThe bar (AR@1 ≥ {r['bar']['ar@1']:g} on every pair across sensors, above Scan "
        f"Context's): {_verdict(r, split)}"
    )
    return out


def _intro(r: dict[str, Any]) -> str:
    return (
        "\nA second drive by the query sensor (rows) against the first drive's map by the map "
        f"sensor (columns), every sensor on a car's roof; a hit within {r['radius_m']:g} m. The "
        "diagonal is one sensor across sessions; the other 20 cells are the bar's pairs. Two "
        "stages: the shortlist re-ranked by the yaw features as the service answers "
        "(the file's own calibration, or the service's defaults where it has none).\n"
    )


def across_pairs() -> str:
    """The shipped file on the sensor test town: every pair, with Scan Context beside."""
    r = load(SHIPPED)
    out = source(SHIPPED, r["command"], when(r))
    out += _intro(r) + "\ntest (the sensor test town):\n"
    return out + pair_tables(r, "test", with_sc=True)


def across_pairs_candidates() -> str:
    """The bird's-eye candidates, on the val town (where they are compared) and the test town."""
    reports = [(p, load(p)) for p in (*CANDIDATES, SHIPPED)]
    out = "".join(source(p, r["command"], when(r)) for p, r in reports)
    out += _intro(reports[0][1])
    for split, title in (
        ("val", "val (calibration town `cal-x00`, where a choice is made)"),
        ("test", "test (the sensor test town)"),
    ):
        out += f"\n{title}:\n"
        for _, r in reports[:-1]:
            out += pair_tables(r, split, with_sc=False)
        out += pair_tables(reports[-1][1], split, with_sc=True)
    return out


RERANK = "reports/model/rerank-across-bev-span-thin.json"
RERANK_PAIRS = "reports/model/across-pairs-bev-span-thin.json"  # its Scan Context, same drives
RERANK_OTHERS = ("reports/model/rerank-across-bev-long.json",)
# the every-sensor option's calibration (models/overlapmamba-any-sensor.onnx), and Scan Context
# on the same test drives from its weights' across-pairs run (in the sensor's columns: Scan
# Context does not depend on the file); the column phase was chosen with the option's earlier
# first stage (mixed:0.5:8:none): the same weights and stage in the sensor's columns and aligned
RERANK_ANY = "reports/model/rerank-across-any-sensor.json"
RERANK_ANY_PAIRS = "reports/model/across-pairs-bev-span-thin-cpu-more-e16-still.json"
RERANK_ANY_SENSOR_COLUMNS = "reports/model/rerank-across-any-sensor-sensor-columns.json"
RERANK_ANY_ALIGNED = "reports/model/rerank-across-any-sensor-aligned.json"
# the same file with shortlists past the 50 the service took before the row cache
RERANK_ANY_LONG = "reports/model/rerank-across-any-sensor-long.json"
# the same file's grid scored by the network's own descriptors inside its first stage
RERANK_ANY_NETWORK = "reports/model/rerank-across-any-sensor-network-score.json"


def _setting(r: dict[str, Any]) -> str:
    if r["shortlist"] == 1:
        return "the descriptor alone"
    return f"shortlist {r['shortlist']}, weight {r['weight']:g}"


def _figures(x: dict[str, Any]) -> list[str]:
    """A setting's AR@1: over the 25 pairs, across sensors (mean / lowest / at the bar), same
    sensor."""
    return [
        f3(x["mean_ar@1"]),
        f"{f3(x['cross_mean_ar@1'])} / {f3(x['cross_min_ar@1'])} / {x['pairs_at_bar']}",
        f3(x["same_mean_ar@1"]),
    ]


def sweep_test_rows(r: dict[str, Any], own: str = "its own") -> list[list[str]]:
    """A ``rerank_across`` report's three answers on test: the file's descriptor alone, its
    own setting (named ``own``), and the setting chosen on val."""
    return [
        [f"{label}: {_setting(x)}" if x["shortlist"] > 1 else _setting(x), *_figures(x)]
        for label, x in (
            ("descriptor", r["test"]["descriptor"]),
            (own, r["test"]["own"]),
            ("chosen on val", r["test"]["chosen"]),
        )
    ]


def _scored(r: dict[str, Any]) -> str:
    """What the grid's score measures d² between, where it is not the first stage's vectors."""
    if r["grid"].get("score", "stage") == "stage":
        return ""
    return (
        "; the grid (and its choice) scores by d² between the network's own descriptors inside "
        "the first stage (`--score network`)"
    )


def rerank_across(path: str = RERANK, pairs: str = RERANK_PAIRS) -> str:
    """The second stage's shortlist and weight across sensors, chosen on val, on test, for
    the file of ``path`` (Scan Context from ``pairs``, an across-pairs report of the same
    file on the same drives)."""
    r, sc_report = load(path), load(pairs)
    if r["sensors"] != sc_report["sensors"] or r["radius_m"] != sc_report["radius_m"]:
        raise ValueError(f"{path} and {pairs} measured other pairs or another radius")
    out = source(path, r["command"], when(r)) + source(pairs, sc_report["command"], when(sc_report))
    own = r["own"]
    out += (
        f"\n{_label(r)}; its own setting when measured: shortlist {own['shortlist']}, weight "
        f"{own['weight']:g} ({'its calibration' if own['calibrated'] else 'the service defaults'}"
        f"{', scored by ' + own['score'] if own.get('score', 'stage') != 'stage' else ''})"
        f"{_scored(r)}. AR@1 over the 25 pairs (mean), over the 20 across sensors (mean, "
        f"lowest, how many reach {r['bar_ar@1']:g}) and over the five same-sensor pairs; the "
        "cost is the yaw correlations of the shortlist, a query, one thread (median).\n\n"
        "val (calibration town `cal-x00`: the choice):\n\n"
    )
    rows = [
        [
            _setting(x),
            *_figures(x),
            f"{r['cost_ms'][str(x['shortlist'])]:.2f} ms" if x["shortlist"] > 1 else "—",
        ]
        for x in r["val"]["settings"]
    ]
    head = ["setting", "mean", "across: mean / lowest / at the bar", "same sensor", "cost"]
    out += table(head, rows)
    chosen = r["val"]["chosen"]
    out += f"\nChosen: {_setting(chosen)}.\n\ntest (the sensor test town: reported):\n\n"
    out += table(head[:-1], sweep_test_rows(r))
    best = {(p["queries"], p["map"]): p["ar@1"] for p in r["test"]["chosen"]["pairs"]}
    return out + against_scan_context(
        sc_report, best, "the setting chosen on val, pair by pair: AR@1"
    )


def against_scan_context(
    sc_report: dict[str, Any], ours: dict[tuple[str, str], float], what: str
) -> str:
    """Test, pair by pair: ``ours`` (by (queries, map)) / Scan Context's AR@1 on the same
    drives (``sc_report``: an across-pairs report), and on how many pairs across it is above."""
    sc = {(p["queries"], p["map"]): p["scan_context"]["ar@1"] for p in sc_report["test"]["pairs"]}
    sensors = sc_report["sensors"]
    grid = [
        [NAMES[q], *(f"{f3(ours[(q, m)])} / {f3(sc[(q, m)])}" for m in sensors)] for q in sensors
    ]
    above = sum(ours[k] > sc[k] for k in ours if k[0] != k[1])
    head = (
        f"\ntest, {what} / Scan Context's AR@1 on the same drives (above it on {above} of 20 "
        "pairs across sensors):\n\n"
    )
    return head + table(["queries ↓ map →", *(NAMES[m] for m in sensors)], grid)


def _other_networks() -> str:
    """The same sweep for the other candidates: the setting each chose on val, on test."""
    out = ""
    rows = []
    for path in RERANK_OTHERS:
        r = load(path)
        out += source(path, r["command"], when(r))
        rows += [[_file_name(r), *row] for row in sweep_test_rows(r)]
    head = ["network", "setting", "mean", "across: mean / lowest / at the bar", "same sensor"]
    return out + "\nThe same sweep for `bev-long`, on test:\n\n" + table(head, rows)


def column_phases(
    files: tuple[tuple[str, str], ...] = (
        (RERANK_ANY_SENSOR_COLUMNS, "sensor"),
        (RERANK_ANY_ALIGNED, "aligned"),
    ),
) -> str:
    """The same weights in the sensor's columns and aligned (``rerank_across`` reports of
    both files, ``files`` with the column phase each was measured with, the same drives):
    AR@1 of the descriptor alone and of the setting each chose on val, on val and on test."""
    reports = [(load(p), phase) for p, phase in files]
    stages = {r["first_stage"] for r, _ in reports}
    if len(stages) != 1:
        raise ValueError(f"the column phases were measured with other first stages: {stages}")
    out = ""
    for (path, _), (r, _) in zip(files, reports, strict=True):
        out += source(path, r["command"], when(r))
    out += (
        f"\nThe same weights, first stage (`{stages.pop()}`) and input, with the columns at the "
        "sensor's azimuth "
        "or at each scan's mean bearing (aligned); AR@1 as above, of the descriptor alone and "
        "of the setting each file chose on val:\n\n"
    )
    rows = []
    for r, phase in reports:
        if r.get("column_phase", phase) != phase:  # reports before 2026-12-01 do not say
            raise ValueError(f"{r['model']} was measured with {r['column_phase']} columns")
        alone = next(x for x in r["val"]["settings"] if x["shortlist"] == 1)
        for split, answers in (
            ("val", (alone, r["val"]["chosen"])),
            ("test", (r["test"]["descriptor"], r["test"]["chosen"])),
        ):
            for x in answers:
                what = _setting(x) + (" (chosen on val)" if x["shortlist"] > 1 else "")
                rows.append([f"{_file_name(r)} (`{r['model_id']}`)", phase, split, what])
                rows[-1] += _figures(x)
    head = ["file", "columns", "split", "answer", "mean", "across: mean / lowest / at the bar"]
    return out + table([*head, "same sensor"], rows)


RENDERERS = {
    "across-pairs": across_pairs,
    "across-pairs-candidates": across_pairs_candidates,
    "rerank-across": lambda: rerank_across() + _other_networks(),
    "rerank-across-any-sensor": lambda: rerank_across(RERANK_ANY, RERANK_ANY_PAIRS),
    "rerank-across-any-sensor-long": lambda: rerank_across(RERANK_ANY_LONG, RERANK_ANY_PAIRS),
    "rerank-across-any-sensor-network-score": lambda: rerank_across(
        RERANK_ANY_NETWORK, RERANK_ANY_PAIRS
    ),
    "column-phase-any-sensor": column_phases,
}
