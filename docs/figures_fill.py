"""Tables on one-column gaps in other sensors' images (the ``elevation-fill`` and
``elevation-reach`` inputs): what the gaps are and what filling them does to a frame's
descriptor (``benchmarks/fill_gaps.py``), every pair across sensors with the shipped weights
taking each input and the continuations trained on filled images
(``benchmarks/across_pairs.py``), and real scans (``eval-real``); each
rendered from the JSON a command wrote (``docs/render.py`` pastes them; nothing here types a
measured number)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from figures_bev import real_table
from figures_kit import f3, load, source, table, when
from figures_pairs import pair_tables

FILL_GAPS = tuple(f"reports/model/fill-gaps-{s}.json" for s in ("val", "test"))
PAIRS = (
    "reports/model/across-pairs.json",
    "reports/model/across-pairs-fill.json",
    "reports/model/across-pairs-reach.json",
)
REAL = {
    "the shipped file (`elevation`)": ("real-shipped-kitti", "real-shipped-nuscenes"),
    "`elevation-fill`": ("real-fill-kitti", "real-fill-nuscenes"),
    "`elevation-reach`": ("real-reach-kitti", "real-reach-nuscenes"),
}
TRAINED_RUNS = ("fill-towns-pilot", "reach-towns-pilot")
WAYS = ("elevation", "elevation-fill", "fill-every-sensor")


def fill_gaps() -> str:
    """Per rendering, the gap share and the paired cosine three ways; the car's own cost."""
    reports = [(p, load(p)) for p in FILL_GAPS]
    out = "".join(source(p, r["command"], when(r)) for p, r in reports)
    for _, r in reports:
        rows = [
            [
                f"`{x['rendering']}`",
                str(x["columns"]),
                f3(x["gap_share"]),
                *(f3(x[w]) for w in WAYS),
            ]
            for x in r["rows"]
        ]
        rows.append(["mean", "", "", *(f3(r["mean"][w]) for w in WAYS)])
        own = r["car_loop_closure"]
        out += (
            f"\n{r['split']} (`{r['car']}`, {r['frames']} frames, {r['views']} views a scan "
            "as served), the median cosine between a frame's descriptor and the car's of that "
            "frame:\n\n"
        )
        out += table(
            ["rendering", "columns a turn", "one-column gaps (share of cells)", *WAYS], rows
        )
        out += (
            f"\nThe car's own scans: one-column gaps {f3(r['car_gap_share'])} of the cells; a "
            f"frame against one half a drive away {f3(r['car_far_cosine'])}; filled against "
            f"plain {f3(r['car_filled_to_plain_cosine'])}. Its drive's loop closure (the "
            f"descriptor alone, F1max / R@1) plain {f3(own['plain']['f1max'])} / "
            f"{f3(own['plain']['recall@1'])}, filled {f3(own['filled']['f1max'])} / "
            f"{f3(own['filled']['recall@1'])}. "
            + (
                "The pick"
                if r["split"] == "val"
                else "What the same rule picks here, reported only"
            )
            + " (the highest mean among the ways that keep the car's own F1max and R@1): "
            f"`{r['pick']}`.\n"
        )
    return out


def _input(r: dict[str, Any]) -> str:
    return f"`{r['sensor_input']}`"


def pairs_summary(
    split: str,
    reports: list[tuple[str, dict[str, Any]]],
    label: Callable[..., str] = _input,
    first: str = "input",
) -> str:
    rows = []
    for _, r in reports:
        v = r[split]["verdict"]
        same = {p["queries"]: p for p in r[split]["pairs"] if p["queries"] == p["map"]}
        cells = [
            f"{f3(v[a]['mean_ar@1'])} / {f3(v[a]['min_ar@1'])} / {v[a]['meeting_bar']} / "
            f"{v[a]['above_scan_context']}"
            for a in ("descriptor", "two_stage")
        ]
        hdl = same["kitti-hdl64"]
        rows.append(
            [
                label(r),
                *cells,
                f"{f3(hdl['descriptor']['ar@1'])} / {f3(hdl['two_stage']['ar@1'])}",
            ]
        )
    sc = reports[0][1][split]["verdict"]["scan_context"]
    head = [
        first,
        "descriptor alone: mean / lowest / at the bar / above Scan Context",
        "two stages: mean / lowest / at the bar / above Scan Context",
        "HDL-64E on its own map, AR@1 descriptor / two stages",
    ]
    return (
        table(head, rows)
        + f"\nScan Context on the same drives: mean {f3(sc['mean_ar@1'])}, lowest "
        f"{f3(sc['min_ar@1'])}.\n"
    )


def across_pairs_fill() -> str:
    """The shipped weights taking each input, all 20 pairs across sensors summed up on val
    (where the input is chosen) and test, then the test matrices of the two new inputs."""
    reports = [(p, load(p)) for p in PAIRS]
    out = "".join(source(p, r["command"], when(r)) for p, r in reports)
    out += (
        "\nThe shipped weights (three views a scan) taking each input; over the 20 pairs "
        "across sensors, AR@1 (a hit within 5 m) mean / lowest / pairs at the bar (≥ 0.85 and "
        "above Scan Context) / pairs above Scan Context:\n"
    )
    for split, title in (
        ("val", "val (calibration town `cal-x00`, where the input is chosen)"),
        ("test", "test (the sensor test town)"),
    ):
        out += f"\n{title}:\n\n" + pairs_summary(split, reports)
    out += "\ntest, pair by pair:\n"
    for _, r in reports[1:]:
        out += pair_tables(r, "test", with_sc=False)
    return out


# the shipped weights by each input (the first three), then the fill and reach continuations
TRAINED = (*PAIRS, *(f"reports/model/across-pairs-{n}.json" for n in TRAINED_RUNS))


def model_label(r: dict[str, Any]) -> str:
    name = r["model"].split("/")[-1].removesuffix(".onnx")
    return f"`{name}` (`{r['sensor_input']}`)"


def trained_pairs(paths: tuple[str, ...], matrices: tuple[str, ...]) -> str:
    """The across-pairs reports ``paths`` summed up on the test town (three views a scan),
    then pair by pair those among ``matrices``."""
    reports = [(p, load(p)) for p in paths]
    out = "".join(source(p, r["command"], when(r)) for p, r in reports)
    out += (
        "\nThe sensor test town, three views a scan; over the 20 pairs across sensors, AR@1 (a "
        "hit within 5 m) mean / lowest / pairs at the bar (≥ 0.85 and above Scan Context) / "
        "pairs above Scan Context:\n\n"
        + pairs_summary("test", reports, model_label, "file (input)")
    )
    out += "\ntest, pair by pair:\n"
    for p, r in reports:
        if p in matrices:
            out += pair_tables(r, "test", with_sc=False)
    return out


def across_pairs_trained() -> str:
    """The fill and reach continuations' picks across sensors on the test town, beside the
    shipped weights taking each input (the selection was the trainer's, on val)."""
    return trained_pairs(TRAINED, TRAINED[len(PAIRS) :])


def fill_real() -> str:
    """Real scans: KITTI 00 (and its thinned queries) and nuScenes' HDL-32E, per input."""
    return real_table(REAL, described="three views")


RENDERERS = {
    "fill-gaps": fill_gaps,
    "across-pairs-fill": across_pairs_fill,
    "fill-real": fill_real,
    "across-pairs-trained": across_pairs_trained,
}
