"""Tables on the cut at 50 m made a training augmentation (``cut-towns-pilot``, the
``range_cut`` of :mod:`overlapmamba.train.augment`) instead of an input (``elevation-reach``),
and the reach continuation's second seed: by epoch on ``val``, each pick on the sensor test
town, across every pair of sensors and on real scans; each rendered from the JSON a command
wrote (``docs/render.py`` pastes them; nothing here types a measured number)."""

from __future__ import annotations

from typing import Any

from figures_bev import pilot_epochs, real_table
from figures_fill import PAIRS, trained_pairs
from figures_kit import f3, load, source, table, when
from figures_lerp import pilot_test

# the control (fill), the cut made an augmentation and the cut at the input, each by two seeds
CUT_NAMES = (
    "fill-towns-pilot",
    "cut-towns-pilot",
    "cut-towns-pilot-s1",
    "reach-towns-pilot",
    "reach-towns-pilot-s1",
)
CUT_RUNS = tuple(f"reports/model/{n}.json" for n in CUT_NAMES)
CUT_REAL = {
    "`fill-towns-pilot`, its pick (elevation-fill)": (
        "fill-pilot-real-kitti",
        "fill-pilot-real-nuscenes",
    ),
    "`cut-towns-pilot`, its pick (elevation-fill)": (
        "cut-pilot-real-kitti",
        "cut-pilot-real-nuscenes",
    ),
    "`reach-towns-pilot`, its pick (elevation-reach)": (
        "reach-pilot-real-kitti",
        "reach-pilot-real-nuscenes",
    ),
    "`reach-towns-pilot-s1`, its pick: its start, the shipped weights (elevation-reach)": (
        "reach-start-real-kitti",
        "reach-start-real-nuscenes",
    ),
}
# the two runs' test reports hold both starts (the fill and the reach input's) and their picks;
# the cut run's holds its pick (its start is the fill run's); reach-s1 keeps its start
CUT_TEST = tuple(
    f"reports/model/{n}-test.json"
    for n in ("fill-towns-pilot", "reach-towns-pilot", "cut-towns-pilot")
)
# the shipped weights by each input (the reach one is reach-s1's pick), then the three picks
CUT_PAIRS = (
    *PAIRS,
    *(
        f"reports/model/across-pairs-{n}.json"
        for n in ("fill-towns-pilot", "reach-towns-pilot", "cut-towns-pilot", "cut-towns-pilot-s1")
    ),
)


START = (
    "\nEpoch 0 is the shipped network (its batch norm frozen, as in every run here), other "
    "sensors' scans taken by the run's input. "
)


def _plan(r: dict[str, Any]) -> str:
    cut = r["train_config"].get("augment", {}).get("range_cut", 0.0)
    return f"input `{r['model_config']['sensor_input']}`, seed {r['train_config']['seed']}" + (
        f", range_cut {cut:g}" if cut else ""
    )


def cut_pilot() -> str:
    """The four continuations by epoch on val, then each pick on real scans."""
    _, out = pilot_epochs(CUT_RUNS, _plan, START)
    return out + "\n" + real_table(CUT_REAL)


def cut_pilot_test() -> str:
    """Each run's start and pick on the sensor test town, scored as the trainer scores val."""
    return pilot_test(CUT_TEST)


def across_pairs_cut() -> str:
    """Each pick across sensors on the test town (three views a scan, as the service runs
    them), beside the shipped weights by each input; the cut runs' picks pair by pair."""
    return trained_pairs(CUT_PAIRS, CUT_PAIRS[-2:])


CUT_MARGIN = tuple(f"reports/model/cut-margin-{s}.json" for s in ("val", "test"))


def cut_margin() -> str:
    """Each sensor's scans against the car's of the same frame and of other places, uncut
    and cut at 50 m, with the shipped weights, on val and test."""
    reports = [(p, load(p)) for p in CUT_MARGIN]
    out = "".join(source(p, r["command"], when(r)) for p, r in reports)
    r0 = reports[0][1]
    out += (
        f"\nThe shipped weights ({r0['views']} views a scan), every {r0['step']}th frame of "
        "each drive: a rendering's scan against the car's scan of the same frame (paired), of "
        "a frame half the drive on (unrelated), and the nearest car scan of another place "
        f"(more than {r0['hit_m']:g} m away), medians; Recall@1: the nearest car scan among "
        f"the sampled frames lies within {r0['hit_m']:g} m.\n\n"
    )
    rows = []
    for _, r in reports:
        by = {(x["sensor"], x["input"]): x for x in r["rows"]}
        for sensor in dict.fromkeys(x["sensor"] for x in r["rows"]):
            for mode in ("elevation-fill", "elevation-reach"):
                x = by[(sensor, mode)]
                rows.append(
                    [
                        r["split"],
                        sensor,
                        f"`{mode}`",
                        f3(x["paired"]),
                        f3(x["unrelated"]),
                        f3(x["nearest_wrong"]),
                        f3(x["recall@1"]),
                    ]
                )
    head = ["split", "sensor", "input", "paired", "unrelated", "nearest other place", "Recall@1"]
    return out + table(head, rows)


RENDERERS = {
    "cut-margin": cut_margin,
    "cut-pilot": cut_pilot,
    "cut-pilot-test": cut_pilot_test,
    "across-pairs-cut": across_pairs_cut,
}
