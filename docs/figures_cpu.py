"""The bird's-eye recipe from scratch on two CPU cores (``overlapmamba/train/cpu_recipes.py``):
the runs by epoch and where their time went, their picks on real scans, the first stage
chosen for them, and every bird's-eye file across sensors on the test town, each rendered
from the JSON a command wrote (``docs/render.py`` pastes them; nothing here types a measured
number)."""

from __future__ import annotations

from typing import Any

from figures_bev import BEV_GPU, _weight, pilot_epochs, real_table
from figures_kit import f3, load, source, table, when
from figures_pairs import _file_name, _label
from figures_spectrum import real_sets

# the recipe with the sparser-sensor term, two seeds
BEV_CPU_TERM = tuple(
    f"reports/model/{n}.json" for n in ("bev-span-thin-cpu", "bev-span-thin-cpu-s1")
)
# the same without the sparser-sensor term, two seeds
BEV_CPU_CONTROL = tuple(f"reports/model/{n}.json" for n in ("bev-span-cpu", "bev-span-cpu-s1"))
BEV_CPU_REAL = {
    f"`{run}`, its pick": (f"{run}-real-kitti", f"{run}-real-nuscenes")
    for run in ("bev-span-thin-cpu", "bev-span-thin-cpu-s1", "bev-span-cpu", "bev-span-cpu-s1")
} | {  # the calibration pairs' epoch (benchmarks/epoch_pairs.py)
    "`bev-span-thin-cpu`, the pairs' pick (epoch 10)": (
        "bev-span-thin-cpu-e10-real-kitti",
        "bev-span-thin-cpu-e10-real-nuscenes",
    ),
    "`bev-span-thin-cpu-s1`, the pairs' pick (epoch 9)": (
        "bev-span-thin-cpu-s1-e9-real-kitti",
        "bev-span-thin-cpu-s1-e9-real-nuscenes",
    ),
    "`bev-span-thin-cpu-more`, the pairs' pick (epoch 16)": (
        "bev-span-thin-cpu-more-e16-real-kitti",
        "bev-span-thin-cpu-more-e16-real-nuscenes",
    ),
}
# the CPU run's pick across sensors on the test town, beside the GPU-trained bird's-eye files
BEV_CPU_PAIRS = tuple(
    f"reports/model/across-pairs-{n}.json"
    for n in (
        "bev-span-thin-cpu",
        "bev-span-thin-cpu-e10",  # the calibration pairs' epoch (epoch_pairs.py)
        "bev-span-thin-cpu-e10-still",
        "bev-span-thin-cpu-more-e16",  # the run continued to 16 epochs, its pairs' pick
        "bev-span-thin-cpu-more-e16-still",
        "bev-span-thin-cpu-s1-more-e14",  # the second seed continued to 16 epochs, its pick
        "bev-span-thin-cpu-s1-more-e14-still",
        "bev-span-thin-cpu-first",
        "bev-span-thin-cpu-still",
        "bev-span-thin-cpu-s1",
        "bev-span-thin-cpu-s1-e9",  # its calibration pairs' epoch
        "bev-span-cpu",
        "bev-span-cpu-still",
        "bev-span-cpu-s1",
        "bev-long",
        "bev-span-thin",
        "bev-span-thin-first",
    )
)
BEV_CPU_SPECTRUM = "reports/model/yaw-spectrum-bev-span-thin-cpu.json"
# the first stage chosen again among the variants that keep still under a turn (--turn-floor)
BEV_CPU_STILL = {  # each run's report → the across-pairs report of the file it chose
    "reports/model/yaw-spectrum-bev-span-thin-cpu-still.json": (
        "reports/model/across-pairs-bev-span-thin-cpu-still.json"
    ),
    "reports/model/yaw-spectrum-bev-span-cpu-still.json": (
        "reports/model/across-pairs-bev-span-cpu-still.json"
    ),
    "reports/model/yaw-spectrum-bev-span-thin-cpu-e10.json": (
        "reports/model/across-pairs-bev-span-thin-cpu-e10-still.json"
    ),
    "reports/model/yaw-spectrum-bev-span-thin-cpu-more-e16.json": (
        "reports/model/across-pairs-bev-span-thin-cpu-more-e16-still.json"
    ),
    "reports/model/yaw-spectrum-bev-span-thin-cpu-s1-more-e14.json": (
        "reports/model/across-pairs-bev-span-thin-cpu-s1-more-e14-still.json"
    ),
}


def bev_cpu() -> str:
    """bev-span-thin-long's recipe from scratch at a 2-core budget (bev-span-thin-cpu) and its
    control without the term (bev-span-cpu): by epoch, where their time went, their picks on
    real scans, the first stages chosen for the first, every file across sensors."""
    start = (
        "\n`bev-span-thin-cpu-s1` is its second seed; `bev-span-cpu` is its control at the "
        "same budget: the same recipe without the term (`-s1`: its second seed). "
        "Beside them, `bev-long`'s epochs on a lent GPU (the same recipe on `bev`, without the "
        "term). Epoch 0 is the untrained network, batch norm recalibrated. "
    )

    def what(r: dict[str, Any]) -> str:
        where = "a lent GPU" if r.get("trained_on") else f"{r['machine']['cores']} CPU cores"
        return (
            f"input `{r['model_config']['sensor_input']}`, {_weight(r)}, seed "
            f"{r['train_config'].get('seed', 0)}, on {where}"
        )

    runs, out = pilot_epochs((*BEV_CPU_TERM, *BEV_CPU_CONTROL, BEV_GPU[0]), what, start)
    out += "\n" + _time_spent(runs[:-1]) + "\n" + real_table(BEV_CPU_REAL) + "\n"
    out += _spectrum_choice(BEV_CPU_SPECTRUM, BEV_CPU_PAIRS[1])
    out += "".join("\n" + _still_choice(p, written) for p, written in BEV_CPU_STILL.items())
    return out + "\n" + _pairs_summary(BEV_CPU_PAIRS)


def _time_spent(runs: list[dict[str, Any]]) -> str:
    """Run summaries → where each run's recorded time went, in minutes."""
    rows = []
    for r in runs:
        parts: dict[str, float] = {}
        for e in r["epochs"]:
            for k, v in e["seconds"].items():
                parts[k] = parts.get(k, 0.0) + v
        rows.append(
            [
                f"`{r['run'].split('/')[-1]}`",
                f"{r['epochs_run']} × {r['train_config']['epoch_scans']:,}",
                f"{r['seconds'] / 60:.0f}",
                *(f"{parts.get(k, 0.0) / 60:.0f}" for k in ("train", "mine", "validate")),
            ]
        )
    m = runs[0]["machine"]
    head = ["run", "epochs × scans", "minutes in all", "training steps", "mining", "validating"]
    return (
        f"\nWhere their time went ({m['cpu']}, {m['cores']} cores; validation is every epoch "
        "and epoch 0; the range images' cache, built once a machine, is not in it):\n\n"
        + table(head, rows)
    )


def _spectrum_choice(path: str, written: str) -> str:
    """A yaw-spectrum report → the first stage chosen on the calibration town, the file it
    was written into (``written``: that file's across-pairs report) and how far it and the
    descriptor move under continuous turns of real scans."""
    r, file = load(path), load(written)
    chosen = r["val"]["chosen"]
    turns = real_sets(r)
    moves = "; ".join(
        f"{name}: {v[chosen]['cosine_min']:.4f} (the descriptor's {d['cosine_min']:.4f})"
        for name, v in turns.items()
        for d in [v["descriptor"]]
    )
    return (
        source(path, r["command"], when(r))
        + f"\nThe first stage chosen for it on the calibration town `cal-x00` by mean R@1 over its "
        f"25 pairs: `{chosen}`, written into the file as its descriptor by `overlapmamba export "
        f"{r['model']} --first-stage {chosen} --out {file['model']}` "
        f"({_file_name(file)} below). The lowest cosine of a real scan's vector and its "
        f"turned copy's ({r['turns']['seeds']} random continuous turns, one pass a scan): "
        f"{moves}.\n"
    )


def _still_choice(path: str, written: str | None) -> str:
    """A yaw-spectrum report chosen with a turn floor → the choice, beside the descriptor and
    the best variant without the floor: on val (with how far each moves under a turn of the
    calibration town's scans), on test and under turns of real scans, and the file it was
    written into (``written``: that file's across-pairs report; ``None``: none was)."""
    r = load(path)
    val = {x["first"]: x for x in r["val"]["rows"]}
    test = {x["first"]: x for x in r["test"]["rows"]}
    turns = real_sets(r)
    rows = [
        [
            f"`{name}`" + (" (chosen)" if name == r["val"]["chosen"] else ""),
            f3(val[name]["mean_r@1"]),
            f"{val[name]['turn_min']:.5f}",
            f"{f3(t['mean_r@1'])}; {f3(t['across_mean_r@1'])} / {f3(t['across_min_r@1'])}",
            *(f"{v[name]['cosine_min']:.5f}" for v in turns.values()),
        ]
        for name, t in test.items()
    ]
    head = [
        "first stage",
        "val R@1 mean",
        "val turn, lowest cosine",
        "test R@1 mean; across: mean / lowest",
        *(f"{k}, lowest cosine" for k in turns),
    ]
    return (
        source(path, r["command"], when(r))
        + f"\n{_label(r)}: chosen again on `cal-x00`, by mean R@1 among the variants whose "
        f"lowest cosine under random continuous turns of that town's scans (every "
        f"{r['turn_stride']}th scan of each sensor's second drive, {r['turns']['seeds']} draws) "
        f"reaches {r['turn_floor']:g}: "
        f"`{r['val']['chosen']}` (without that condition: `{r['val']['unconstrained']}`), "
        + _written(r, written)
        + " Each measured on test and under turns of real scans (one pass a scan):\n\n"
        + table(head, rows)
    )


def _written(r: dict[str, Any], written: str | None) -> str:
    if written is None:
        return "not written into a file."
    file = load(written)
    return (
        f"written into the file by `overlapmamba export {r['model']} --first-stage "
        f"{r['val']['chosen']} --out {file['model']}` ({_file_name(file)} below)."
    )


def _pairs_summary(paths: tuple[str, ...]) -> str:
    """Across-pairs reports → one row per file and answer on the test town: AR@1 over the 20
    pairs across sensors (mean, lowest), over the five same-sensor pairs (mean), how many
    pairs meet the bar and how many lie above Scan Context on the same drives."""
    reports = [(p, load(p)) for p in paths]
    out = "".join(source(p, r["command"], when(r)) for p, r in reports)
    rows = []
    for _, r in reports:
        t = r["test"]
        for answer in ("descriptor", "two_stage"):
            v = t["verdict"][answer]
            same = [x[answer]["ar@1"] for x in t["pairs"] if x["queries"] == x["map"]]
            rows.append(
                [
                    f"{_file_name(r)} ({r['sensor_input']}"
                    + (
                        f", first stage {r['first_stage']})"
                        if r.get("first_stage") not in (None, "descriptor")
                        else ")"
                    ),
                    answer.replace("_", " "),
                    f"{f3(v['mean_ar@1'])} / {f3(v['min_ar@1'])}",
                    f3(sum(same) / len(same)),
                    f"{v['meeting_bar']} / {v['above_scan_context']}",
                ]
            )
    sc = reports[0][1]["test"]["verdict"]["scan_context"]
    head = [
        "file",
        "answer",
        "AR@1 across: mean / lowest",
        "AR@1 same sensor",
        "at the bar / above SC",
    ]
    return (
        out
        + "\nAcross sensors on the sensor test town (`python benchmarks/across_pairs.py --model "
        "FILE --split test`; 20 pairs across, a hit within 5 m; Scan Context on the same drives: "
        f"AR@1 mean {f3(sc['mean_ar@1'])}, lowest {f3(sc['min_ar@1'])}):\n\n" + table(head, rows)
    )


# every epoch of a run measured across sensors: the calibration town's pairs, and test's
EPOCH_PAIRS = tuple(
    f"reports/model/epoch-pairs-{n}.json"
    for n in (
        "bev-span-thin-cpu",
        "bev-span-thin-cpu-s1",
        "bev-span-cpu",
        "bev-span-thin-cpu-more",
        "bev-span-thin-cpu-s1-more",
        "bev-span-thin-cpu-more24",
    )
)


def epoch_pairs() -> str:
    """Epoch-pairs reports → for each run, every epoch's trainer score and descriptor AR@1 on
    the calibration town's pairs and the test town's, the two picks, and how well each score
    ranks the epochs as the test town does."""
    out = ""
    for path in EPOCH_PAIRS:
        r = load(path)
        picks = {r["trainer_best"]: "the trainer's pick", r["chosen"]: "the pairs' pick"}
        if r["trainer_best"] == r["chosen"]:
            picks = {r["chosen"]: "both picks"}
        tested = "rank_correlation_with_test_across" in r  # measured with --test
        rows = [
            [
                f"{e['epoch']}" + (f" ({picks[e['epoch']]})" if e["epoch"] in picks else ""),
                f3(e["trainer_score"]),
                f"{f3(e['val']['mean_ar@1'])}; {f3(e['val']['across_mean_ar@1'])}",
                *(
                    [
                        f"{f3(e['test']['mean_ar@1'])}; {f3(e['test']['across_mean_ar@1'])}"
                        f" / {f3(e['test']['across_min_ar@1'])}"
                    ]
                    if tested
                    else []
                ),
            ]
            for e in r["epochs"]
        ]
        head = ["epoch", "trainer's score (`val` F1max, renderings' mean)"]
        head += ["cal-x00 AR@1: 25 pairs; across"]
        name = r["run"].split("/")[-1]
        reused = (  # a continued run's first epochs, taken from its original's report
            f"; epochs {r['reused']['epochs'][0]} … {r['reused']['epochs'][-1]} are the same "
            "checkpoints as the run it continues, their rows taken from "
            f"`{r['reused']['report']}` (`--reuse`)"
            if "reused" in r
            else ""
        )
        if tested:
            rho = r["rank_correlation_with_test_across"]
            head += ["test AR@1: 25 pairs; across mean / lowest"]
            said = (
                f"\n`{name}`, every epoch's descriptor (one view, as `overlapmamba export` "
                "writes it) on the calibration town's pairs and on the test town's. Over its "
                f"{len(rows)} epochs Spearman's rank correlation with the test town's mean AR@1 "
                f"across sensors is {rho['trainer_score']:.2f} for the trainer's score and "
                f"{rho['pairs_mean_ar@1']:.2f} for the calibration pairs' mean{reused}:\n\n"
            )
        else:
            said = (
                f"\n`{name}`, every epoch's descriptor (one view, as `overlapmamba export` "
                "writes it) on the calibration town's pairs only (without `--test`: the two "
                "picks are measured on the test town in the table of files across sensors "
                f"above){reused}:\n\n"
            )
        out += source(path, r["command"], when(r)) + said + table(head, rows)
    return out


def _val_only(path: str, name: str, who: str) -> str:
    """One variant of a yaw-spectrum report on the calibration town only (no test row)."""
    x = {r["first"]: r for r in load(path)["val"]["rows"]}[name]
    return (
        f"\n`{name}` ({who}), on the calibration town over the same draws: val R@1 mean "
        f"{f3(x['mean_r@1'])}, lowest cosine under a turn {x['turn_min']:.5f}.\n"
    )


# the sixteen-epoch file's first stage chosen again with its turn floor over 20 draws of every
# fifth scan (the option's in the sensor's columns was chosen over 3): the stricter rule's pick
STILL_DRAWS = "reports/model/yaw-spectrum-bev-span-thin-cpu-more-e16-draws20.json"

RENDERERS = {
    "bev-cpu": bev_cpu,
    "epoch-pairs": epoch_pairs,
    "spectrum-draws": lambda: (
        _still_choice(STILL_DRAWS, None)
        + _val_only(STILL_DRAWS, "mixed:0.5:8:none", "the option's in the sensor's columns")
    ),
}
