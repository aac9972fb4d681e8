"""The HDL-64E network in one pass a scan with a first stage from its yaw features'
spectrum (``benchmarks/first_stage.py``): the choice on val, and the test towns."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from figures_fleet import fleet_views
from figures_kit import f3, load, source, table, when
from figures_spectrum import _first
from figures_verify import verify

FIRST_STAGE = "reports/model/first-stage-one-view.json"
VERIFY_ONE_PASS = "reports/service/verify-test-one-pass.json"
FLEET_ONE_PASS = "reports/client/fleet-one-pass.json"
VERIFY_ONE_PASS_256 = "reports/service/verify-test-one-pass-256.json"
FLEET_ONE_PASS_256 = "reports/client/fleet-one-pass-256.json"
SIZING = "reports/deploy/sizing.json"
SIZING_ONE_PASS = "reports/deploy/sizing-one-pass.json"
AMBIGUITY = "reports/service/verify-ambiguity-one-pass.json"
VERIFY_OS0 = "reports/service/verify-os0-128.json"  # the default file on the OS0-128 towns
SUBSETS = ("all", "same", "reverse")


def _pair(x: dict[str, float]) -> str:
    return f"{f3(x['f1max'])} / {f3(x['recall@1'])}"


def _turn(x: float) -> str:
    return f"{x:.5f}"


def first_stage_one_view() -> str:
    """Every first stage on val (the choice), then the network's descriptor and the choice
    on the test towns (mean of the three) and on real scans turned at random."""
    r = load(FIRST_STAGE)
    out = source(FIRST_STAGE, r["command"], when(r))
    out += (
        f"\n`{r['model']}` (`{r['model_id']}`, {r['views']} view, columns {r['column_phase']})"
        ": F1max / Recall@1 within one drive (all revisits and the reverse ones), of the first "
        "stage alone and with the second stage on top (shortlist "
        f"{r['rerank']['shortlist']}, weight {r['rerank']['weight']:g}); AR@1 of the second "
        "drive against the first, the first stage alone; the lowest cosine of a scan's vector "
        f"to its turned copy's (every {r['turn_stride']}th val scan, {r['seeds']} draws of "
        "random continuous turns).\n\nval (the choice: the mean of the first stage's F1max, "
        "Recall@1 and AR@1, among the stages whose turned cosine reaches "
        f"{r['turn_floor']:g}):\n\n"
    )
    head = ["first stage", "floats", "first stage: all", "reverse", "AR@1"]
    head += ["two stages: all", "turned: lowest cosine"]
    rows = [
        [
            _first(x["first_stage"]),
            str(x["dimension"]),
            _pair(x["drive"]["first"]["all"]),
            _pair(x["drive"]["first"]["reverse"]),
            f3(x["sessions_ar@1"]),
            _pair(x["drive"]["two_stages"]["all"]),
            _turn(x["turn_min"]),
        ]
        for x in r["val"]["rows"]
    ]
    out += table(head, rows)
    towns = ", ".join(f"`{t.rsplit('/', 1)[-1]}`" for t in r["test"]["towns"])
    out += (
        f"\nChosen: {_first(r['chosen'])}.\n\ntest ({towns}, their mean; "
        f"`{r['test']['second_drive'].rsplit('/', 1)[-1]}` against the first):\n\n"
    )
    head = ["first stage", "first stage: all", "same direction", "reverse", "AR@1"]
    head += ["two stages: all", "same direction", "reverse"]
    rows = [
        [
            _first(x["first_stage"]),
            *(_pair(x["drive"]["first"][s]) for s in SUBSETS),
            f3(x["sessions_ar@1"]),
            *(_pair(x["drive"]["two_stages"][s]) for s in SUBSETS),
        ]
        for x in r["test"]["rows"]
    ]
    out += table(head, rows)
    sets = {k: v for k, v in r["turns"].items() if isinstance(v, dict) and "scans" in v}
    names = [x["first_stage"] for x in r["test"]["rows"]]
    out += (
        f"\nReal scans turned at random ({r['turns']['seeds']} draws, every scan), the lowest "
        "cosine of a scan's vector to its turned copy's:\n\n"
    )
    rows = [
        [name, str(v["scans"]), *(_turn(v[n]["cosine_min"]) for n in names)]
        for name, v in sets.items()
    ]
    return out + table(["real scans", "scans", *(_first(n) for n in names)], rows)


def sizing_one_pass() -> str:
    """What a keyframe and a query cost with the default file's 256 floats and the one-pass
    file's 768: the FAISS store and snapshot a keyframe, a query at the benchmark's map, and
    the search stage at its large map (idle, one FAISS thread)."""
    runs = [(load(SIZING), SIZING), (load(SIZING_ONE_PASS), SIZING_ONE_PASS)]
    out = "".join(source(path, r["command"], when(r)) for r, path in runs)
    rows = []
    for r, _ in runs:
        f = r["backends"]["faiss"]
        stage = next(
            x for x in r["search_stage"] if x["load"] == "idle" and x["faiss_threads"] == 1
        )
        two = stage["search_two_stage"]
        rows.append(
            [
                f"`{r['model']['path'].rsplit('/', 1)[-1]}`",
                str(r["descriptor_dim"]),
                f"{f['store_bytes_per_keyframe'] / 1e3:.1f} KB / "
                f"{f['snapshot_bytes_per_keyframe'] / 1e3:.1f} KB",
                f"{f['query_p50_ms']:.2f} ms ({f['n']:,})",
                f"{stage['index']['p50_ms']:.2f} ms",
                f"{two['p50_ms']:.2f} ms (shortlist {two['shortlist']})",
                str(stage["keyframes"]),
            ]
        )
    head = ["file", "floats", "FAISS store / snapshot a keyframe", "query p50 (keyframes)"]
    head += ["search stage: index p50", "two stages p50", "keyframes"]
    out += (
        "\nThe FAISS backend; the search stage idle, one FAISS thread (the deploy guide's "
        "[Sizing](../docs/deploy.md#sizing) has every row of the default file's run):\n\n"
    )
    return out + table(head, rows)


def verify_ambiguity() -> str:
    """Accepted closures' fitness against the best other quarter turn's, right and wrong,
    and what each margin would keep (``benchmarks/verify_ambiguity.py``)."""
    r = load(AMBIGUITY)
    out = source(AMBIGUITY, r["command"], when(r))
    out += (
        f"\n`{r['model_id']}` at its own thresholds (fitness ≥ {r['verify']['min_fitness']:g}):"
        " each accepted closure registered again from its seed turned by "
        f"{', '.join(f'{t:g}°' for t in r['turns_deg'])}; the margin is its fitness less the "
        f"best other fit (a pose more than {r['turn_apart_deg']:g}° apart). Right: pose "
        "within 1 m and 2°. Kept: right / wrong closures whose margin reaches it.\n\n"
    )
    margins = [k["margin"] for k in next(iter(r["towns"].values()))["kept"]]
    head = ["town", "accepted", "wrong", "right: margin p1 / p5", "wrong: margin median"]
    rows = []
    for name, t in r["towns"].items():
        mr, mw = t["margin_right"], t["margin_wrong"]
        rows.append(
            [
                f"`{name}`",
                str(t["accepted"]),
                str(t["wrong"]),
                f"{f3(mr['p1'])} / {f3(mr['p5'])}" if mr else "—",
                f3(mw["p50"]) if mw else "—",
                *(f"{k['right']} / {k['wrong']}" for k in t["kept"]),
            ]
        )
    return out + table([*head, *(f"kept at {m:g}" for m in margins)], rows)


SCREENS = (
    "reports/service/verify-ambiguity.json",
    AMBIGUITY,
    "reports/service/verify-ambiguity-any-sensor.json",
)


def ambiguity_screen() -> str:
    """The screen of the ambiguity check, per file and town: turns that ended above their
    seed's share within reach, and the checks it decided otherwise
    (``benchmarks/verify_ambiguity.py``)."""
    out, rows = "", []
    for path in SCREENS:
        r = load(path)
        out += source(path, r["command"], when(r))
        for name, t in r["towns"].items():
            x = t["screen"]
            rows.append(
                [
                    f"`{r['model_id']}` (margin {x['margin']:g})",
                    f"`{name}`",
                    str(x["turns"]),
                    str(x["above_reach"]),
                    f3(x["largest_excess"]) if x["largest_excess"] is not None else "—",
                    f"{x['registered']} ({x['registered'] / max(x['turns'], 1):.0%})",
                    f"{x['changed']} of {x['checked']}",
                ]
            )
    out += (
        "\nEvery candidate that passes the file's fitness threshold, each of its turns "
        "registered in full: the turns that ended with a fitness above the share of their "
        "points within GICP's reach at their seed, the largest such excess (negative: none "
        "did), the turns the served check registers at the file's margin (a seed within reach "
        "of the fit that would refuse; the others cost a nearest-neighbour search), and the "
        "checks whose verdict the screen changes (a turn it leaves out would have refused):\n\n"
    )
    head = ["file", "town", "turns", "above their reach", "largest excess", "registered", "changed"]
    return out + table(head, rows)


# each file's verify calibration on its validation towns (benchmarks/verify_threshold.py)
CALIBRATIONS = {
    "overlapmamba-hdl64.onnx": "reports/service/verify_threshold.json",
    "overlapmamba-hdl64-one-pass.onnx": "reports/service/verify_threshold-one-pass.json",
    "overlapmamba-hdl64-one-view.onnx": "reports/service/verify_threshold-one-view.json",
    "overlapmamba-hdl64-tokens.onnx": "reports/service/verify_threshold-tokens.json",
    "overlapmamba-any-sensor.onnx": "reports/service/verify_threshold-any-sensor.json",
}


def ambiguity_margins() -> str:
    """``verify.ambiguity_margin`` as each file's calibration chose it on its validation
    towns, after its fitness, rmse and gate: what the margin cost there."""
    out, rows = "", []
    for name, rel in CALIBRATIONS.items():
        r = load(rel)
        out += source(rel, r["command"], when(r))
        cal = r["calibration"]
        g, m = cal["gate"], cal.get("ambiguity")
        towns = ", ".join(f"`{t['town'].rsplit('/', 1)[-1]}`" for t in r["towns"])
        rmse = "—" if g["max_rmse_m"] >= 1e9 else f"{g['max_rmse_m']:g}"
        rows.append(
            [
                f"`{name}`" + (" (default)" if rel.endswith("verify_threshold.json") else ""),
                towns,
                f"{g['min_fitness']:g} / {rmse} / {g['gate_distance']:g}",
                "not calibrated" if m is None else f"{m['ambiguity_margin']:g}",
                f"{g['correct']} of {g['accepted']}, {f3(g['recall'])}",
                "—" if m is None else f"{m['correct']} of {m['accepted']}, {f3(m['recall'])}",
            ]
        )
    head = [
        "file",
        "calibrated on",
        "fitness / rmse / gate",
        "ambiguity margin",
        "closures right, recall: without the margin",
        "with it",
    ]
    return out + "\n" + table(head, rows)


EACH = "reports/service/verify_threshold-any-sensor-each.json"  # every pair at the target
POOLED = "reports/service/verify_threshold-any-sensor-across.json"  # all queries at the target


def _thresholds(t: dict) -> str:
    rmse = "—" if t["max_rmse_m"] >= 1e9 else f"{t['max_rmse_m']:g}"
    margin = "off" if t["ambiguity_margin"] is None else f"{t['ambiguity_margin']:g}"
    return f"{t['min_fitness']:g} / {rmse} / {t['gate_distance']:g} / {margin}"


def ambiguity_each() -> str:
    """The every-sensor option's thresholds in force beside those chosen on the validation
    towns and the calibration town's pairs of drives, with each town and pair at the
    precision target (``--across --each``) or all their queries together (``--across``):
    precision and recall over all those queries, and the lowest town or pair."""
    each, pooled = load(EACH), load(POOLED)
    target = each["calibration"]["target_precision"]
    rows = []
    for label, cal, key in (
        ("in the file (chosen on the five towns)", each["calibration"], "in_force"),
        (f"each town and pair at precision ≥ {target:g}", each["calibration"], "calibrated"),
        (f"all together at precision ≥ {target:g}", pooled["calibration"], "calibrated"),
    ):
        t = cal[key]
        w = t["worst_group"]
        rows.append(
            [
                label,
                _thresholds(t),
                f"{t['correct']} of {t['accepted']} ({f3(t['precision'])})",
                f3(t["recall"]),
                f"{f3(w['precision'])} ({w['group']})",
            ]
        )
    head = ["thresholds", "fitness / rmse / gate / margin", "right, all", "recall, all"]
    head.append("lowest precision: town or pair")
    out = source(EACH, each["command"], when(each)) + source(
        POOLED, pooled["command"], when(pooled)
    )
    return out + "\n" + table(head, rows)


SENSORS = "reports/model/sensors.json"  # the default file on every sensor, before the margin


def verify_os0_128() -> str:
    """The default file's verified closures on the OS0-128's test towns with its margin, and
    the same towns' precision and recall in the sensor table, measured before it."""
    s = load(SENSORS)
    before = {Path(row["town"]).name: row["verified"] for row in s["same_sensor"]}
    rows = []
    for t in load(VERIFY_OS0)["towns"]:
        name, v = Path(t["town"]).name, t["verified_stop_at_first"]
        b = before[name]
        rows.append(
            [
                f"`{name}`",
                f"{f3(b['precision'])} ({b['correct']} of {b['accepted']}), {f3(b['recall'])}",
                f"{f3(v['precision'])} ({v['correct']} of {v['accepted']}), {f3(v['recall'])}",
            ]
        )
    out = verify(VERIFY_OS0, both=False) + source(SENSORS, s["command"], when(s))
    out += "\nPrecision (closures right of accepted) and recall, before and with the margin:\n\n"
    head = ["town", "before (the sensor table, no margin)", "with the margin"]
    return out + table(head, rows)


COSTS = ("reports/service/ambiguity-cost.json", "reports/service/ambiguity-cost-one-pass.json")
COST_CAPTION = (
    "\nThe verify stage a query (every 2nd query of the town, its candidates in the "
    "service's order, the file's own settings; one thread, in-process), the three ways on "
    "the same queries in turn; GICP runs a query; closures accepted; and the queries "
    "the served check decided otherwise than registering every turn:\n\n"
)
WAYS = {
    "off": "no check",
    "served": "the check as served",
    "every_turn": "the check, every turn registered",
}


def ambiguity_cost() -> str:
    """The verify stage a query without the ambiguity check, with it as served (a turn
    registered only where its seed could rival) and registering every turn
    (``benchmarks/ambiguity_cost.py``)."""
    out, rows = "", []
    for path in COSTS:
        r = load(path)
        out += source(path, r["command"], when(r))
        for t in r["towns"]:
            for way, x in t["ways"].items():
                rows.append(
                    [
                        f"`{r['model_id']}` (margin {r['verify']['ambiguity_margin']:g})",
                        f"`{t['town']}`",
                        WAYS[way],
                        f"{x['ms_mean']:.2f} / {x['ms_p50']:.2f} / {x['ms_p90']:.2f} ms",
                        f"{x['gicp_per_query']:.2f}",
                        str(x["accepted"]),
                        f"{t['decided_differently']} of {t['queries']}" if way == "served" else "",
                    ]
                )
    head = ["file", "town", "way", "mean / p50 / p90", "GICP a query", "accepted", "differ"]
    return out + COST_CAPTION + table(head, rows)


RENDERERS: dict[str, Callable[[], str]] = {
    "ambiguity-cost": ambiguity_cost,
    "ambiguity-screen": ambiguity_screen,
    "first-stage-one-view": first_stage_one_view,
    "verify-one-pass": lambda: verify(VERIFY_ONE_PASS, both=False),
    "fleet-one-pass": lambda: fleet_views(FLEET_ONE_PASS),
    "verify-one-pass-256": lambda: verify(VERIFY_ONE_PASS_256, both=False),
    "fleet-one-pass-256": lambda: fleet_views(FLEET_ONE_PASS_256),
    "sizing-one-pass": sizing_one_pass,
    "verify-ambiguity-one-pass": verify_ambiguity,
    "ambiguity-margins": ambiguity_margins,
    "verify-os0-128": verify_os0_128,
    "ambiguity-each": ambiguity_each,
}
