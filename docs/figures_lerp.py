"""Tables on the inputs in training: the shipped network continued on five towns of five
sensors, other sensors' scans by ``elevation-lerp``, ``elevation-fill``, ``elevation-reach`` or
by the shipped ``elevation``, by epoch, then each run's pick on real scans; each rendered
from the JSON a command wrote (``docs/render.py`` pastes them; nothing here types a measured
number)."""

from __future__ import annotations

from figures_bev import pilot_epochs, real_table
from figures_kit import f3, load, source, table, when

LERP_RUNS = tuple(
    f"reports/model/{n}.json" for n in ("lerp-towns-pilot", "lerp-towns-pilot-control")
)
# each run's pick → its eval-real reports on KITTI 00 and on nuScenes
LERP_REAL = {
    "the shipped weights, one view (elevation-lerp)": (
        "lerp-start-real-kitti",
        "lerp-start-real-nuscenes",
    ),
    "`lerp-towns-pilot`, its pick (elevation-lerp)": (
        "lerp-pilot-real-kitti",
        "lerp-pilot-real-nuscenes",
    ),
    "the shipped weights, one view (elevation)": (
        "lerp-control-start-real-kitti",
        "lerp-control-start-real-nuscenes",
    ),
    "`lerp-towns-pilot-control`, its pick (elevation)": (
        "lerp-control-real-kitti",
        "lerp-control-real-nuscenes",
    ),
}
START = (
    "\nEpoch 0 is the shipped network (its batch norm frozen, as in both runs), other "
    "sensors' scans taken by the run's input. "
)


def pilot_by_input(runs: tuple[str, ...], real: dict[str, tuple[str, str]]) -> str:
    """Continuations that differ in their input, by epoch, then each one's pick on real
    scans (``real``: row label → its eval-real reports on KITTI 00 and on nuScenes)."""
    _, out = pilot_epochs(runs, lambda r: f"input `{r['model_config']['sensor_input']}`", START)
    return out + "\n" + real_table(real)


def lerp_pilot() -> str:
    """The two continuations by epoch, then each one's pick on real scans."""
    return pilot_by_input(LERP_RUNS, LERP_REAL)


LERP_TEST = tuple(
    f"reports/model/{n}-test.json" for n in ("lerp-towns-pilot", "lerp-towns-pilot-control")
)


def lerp_pilot_test() -> str:
    """Each run's start and pick on the sensor test town, scored as the trainer scores val."""
    return pilot_test(LERP_TEST)


def pilot_test(paths: tuple[str, ...]) -> str:
    """The renderings_test reports ``paths``: each checkpoint on the sensor test town."""
    reports = [(p, load(p)) for p in paths]
    out = "".join(source(p, r["command"], when(r)) for p, r in reports)
    names = list(reports[0][1]["checkpoints"][0]["renderings"])
    rows = []
    for _, r in reports:
        for c in r["checkpoints"]:
            d, sens = c["drive"]["all"], c["renderings"]
            rows.append(
                [
                    f"`{c['checkpoint']}` (epoch {c['epoch']})",
                    f"`{c['sensor_input']}`",
                    f"{c['score']:.3f}",
                    f"{f3(d['f1max'])} / {f3(d['recall@1'])}",
                    *(
                        f"{f3(sens[n]['cross']['all']['f1max'])} / "
                        f"{f3(sens[n]['cross']['all']['recall@1'])}"
                        for n in names
                    ),
                    " / ".join(f3(sens[n]["own"]["all"]["f1max"]) for n in names),
                ]
            )
    head = [
        "checkpoint",
        "input",
        "score",
        "drive F1max / R@1",
        *(f"{n} across, F1max / R@1" for n in names),
        f"own F1max ({' / '.join(names)})",
    ]
    drive = reports[0][1]["drive"].split("/")[-1]
    return (
        out
        + f"\nThe sensor test town (`{drive}` and its renderings), scored as the trainer scores "
        "`val` (one view a scan; the score is the mean F1max over the drive and every "
        "rendering's own and across scores).\n\n" + table(head, rows)
    )


# The fill and reach continuations (overlapmamba/train/fill_recipes.py) beside their control at
# an equal budget, lerp-towns-pilot-control (the same continuation by the shipped input).
FILL_NAMES = ("fill-towns-pilot", "reach-towns-pilot", "lerp-towns-pilot-control")
FILL_RUNS = tuple(f"reports/model/{n}.json" for n in FILL_NAMES)
FILL_REAL = {
    "the shipped weights, one view (elevation)": (
        "lerp-control-start-real-kitti",
        "lerp-control-start-real-nuscenes",
    ),
    "the shipped weights, one view (elevation-fill)": (
        "fill-start-real-kitti",
        "fill-start-real-nuscenes",
    ),
    "`fill-towns-pilot`, its pick (elevation-fill)": (
        "fill-pilot-real-kitti",
        "fill-pilot-real-nuscenes",
    ),
    "the shipped weights, one view (elevation-reach)": (
        "reach-start-real-kitti",
        "reach-start-real-nuscenes",
    ),
    "`reach-towns-pilot`, its pick (elevation-reach)": (
        "reach-pilot-real-kitti",
        "reach-pilot-real-nuscenes",
    ),
    "`lerp-towns-pilot-control`, its pick (elevation)": (
        "lerp-control-real-kitti",
        "lerp-control-real-nuscenes",
    ),
}
FILL_TEST = tuple(f"reports/model/{n}-test.json" for n in FILL_NAMES)


def fill_pilot() -> str:
    """The fill and reach continuations and their control by epoch, then each pick on real
    scans."""
    return pilot_by_input(FILL_RUNS, FILL_REAL)


def fill_pilot_test() -> str:
    """The fill and reach continuations' and their control's start and pick on the sensor
    test town."""
    return pilot_test(FILL_TEST)


RENDERERS = {
    "lerp-pilot": lerp_pilot,
    "lerp-pilot-test": lerp_pilot_test,
    "fill-pilot": fill_pilot,
    "fill-pilot-test": fill_pilot_test,
}
