"""A first stage from the yaw features' magnitude spectrum (``benchmarks/yaw_spectrum.py``,
``overlapmamba.core.yaw_spectrum``) across sensors beside the descriptor and Scan Context,
and the file that carries it as its descriptor (``benchmarks/across_pairs.py``)."""

from __future__ import annotations

from typing import Any

from figures_kit import f3, load, source, table, when
from figures_pairs import (
    RERANK_ANY,
    RERANK_ANY_ALIGNED,
    _file_name,
    _label,
    _setting,
    against_scan_context,
    sweep_test_rows,
)

SPECTRUM = "reports/model/yaw-spectrum-bev-span-thin.json"
SC_PAIRS = "reports/model/across-pairs-bev-span-thin.json"
FIRST_FILE = "reports/model/across-pairs-bev-span-thin-first.json"
FIRST_SWEEP = "reports/model/rerank-across-bev-span-thin-first.json"


def _first(name: str) -> str:
    """A first stage's name as the docs say it."""
    if name == "descriptor":
        return "the descriptor (NetVLAD)"
    parts = name.split(":")
    if parts[0] == "spectrum":
        return f"the spectrum ({parts[1]} bins, {parts[2]})"
    return f"mixed: {parts[1]} spectrum ({parts[2]} bins, {parts[3]}) + descriptor"


def real_sets(r: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """A yaw-spectrum report's turned real sets that were there (name → each stage's lowest
    cosine and the scans), without the seeds' count or a skipped set."""
    return {k: v for k, v in r["turns"].items() if isinstance(v, dict) and "scans" in v}


def _recall_row(x: dict[str, Any]) -> list[str]:
    return [
        _first(x["first"]),
        f3(x["mean_r@1"]),
        f"{f3(x['across_mean_r@1'])} / {f3(x['across_min_r@1'])}",
        f3(x["mean_r@20"]),
        f3(x["mean_r@50"]),
    ]


def yaw_spectrum() -> str:
    """The first stages on val (the choice) and test, the pairs against Scan Context, the
    turned real scans, and the chosen first stage's shortlist re-ranked."""
    r, sc_report = load(SPECTRUM), load(SC_PAIRS)
    out = source(SPECTRUM, r["command"], when(r)) + source(
        SC_PAIRS, sc_report["command"], when(sc_report)
    )
    out += (
        f"\n{_label(r)}. Over the 25 pairs (mean) and the 20 across sensors (mean / lowest): "
        "the share of queries whose first answer is within 5 m (R@1, the descriptor's AR@1), "
        "and whose first 20 and 50 answers hold one (the shortlist a second stage re-ranks)."
        "\n\nval (calibration town `cal-x00`: the choice, by mean R@1):\n\n"
    )
    head = ["first stage", "R@1 mean", "R@1 across: mean / lowest", "R@20", "R@50"]
    out += table(head, [_recall_row(x) for x in r["val"]["rows"]])
    out += f"\nChosen: {_first(r['val']['chosen'])}.\n\ntest (the sensor test town):\n\n"
    test = r["test"]["rows"]
    out += table(head, [_recall_row(x) for x in test])
    best = {(p["queries"], p["map"]): p["r@1"] for p in test[-1]["pairs"]}
    out += against_scan_context(sc_report, best, "the chosen first stage alone, pair by pair: R@1")
    turns = r["turns"]
    rows = [
        [
            name,
            str(v["scans"]),
            *(f"{v[k]['cosine_min']:.4f}" for k in ("descriptor", test[-1]["first"])),
        ]
        for name, v in real_sets(r).items()
    ]
    out += (
        f"\nReal scans turned by a random continuous angle ({turns['seeds']} draws, one pass a "
        "scan): the lowest cosine between a scan's vector and its turned copy's:\n\n"
    )
    out += table(["real set", "scans", "descriptor", _first(test[-1]["first"])], rows)
    return out + _in_the_file()


def _in_the_file() -> str:
    """The chosen first stage written into the file (``overlapmamba export --first-stage``),
    measured as the service answers (``benchmarks/across_pairs.py``)."""
    r, before = load(FIRST_FILE), load(SC_PAIRS)
    out = "\n" + source(FIRST_FILE, r["command"], when(r))
    out += (
        f"\nThe chosen first stage written into the file as its descriptor: {_label(r)}, "
        f"descriptor `{r['first_stage']}`; AR@1 over the 20 pairs across sensors as the service "
        "answers (two stages: the service's defaults), beside the file it was written from:\n\n"
    )
    rows = []
    for name, rep in ((_file_name(before), before), (_file_name(r), r)):
        for split in ("val", "test"):
            v = rep[split]["verdict"]
            for answer in ("descriptor", "two_stage"):
                x = v[answer]
                rows.append(
                    [
                        name,
                        split,
                        answer.replace("_", " "),
                        f"{f3(x['mean_ar@1'])} / {f3(x['min_ar@1'])}",
                        f"{x['meeting_bar']} / {x['above_scan_context']}",
                    ]
                )
    head = ["file", "split", "answer", "AR@1 mean / lowest", "pairs at the bar / above SC"]
    return out + table(head, rows) + _sweep()


def _sweep() -> str:
    """The file's second stage swept (``benchmarks/rerank_across.py --shortlists``): the
    setting chosen on val, on test."""
    r = load(FIRST_SWEEP)
    out = "\n" + source(FIRST_SWEEP, r["command"], when(r))
    chosen = r["val"]["chosen"]
    grid = r["grid"]
    out += (
        f"\nIts second stage swept on val (shortlists {', '.join(map(str, grid['shortlists']))} "
        f"× weights {', '.join(f'{w:g}' for w in grid['weights'])}; chosen: "
        f"{_setting(chosen)}), AR@1 on test:\n\n"
    )
    rows = sweep_test_rows(r, own="the service defaults")
    rows[0][0] = "the spectrum alone"  # the file's descriptor is its first stage
    head = ["answer", "mean", "across: mean / lowest / at the bar", "same sensor"]
    return out + table(head, rows)


ALIGNED = "reports/model/yaw-spectrum-any-sensor-aligned.json"
ALIGNED_FILES = (  # the option before, then the candidates the choice above wrote
    RERANK_ANY_ALIGNED,
    "reports/model/rerank-across-any-sensor-aligned-spectrum-128-sqrt.json",
    "reports/model/rerank-across-any-sensor-aligned-spectrum-32-sqrt.json",
)


def spectrum_aligned() -> str:
    """The first stage chosen again for the option's network with aligned columns (every
    stage still under a turn, so the floor no longer binds): the stages on val and the
    choice on test, then the candidate files as the service answers beside the option."""
    r = load(ALIGNED)
    out = source(ALIGNED, r["command"], when(r))
    out += (
        f"\n{_label(r)}, columns aligned. R@1 as above; the stages on val by mean R@1, the "
        "first eight:\n\n"
    )
    head = ["first stage", "R@1 mean", "R@1 across: mean / lowest", "R@20", "R@50"]
    ranked = sorted(r["val"]["rows"], key=lambda x: -x["mean_r@1"])[:8]
    out += table(head, [_recall_row(x) for x in ranked])
    worst = min(v[k]["cosine_min"] for v in real_sets(r).values() for k in v if k != "scans")
    out += (
        f"\nChosen: {_first(r['val']['chosen'])} (the lowest cosine under turns of real scans, "
        f"any stage measured: {worst:.5f}). On test:\n\n"
    )
    out += table(head, [_recall_row(x) for x in r["test"]["rows"]])
    reports = [(p, load(p)) for p in ALIGNED_FILES]
    out += "\n" + "".join(source(p, x["command"], when(x)) for p, x in reports)
    out += (
        "\nAs the service answers, each file's second stage chosen on val "
        "(`benchmarks/rerank_across.py`), AR@1 on test:\n\n"
    )
    rows = []
    for _, x in reports:
        name = f"{_file_name(x)} (`{x['first_stage']}`)"
        for row in sweep_test_rows(x):
            if not row[0].startswith("its own"):
                rows.append([name, *row])
    head = ["file", "answer", "mean", "across: mean / lowest / at the bar", "same sensor"]
    return out + table(head, rows)


# within one drive on the five val towns (benchmarks/loop_threshold.py, scored as one curve) for
# the stages of the aligned choice above, each written into a file; each report names its stage
WITHIN = tuple(
    f"reports/service/loop_threshold-any-sensor-{name}.json"
    for name in (
        "net-aligned",
        "aligned",
        "aligned-mixed-0.75-32-sqrt",
        "aligned-spectrum-32-sqrt",
        "aligned-spectrum-128-sqrt",
    )
)


def within_and_across(within: tuple[str, ...] = WITHIN) -> str:
    """Each first stage on val two ways: across sensors on the calibration town (the choice's
    rows above) and within one drive on the five sensors' validation towns, the stage alone,
    and the rule that weighs the four figures alike, beside the option's own stage."""
    across = {x["first"]: x for x in load(ALIGNED)["val"]["rows"]}
    loaded = [(p, load(p)) for p in within]
    if len({r["model_id"] for _, r in loaded}) != len(loaded):
        raise ValueError(f"two reports of one file among {list(within)}")
    towns = {r["sequence"] for _, r in loaded}
    if len(towns) != 1:
        raise ValueError(f"the stages were scored on other towns: {towns}")
    names = ", ".join(f"`{t.strip().rsplit('/', 1)[-1]}`" for t in towns.pop().split(","))
    out = "".join(source(p, r["command"], when(r)) for p, r in loaded)
    out += (
        "\nOn val only. Across sensors: the calibration town's 25 pairs, R@1 mean and the 20 "
        f"across sensors' lowest (the choice above). Within one drive: {names}, scored as one "
        "curve, the first stage alone, F1max / Recall@1 (all revisits):\n\n"
    )
    rows, scores = [], {}
    for _, r in loaded:
        x, m = across[r["first_stage"]], r["summary"]
        four = (x["mean_r@1"], x["across_min_r@1"], m["f1max"], m["recall@1"])
        scores[r["first_stage"]] = float(sum(four) / len(four))
        rows.append(
            [
                f"{_first(r['first_stage'])} (`{r['model_id']}`)",
                f"{f3(x['mean_r@1'])} / {f3(x['across_min_r@1'])}",
                f"{f3(m['f1max'])} / {f3(m['recall@1'])}",
                f3(scores[r["first_stage"]]),
            ]
        )
    head = [
        "first stage",
        "across: R@1 mean / lowest",
        "within one drive: F1max / R@1",
        "mean of the four",
    ]
    pick = max(scores, key=lambda k: scores[k])
    option = load(RERANK_ANY)  # the option as shipped: its stage as its report records it
    out += table(head, rows)
    return out + (
        f"\nThe rule (the four val figures weighed alike) takes {_first(pick)}; the option "
        f"(`{option['model_id']}`, `{RERANK_ANY}`) carries {_first(option['first_stage'])}.\n"
    )


RENDERERS = {
    "yaw-spectrum": yaw_spectrum,
    "spectrum-aligned": spectrum_aligned,
    "first-stage-within": within_and_across,
}
