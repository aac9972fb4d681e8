"""Tables on the bird's-eye inputs (``bev``, ``bev-soft``, ``bev-span``): their layouts, the
networks trained on them and the pilots that continued those (the sensor term's weight, its
seeds, more data, more steps), how they read real scans and other sensors, each rendered
from the JSON a command wrote (``docs/render.py`` pastes them; nothing here types a
measured number)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from figures_input import (
    EPOCH_COLUMNS,
    STRUCTURE_BEAMS,
    beams_table,
    epoch_rows,
    gpu_runs,
    planned,
    real_scans,
)
from figures_kit import f3, load, source, table, when

BEV_INPUT = "reports/model/bev-input.json"
BEV_GPU = tuple(f"reports/model/{n}.json" for n in ("bev-long", "structure-all-rows-long"))
BEV_BEAMS = "reports/model/bev-beams.json"
BEV_PILOT = tuple(f"reports/model/{n}.json" for n in ("bev-thin-pilot", "bev-thin-pilot-control"))
BEV_SOFT_RUNS = tuple(
    f"reports/model/{n}.json"
    for n in (
        "bev-soft-pilot",
        "bev-span-pilot",
        "bev-thin-pilot-control",
        "bev-span-thin-pilot",
        "bev-thin-pilot",
    )
)
# each network → its eval-real reports on KITTI 00 and on nuScenes
SPAN_THIN_REAL = ("bev-span-thin-real-kitti", "bev-span-thin-real-nuscenes")
BEV_SOFT_REAL = {
    "`bev-long` (bev)": ("bev-real-kitti", "bev-real-nuscenes"),
    "`bev-thin-pilot-control`, epoch 1 (bev)": (
        "bev-control-real-kitti",
        "bev-control-real-nuscenes",
    ),
    "`bev-soft-pilot`, epoch 1 (bev-soft)": ("bev-soft-real-kitti", "bev-soft-real-nuscenes"),
    "`bev-span-pilot`, epoch 1 (bev-span)": ("bev-span-real-kitti", "bev-span-real-nuscenes"),
    "`bev-thin-pilot`, epoch 1 (bev, sensor term)": (
        "bev-thin-real-kitti",
        "bev-thin-real-nuscenes",
    ),
    "`bev-span-thin-pilot`, epoch 1 (bev-span, sensor term)": SPAN_THIN_REAL,
    "`bev-span-pilot`, epoch 0, the run's pick (bev-span)": (
        "bev-span-best-real-kitti",
        "bev-span-best-real-nuscenes",
    ),
}
BEV_HEAVY_RUNS = tuple(
    f"reports/model/{n}.json" for n in ("bev-span-thin-pilot", "bev-span-heavy-pilot")
)
BEV_HEAVY_REAL = {
    "`bev-span-thin-pilot`, epoch 1 (sensor term weight 1)": SPAN_THIN_REAL,
    "`bev-span-heavy-pilot`, epoch 1 (sensor term weight 4)": (
        "bev-span-heavy-real-kitti",
        "bev-span-heavy-real-nuscenes",
    ),
}
# (control, with the sensor term) for seed 0 and seed 1
BEV_SPAN_SEEDS = tuple(
    (f"reports/model/bev-span-pilot{s}.json", f"reports/model/bev-span-thin-pilot{s}.json")
    for s in ("", "-s1")
)
BEV_RENDERS_RUNS = tuple(
    f"reports/model/{n}.json"
    for n in ("bev-span-thin-pilot", "bev-span-thin-pilot-s1", "bev-span-renders-pilot")
)
BEV_MORE_RUNS = tuple(
    f"reports/model/{n}.json" for n in ("bev-span-thin-pilot", "bev-span-thin-more")
)
BEV_MORE_REAL = {
    "`bev-span-thin-pilot`, epoch 1 (one epoch)": SPAN_THIN_REAL,
    "`bev-span-thin-more`, epoch 1 (two epochs)": (
        "bev-span-thin-more-real-kitti",
        "bev-span-thin-more-real-nuscenes",
    ),
}
BEV_SPAN_BEAMS = "reports/model/bev-span-beams.json"
BEV_SPAN_THIN_BEAMS = "reports/model/bev-span-thin-beams.json"
BEV_REAL = {
    "reports/model/bev-real-kitti.json": "KITTI 00, frames 0–100",
    "reports/model/bev-real-nuscenes.json": "nuScenes scene-0061",
}


START = "\nEpoch 0 is `bev-long`'s network, batch norm recalibrated. "


def _name(r: dict[str, Any]) -> str:
    return f"`{r['run'].split('/')[-1]}`"


def pilot_epochs(
    paths: tuple[str, ...], what: Callable[[dict[str, Any]], str], start: str = START
) -> tuple[list[dict[str, Any]], str]:
    """The run reports ``paths`` → (the reports, their sources, what epoch 0 is
    (``start``), each run's plan (``what`` it is) and a table of every run's epochs)."""
    runs = [load(path) for path in paths]
    out = "".join(source(p, r["command"], when(r)) for p, r in zip(paths, runs, strict=True))
    out += start + EPOCH_COLUMNS + "".join(planned(r, what(r)) for r in runs)
    head, rows = epoch_rows(runs, _name)
    return runs, out + "\n" + table(["run", *head], rows)


def _weight(r: dict[str, Any]) -> str:
    return f"sensor term weight {r['train_config']['look_weight']:g}"


def bev_gpu() -> str:
    """The bev input and the structure input with every row reaching the descriptor, side by
    side on a lent GPU, on structure-towns' five towns."""
    return gpu_runs(BEV_GPU)


def bev_real() -> str:
    """The best bev network on real scans, as :func:`structure_real`."""
    return real_scans(BEV_REAL)


def bev_beams() -> str:
    """The best bev network across sensors on the sensor test town, beside the best
    structure network, the shipped weights and Scan Context on the same pairs."""
    return beams_table([BEV_BEAMS, STRUCTURE_BEAMS])


def bev_pilot() -> str:
    """bev-long's network continued for one short epoch with the sparser-sensor term, and
    without it (the control)."""
    return pilot_epochs(BEV_PILOT, _weight)[1]


def bev_input() -> str:
    """Layouts of a polar bird's-eye view scored by a hand-made spectrum, each sensor's
    scans against its own and against the HDL-64E's, on the validation drive."""
    r = load(BEV_INPUT)
    out = source(BEV_INPUT, r["command"], when(r))
    others = [s for s in r["data"] if s != "kitti-hdl64"]
    out += (
        f"\nDescriptor: {r['descriptor']} (no network). F1max of each sensor's scans against its "
        "own earlier scans (own) and against the HDL-64E's (across), on `val-kitti-hdl64` and "
        "its renderings.\n\n"
    )
    rows = []
    for lay in r["layouts"]:
        rows.append(
            [
                lay["name"],
                " / ".join(f"{b:g}" for b in lay["bands_m"]),
                str(lay["rings"]),
                f3(lay["kitti-hdl64"]["own"]["f1max"]),
                *(f"{f3(lay[s]['own']['f1max'])} / {f3(lay[s]['cross']['f1max'])}" for s in others),
                f"{f3(lay['mean_own_f1max'])} / {f3(lay['mean_cross_f1max'])}",
            ]
        )
    head = ["layout", "band edges (m)", "rings", "kitti-hdl64 own"]
    head += [f"{s} own / across" for s in others] + ["mean own / across"]
    return out + table(head, rows)


def bev_soft() -> str:
    """bev-long's network continued for one short epoch on the bev-soft and bev-span inputs
    and on bev (the control), and on bev-span and bev with the sparser-sensor term, by epoch;
    then each on real scans under random continuous turns."""
    _, out = pilot_epochs(
        BEV_SOFT_RUNS, lambda r: f"input `{r['model_config']['sensor_input']}`, " + _weight(r)
    )
    return out + "\n" + real_table(BEV_SOFT_REAL)


def real_table(networks: Mapping[str, tuple[str, ...]], described: str = "one view") -> str:
    """Each network's eval-real reports (label → report names): invariance under random
    continuous turns, odd → even retrieval, and thinned queries against whole scans;
    ``described``: how the networks describe a scan (the cosine column says)."""
    real = {
        label: [(f"reports/model/{n}.json", load(f"reports/model/{n}.json")) for n in names]
        for label, names in networks.items()
    }
    out = "".join(source(p, r["command"], when(r)) for rs in real.values() for p, r in rs)
    rows = []
    for label, reports in real.items():
        for _, r in reports:
            y, q = r["yaw_invariance"], r["retrieval_odd_to_even"]
            thin = r.get("thinned", {}).values()
            rows.append(
                [
                    label,
                    f"{r['sensor']} ({r['scans']} scans)",
                    f"{y['cosine_min']:.5f} / {y['cosine_mean']:.5f}",
                    f"{y['turned_over_one_metre_step']:.3f}",
                    f"{f3(q['recall@1'])} / {f3(q['scan_context']['recall@1'])}",
                    " / ".join(f3(t["declared"]["recall@1"]) for t in thin) or "—",
                    " / ".join(f3(t["declared"]["cosine_to_full"]["median"]) for t in thin) or "—",
                ]
            )
    head = [
        "network",
        "scans",
        f"cosine under random turns, min / mean ({described})",
        "turned copy / 1 m step",
        "odd→even R@1 / Scan Context's",
        "thinned to 32 / 16 rings, R@1",
        "thinned to 32 / 16, median cosine to the whole scan",
    ]
    return out + "\n" + table(head, rows)


def bev_span_beams() -> str:
    """The picks of the bev-span pilots (with and without the sparser-sensor term) across
    sensors on the sensor test town, beside bev-long (on bev), the shipped weights and Scan
    Context on the same pairs."""
    return beams_table([BEV_SPAN_THIN_BEAMS, BEV_SPAN_BEAMS, BEV_BEAMS])


def bev_heavy() -> str:
    """bev-span-thin-pilot and the same with the sparser-sensor term four times as heavy:
    by epoch, then each one's epoch 1 on real scans."""
    return pilot_epochs(BEV_HEAVY_RUNS, _weight)[1] + "\n" + real_table(BEV_HEAVY_REAL)


def bev_span_seeds() -> str:
    """bev-span-pilot and bev-span-thin-pilot with seeds 0 and 1: each run's epoch 1, the
    term's difference from its control by seed, and that difference's mean."""
    pairs = [tuple(load(p) for p in pair) for pair in BEV_SPAN_SEEDS]
    paths = [p for pair in BEV_SPAN_SEEDS for p in pair]
    runs = [r for pair in pairs for r in pair]
    out = "".join(source(p, r["command"], when(r)) for p, r in zip(paths, runs, strict=True))
    names = list(runs[0]["epochs"][0]["val_sensors"])

    def values(r: dict[str, Any]) -> list[float]:
        e = next(e for e in r["epochs"] if e["epoch"] == 1)
        cross = [e["val_sensors"][n]["cross"]["f1max"] for n in names]
        return [e["score"], e["val"]["all"]["f1max"], *cross]

    rows, gains = [], []
    for seed, (control, term) in enumerate(pairs):
        a, b = values(control), values(term)
        gains.append([y - x for x, y in zip(a, b, strict=True)])
        for r, v in ((control, a), (term, b)):
            rows.append([str(seed), _name(r), *map(f3, v)])
        rows.append([str(seed), "term − control", *(f"{g:+.3f}" for g in gains[-1])])
    mean = [sum(col) / len(col) for col in zip(*gains, strict=True)]
    rows.append(["both", "term − control, mean", *(f"{g:+.3f}" for g in mean)])
    head = ["seed", "run (epoch 1)", "score", "val F1max", *[f"{n} across" for n in names]]
    return out + "\n" + table(head, rows)


def bev_renders() -> str:
    """bev-span-thin-pilot (both seeds) and the same with train-b's renderings by three
    other sensors in its data, by epoch."""
    runs, out = pilot_epochs(BEV_RENDERS_RUNS, lambda r: f"seed {r['train_config']['seed']}")
    out += "\nEpoch 1's health numbers, the epoch's mean (`d(q,p)`, `d(q,n)`: squared distances "
    out += "to positives and negatives; active: the share of hinges that still cost):\n\n"
    keys = ("d_pos", "d_neg", "separation", "active")
    health = [
        [_name(r), *(f3(e["health"][k]) for k in keys)]
        for r in runs
        for e in r["epochs"]
        if e["epoch"] == 1
    ]
    return out + table(["run", "d(q,p)", "d(q,n)", "separation", "active"], health)


def bev_more() -> str:
    """bev-span-thin-pilot and its pick continued for a second short epoch by the same
    recipe: by epoch, then each one's last epoch on real scans."""
    start = (
        "\nEpoch 0 is the network the run starts from (`bev-long`'s, then "
        "`bev-span-thin-pilot`'s pick), batch norm recalibrated. "
    )
    _, out = pilot_epochs(
        BEV_MORE_RUNS, lambda r: f"starts from `{r['train_config']['init']}`", start
    )
    return out + "\n" + real_table(BEV_MORE_REAL)


RENDERERS = {
    "bev-input": bev_input,
    "bev-gpu": bev_gpu,
    "bev-real": bev_real,
    "bev-beams": bev_beams,
    "bev-pilot": bev_pilot,
    "bev-soft": bev_soft,
    "bev-span-beams": bev_span_beams,
    "bev-heavy": bev_heavy,
    "bev-span-seeds": bev_span_seeds,
    "bev-renders": bev_renders,
    "bev-more": bev_more,
}
