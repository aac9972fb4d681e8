"""Issue 40's training runs on several sensors (the pilots' reports), mounted renderings,
sensor alignment and the sensor-like inputs (``docs/figures_kit.py`` says how the tables are
made)."""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

from figures_kit import ROOT, f3, load, source, table, when

# The runs of issue 40 on several sensors (reports/model/sensors-pilot/NAME.json), in order:
# the report's name and what the run was.
SENSOR_RUNS = (
    ("shipped-1view", "the shipped network, one view"),
    (
        "shipped-1view-maps",
        "the shipped network, one view, with sensor maps fitted on four calibration towns",
    ),
    ("tokens", "the shipped network, three views met at the tokens (its twin file)"),
    ("pilot", "`sensors-pilot`: train-b and three renderings, beam_dropout"),
    ("pilot-s1", "`sensors-pilot-s1` (seed 1)"),
    ("control", "`sensors-pilot-control`: train-b alone, beam_dropout"),
    ("control-s1", "`sensors-pilot-control-s1` (seed 1)"),
    ("seen", "`sensors-seen`: train-b alone, sensor_like"),
    ("seen-s1", "`sensors-seen-s1` (seed 1)"),
    ("seen-look", "`sensors-seen-look`: sensor_like and the sensor term"),
    ("seen-look-s1", "`sensors-seen-look-s1` (seed 1)"),
    ("seen-look-light", "`sensors-seen-look-light`: the sensor term at weight 0.3"),
    ("seen-far", "`sensors-seen-far`: sensor_like and far_loss"),
    ("seen-far-s1", "`sensors-seen-far-s1` (seed 1)"),
    ("towns", "`sensors-towns`: train-b and six drawn towns of other sensors, sensor_like"),
    ("towns-s1", "`sensors-towns-s1` (seed 1)"),
    ("towns-car", "`sensors-towns-car`: the same six towns, every sensor on a car, level"),
    ("towns-car-s1", "`sensors-towns-car-s1` (seed 1)"),
)
SENSOR_QUERIES = ("kitti-hdl64", "vlp16", "os0-128", "xt32")
QUICK = "--only test-kitti-hdl64 --no-real --no-verify --out reports/model/sensors-pilot/NAME.json"


def sensor_runs() -> str:
    """One row per run: the same-sensor test town and the second drives of other sensors
    against its map, each from the run's own report."""
    folder = "reports/model/sensors-pilot"
    head = ["run", "descriptor F1max / R@1", "two stages F1max", *SENSOR_QUERIES]
    rows = []
    sc: dict[str, Any] | None = None
    for name, what in SENSOR_RUNS:
        path = ROOT / folder / f"{name}.json"
        if not path.is_file():
            continue
        r = json.loads(path.read_text())
        same = r["same_sensor"][0]
        across = {
            a["query_sensor"]: a for a in r["across_sensors"] if a["map_sensor"] == "kitti-hdl64"
        }
        row = [what, f"{f3(same['descriptor']['f1max'])} / {f3(same['descriptor']['recall@1'])}"]
        row.append(f3(same["two_stage"]["f1max"]))
        for q in SENSOR_QUERIES:
            a = across.get(q)
            row.append(
                f"{f3(a['descriptor']['ar@1'])} / {f3(a['two_stage']['ar@1'])}" if a else "—"
            )
        rows.append(row)
        sc = sc or {"same": same["scan_context"], "across": across}
    if sc is not None:
        row = ["Scan Context", f"{f3(sc['same']['f1max'])} / {f3(sc['same']['recall@1'])}", "—"]
        for q in SENSOR_QUERIES:
            a = sc["across"].get(q)
            row.append(f3(a["scan_context"]["ar@1"]) if a else "—")
        rows.append(row)
    return (
        source(f"{folder}/NAME.json", f"python benchmarks/sensors.py --model NAME.onnx {QUICK}")
        + "\nThe test town by its own sensor (loop closure: F1max / Recall@1), then a second "
        "drive by each sensor queried against that town's map (AR@1, a hit within 5 m: "
        "descriptor alone / two stages; Scan Context: its own).\n\n" + table(head, rows)
    )


MOUNT_RUNS = ("seen", "seen-s1", "towns", "towns-s1", "towns-car", "towns-car-s1")


def sensor_runs_mounts() -> str:
    """The runs' descriptors on the mounted test renderings, mount declared (mounts.py)."""
    folder = "reports/model/sensors-pilot"
    labels = dict(SENSOR_RUNS)
    rows, head = [], ["run"]
    for name in ("shipped", *MOUNT_RUNS):  # the shipped network's own run: Mounts (results)
        path = ROOT / folder / f"mounts-{name}.json"
        if name == "shipped":
            path = ROOT / "reports/model/mounts-test.json"
        if not path.is_file():
            continue
        r = json.loads(path.read_text())
        if len(head) == 1:
            head += [f"{x['town']}: own / the car's map" for x in r["rows"]]
        cells = []
        for x in r["rows"]:
            d = x["declared"]
            cells.append(f"{f3(d['own']['recall@1'])} / {f3(d['against_car']['recall@1'])}")
        label = "the shipped network, one view (`reports/model/mounts-test.json`)"
        rows.append([labels.get(name, label), *cells])
    cmd = "python benchmarks/mounts.py --model NAME.onnx --split test --out "
    cmd += "reports/model/sensors-pilot/mounts-NAME.json"
    return (
        source(f"{folder}/mounts-NAME.json", cmd)
        + "\nRecall@1 of the descriptor alone on the test drive's mounted renderings, mount "
        "declared: against the rendering's own earlier scans / against the car's map.\n\n"
        + table(head, rows)
    )


ALIGN_RUNS = ("shipped-1view", "seen-look")
HOWS = ("raw", "shift", "linear")


def sensor_align() -> str:
    """Per-sensor calibration of the descriptors (benchmarks/sensor_align.py), per network."""
    folder = "reports/model/sensors-pilot"
    labels = dict(SENSOR_RUNS)
    rows = []
    for name in ALIGN_RUNS:
        path = ROOT / folder / f"align-{name}.json"
        if not path.is_file():
            continue
        for x in json.loads(path.read_text())["rows"]:
            cells = [f"{f3(x[h]['test']['ar@1'])} / {f3(x[h]['test']['ar@5'])}" for h in HOWS]
            rows.append([labels[name], x["sensor"], *cells, f"{x['ridge']:g}"])
    head = ["network", "queries", "raw", "shift (means)", "linear (ridge)", "ridge (on val)"]
    cmd = "python benchmarks/sensor_align.py --model NAME.onnx --out "
    cmd += f"{folder}/align-NAME.json"
    return (
        source(f"{folder}/align-NAME.json", cmd)
        + "\nThe second test drive of each sensor against the model sensor's map of the first "
        "(`test-kitti-hdl64`), AR@1 / AR@5 of the descriptor alone (a hit within 5 m), each "
        "query's descriptor taken raw, shifted by the two sensors' validation means, or "
        "mapped linearly; fitted on the validation renderings, the ridge weight chosen there."
        "\n\n" + table(head, rows)
    )


ALIGN_TOWNS = (
    ("towns", "shipped-1view", "4"),
    ("towns8", "shipped-1view", "8"),
    ("towns16", "shipped-1view", "16"),
)


def sensor_align_towns() -> str:
    """The maps fitted on calibration towns (sensor_align.py --fit towns), per network and
    number of towns: across sensors, and what they cost each sensor's own map."""
    folder = "reports/model/sensors-pilot"
    labels = dict(SENSOR_RUNS)
    rows = []
    for prefix, name, towns in ALIGN_TOWNS:
        path = ROOT / folder / f"align-{prefix}-{name}.json"
        if not path.is_file():
            continue
        r = json.loads(path.read_text())
        for x in r["rows"]:
            cells = [f"{f3(x[h]['test']['ar@1'])} / {f3(x[h]['test']['ar@5'])}" for h in HOWS]
            own = x["own"]
            rows.append(
                [
                    labels[name],
                    towns,
                    x["sensor"],
                    *cells,
                    f"{x['ridge']:g}",
                    f"{f3(own['raw']['ar@1'])} → {f3(own['linear']['ar@1'])}",
                ]
            )
    head = ["network", "towns", "queries", "raw", "shift (means)", "linear (ridge)"]
    head += ["ridge (on val)", "its own map: raw → mapped"]
    cmd = "python benchmarks/sensor_align.py --model NAME.onnx --fit towns --towns N "
    cmd += "--write-maps NAME-maps.onnx --out "
    cmd += f"{folder}/align-towns-NAME.json (N = 4; N = 8, 16: align-townsN-NAME.json)"
    return (
        source(f"{folder}/align-towns-NAME.json", cmd)
        + "\nThe maps fitted on N calibration towns × 400 scans, the ridge weight chosen on "
        "the validation renderings. The second test drive of each sensor against the model "
        "sensor's map of the first (`test-kitti-hdl64`), AR@1 / AR@5 of the descriptor alone "
        "(a hit within 5 m); then AR@1 of that drive against the sensor's own first drive "
        "(`test-SENSOR`), both raw, then both mapped.\n\n" + table(head, rows)
    )


SENSOR_LIKE = "reports/model/sensor-like.json"


def sensor_like() -> str:
    """The augmentation against each sensor's rendering of the same validation frames."""
    r = load(SENSOR_LIKE)
    rows = []
    for x in r["rows"]:
        far = [b["share"] for b in x["kept_by_range"] if b["from_m"] >= 40]
        rows.append(
            [
                x["sensor"],
                f3(x["covered"]),
                f3(x["agree_1m"]),
                f3(x["extra"]),
                f3(sum(far) / len(far)) if far else "—",
                f3(x["cosine_real_sim"]),
                f3(x["cosine_real_own"]),
            ]
        )
    head = ["sensor", "pixels covered", "within 1 m", "extra pixels", "far returns kept"]
    head += ["cosine rendering · simulated", "cosine rendering · model sensor's scan"]
    return source(SENSOR_LIKE, r["command"], when(r)) + "\n" + table(head, rows)


def mounts(split: str) -> Callable[[], str]:
    """Mounted renderings with and without their mount declared (benchmarks/mounts.py)."""
    rel = f"reports/model/mounts-{split}.json"

    def render() -> str:
        r = load(rel)
        rows = []
        for x in r["rows"]:
            m = x["mount"]
            row = [x["town"], f"{m['height']} m, pitch {m['pitch_deg']}°, roll {m['roll_deg']}°"]
            for k in ("own", "against_car"):
                a, b = x["none"][k], x["declared"][k]
                fr = [f"{f3(v['f1max'])} / {f3(v['recall@1'])}" for v in (a, b)]
                row.append(" → ".join(fr))
            row.append(f"{f3(x['none']['cosine_to_car'])} → {f3(x['declared']['cosine_to_car'])}")
            rows.append(row)
        head = ["rendering", "mount", "own map: F1max / R@1", f"the car's map ({r['car']})"]
        head.append("cosine to the car's scan")
        return source(rel, r["command"], when(r)) + "\n" + table(head, rows)

    return render


RENDERERS: dict[str, Callable[[], str]] = {
    "mounts-val": mounts("val"),
    "mounts-test": mounts("test"),
    "sensor-like": sensor_like,
    "sensor-runs": sensor_runs,
    "sensor-runs-mounts": sensor_runs_mounts,
    "sensor-align": sensor_align,
    "sensor-align-towns": sensor_align_towns,
}
