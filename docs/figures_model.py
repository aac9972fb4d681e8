"""The model's and the encoder's tables, and the service's calibrated thresholds
(``docs/figures_kit.py`` says how the tables are made)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from figures_kit import ROOT, f3, load, ms, source, table, when

# ---- service -------------------------------------------------------------------------------
BENCH = "reports/service/bench.json"


def service() -> str:
    """The serving benchmark's own summary: each goal, what this run measured, met or not."""
    r = load(BENCH)
    rows = [[s["goal"], s["measured"], s["status"]] for s in r["summary"]]
    parts = "; ".join(f"{k}: {v}" for k, v in r.get("parts_measured", {}).items())
    out = source(BENCH, "make bench (python benchmarks/serving.py)", when(r))
    out += "\n" + table(["goal", "measured", "status"], rows)
    if parts:
        out += f"\nParts: {parts}.\n"
    return out


# ---- encoder -------------------------------------------------------------------------------
ENCODER = "reports/service/encoder-narrow.json"
VARIANTS = {
    "c-kernel (served)": "C-kernel path (served where it is the faster), one pass",
    "scan-loop": "portable graph (ONNX `Scan` loops)",
    "no-scan": "the same graph with the scan removed (yardstick)",
    "torch eager": "PyTorch, eager",
}


def encoder() -> str:
    """One encoder pass per variant at B = 1 and 8, and the peer comparison as the product
    runs (the shipped model with its views) beside one pass, interleaved."""
    r = load(ENCODER)
    rows = []
    for key, label in VARIANTS.items():
        v = r["variants"].get(key)
        if v is None:
            continue
        rows.append(
            [
                label,
                ms(v["b1_t1"]["median_ms"]),
                ms(v["b1_t2"]["median_ms"]),
                ms(v["b8_t2_per_scan_ms"]),
            ]
        )
    out = source(ENCODER, "python benchmarks/encoder.py --narrow", when(r))
    out += f"\nMachine: {r['machine'].get('cpu', '?')}, {r['machine']['cores']} cores; "
    out += f"{r['inputs']}; medians.\n\n"
    out += table(
        ["encoder", "B = 1, 1 thread", "B = 1, 2 threads", "B = 8, per scan, 2 threads"], rows
    )
    p = r.get("peer")
    if p:
        out += (
            f"\nAgainst the OverlapTransformer-style peer ({p['peer_params'] / 1e6:.1f} M "
            f"parameters; ours {p['ours_params'] / 1e6:.1f} M), interleaved, 2 threads, "
            "ms a scan:\n\n"
        )
        prow = []
        for b in ("b1", "b8"):
            x = p[b]
            prow.append(
                [
                    f"B = {b[1:]}",
                    ms(x["ours_views_ms_per_scan"]),
                    ms(x["ours_ms_per_scan"]),
                    ms(x["peer_ms_per_scan"]),
                    f"{x['ours_views_over_peer']:.2f}×",
                    f"{x['ours_over_peer']:.2f}×",
                ]
            )
        out += table(
            [
                "batch",
                f"ours as shipped ({p['views']} views)",
                "ours, one pass",
                "peer",
                "shipped ÷ peer",
                "one pass ÷ peer",
            ],
            prow,
        )
    return out


VIEWS = "reports/service/views.json"


def views() -> str:
    """The shipped model's sub-column views four ways (one view; one view with aligned
    columns, where the JSON has it; met at the descriptors; met at the tokens): cost
    interleaved, turn invariance on real scans, loop closure."""
    r = load(VIEWS)
    aligned = "aligned" in r["model_ids"]
    ways = ("one view", *(("aligned",) if aligned else ()), "descriptors", "tokens")
    v = r["views"]
    head = [
        "threads",
        "what",
        "one view",
        *(("one view, aligned columns",) if aligned else ()),
        f"{v} views met at the descriptors",
        "at the tokens",
    ]
    rows = []
    for x in r["rows"]:
        one = x["one view"]["median_ms"]
        cells = [
            f"{ms(x[k]['median_ms'])} ({x[k]['median_ms'] / one:.2f}×)"
            if k in x
            else "the same projections"
            for k in ways[1:]
        ]
        what = (
            f"project + encode, {x['scans_per_call']} a call"
            if "scans_per_call" in x
            else x["stage"]
        )
        rows.append([x["threads"], what, ms(one), *cells])
    out = source(VIEWS, r.get("command") or "python benchmarks/views.py", when(r))
    kept = r.get("measured_by")
    if kept:  # --cost-only: the cost rows are this command's, the rest an earlier run's
        out += (
            f"\nThe cost rows are that command's; the turn invariance and loop closure are "
            f"from `{kept['command']}` ({kept['date'][:10]}, commit {kept['commit'][:7]}).\n"
        )
    out += f"\n{r['scans']}, {r['reps']} repetitions, medians a scan (× one view).\n\n"
    out += table(head, rows)
    turns = r.get("turn_invariance") or {}
    sets = [k for k in turns if isinstance(turns[k], dict) and "skipped" not in turns[k]]
    if sets:
        out += (
            f"\nMinimum cosine under a random continuous turn, the lowest over "
            f"{turns['seeds']} draws (every scan turned once a draw; bar 0.999):\n\n"
        )
        out += table(
            ["real scans", "scans", *head[2:]],
            [
                [k, turns[k]["scans"], *(f"{turns[k][w]['cosine_min']:.5f}" for w in ways)]
                for k in sets
            ],
        )
    loops = {k: x for k, x in (r.get("loop_closure") or {}).items() if k != "rerank"}
    if loops:
        out += (
            "\nLoop closure, F1max / Recall@1 over all revisits, descriptor alone · two stages:\n\n"
        )
        rows = []
        for town, per in loops.items():
            cells = []
            for w in ways:
                d, t = per[w]["descriptor"]["all"], per[w]["two_stages"]["all"]
                pair = f"{d['f1max']:.3f} / {d['recall@1']:.3f}"
                cells.append(f"{pair} · {t['f1max']:.3f} / {t['recall@1']:.3f}")
            rows.append([f"`{town}`", *cells])
        out += table(["town", *head[2:]], rows)
    return out


LOOP_THRESHOLD = "reports/service/loop_threshold.json"
VERIFY_THRESHOLD = "reports/service/verify_threshold.json"


def calibration() -> str:
    """The service's thresholds as the benchmarks chose them on ``val`` for the shipped model,
    with precision and recall there (old files name them max_distance; the service's names
    are the new ones)."""
    lt, vt = load(LOOP_THRESHOLD), load(VERIFY_THRESHOLD)
    op, opr = lt["operating_points"]["f1max"], lt["operating_points_reranked"]["f1max"]
    dist = op.get("accept_distance", op.get("max_distance"))
    c, g = vt["calibration"]["chosen"], vt["calibration"]["gate"]
    gate = g.get("gate_distance", g.get("max_distance"))
    rows = [
        [
            "verified answers",
            "`verify.min_fitness`, `verify.max_rmse_m`",
            f"{c['min_fitness']}, {c['max_rmse_m']}",
            f"{c['precision']:.3f} ({c['correct']} of {c['accepted']} poses right)",
            f"{c['recall']:.3f}",
        ],
        [
            "… with the descriptor gate",
            "`verify.gate_distance`",
            f"{gate}",
            f"{g['precision']:.3f}",
            f"{g['recall']:.3f} ({g['registered_per_query']:.1f} registered a query)",
        ],
        *ambiguity_row(vt["calibration"].get("ambiguity")),
        [
            "unverified, re-ranked (F1max)",
            "`loop_closure.max_score`",
            f"{opr['max_score']:.4f}",
            f"{opr['precision']:.3f}",
            f"{opr['recall']:.3f}",
        ],
        [
            "unverified, descriptor order (F1max)",
            "`loop_closure.accept_distance`",
            f"{dist:.4f}",
            f"{op['precision']:.3f}",
            f"{op['recall']:.3f}",
        ],
    ]
    out = source(VERIFY_THRESHOLD, vt["command"], when(vt))
    out += source(LOOP_THRESHOLD, lt["command"], when(lt))
    out += f"\nModel {lt['model_id']}, on `{Path(lt['sequence']).name}`:\n\n"
    out += table(["answer", "setting", "value", "precision on val", "recall on val"], rows)
    pts = lt["operating_points"]
    stricter = [
        f"precision ≥ {name.split('>=')[1]} at "
        f"{p.get('accept_distance', p.get('max_distance')):.3f} (recall {p['recall']:.2f})"
        for name, p in pts.items()
        if name.startswith("precision") and p is not None
    ]
    if stricter:
        out += "\nStricter descriptor-order points: " + "; ".join(stricter) + ".\n"
    return out


def ambiguity_row(m: dict | None) -> list[list[str]]:
    """``verify.ambiguity_margin``'s row, when the calibration chose one."""
    if m is None:
        return []
    return [
        [
            "… refusing the ambiguous",
            "`verify.ambiguity_margin`",
            f"{m['ambiguity_margin']}",
            f"{m['precision']:.3f} ({m['correct']} of {m['accepted']} poses right)",
            f"{m['recall']:.3f}",
        ]
    ]


MODEL_TABLES = "reports/model/tables.md"


def model_tables() -> str:
    """The model report's own Markdown (``overlapmamba report`` writes it beside
    report.json), under the command that wrote it."""
    text = (ROOT / MODEL_TABLES).read_text()
    return source(MODEL_TABLES, "overlapmamba report") + "\n" + text


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


TRAINING_SPEED = "reports/model/training-narrow.json"


def training_speed() -> str:
    """One training step of the shipped width per scan backend and weight layout, one run."""
    r = load(TRAINING_SPEED)
    base = r["rows"][0]["scans_per_s"]
    rows = [
        [
            x["backend"],
            x.get("layout", "contiguous"),
            f"{x['step_median_s']:.2f} s",
            f"{x['scans_per_s']:.1f}",
            f"{x['scans_per_s'] / base:.2f}×",
        ]
        for x in r["rows"]
    ]
    head = ["scan backend", "weight layout", "step (median)", "scans/s", "vs first"]
    return (
        source(TRAINING_SPEED, r["command"], when(r))
        + f"\nBatch {r['batch']}, {r['width']} width, {r['threads']} threads, {r['source']}, "
        f"{r['steps']} timed steps each.\n\n" + table(head, rows)
    )


# ---- synthetic data ------------------------------------------------------------------------
OVERLAP_TABLES = "reports/synthetic/overlap_tables.json"


def overlap_tables() -> str:
    """The overlap tables' pairs a second, the shipped code against the definition written
    plainly, on the same pairs in one process, and how far their tables are apart."""
    r = load(OVERLAP_TABLES)
    t, a = r["town"], r["agreement"]
    rate = r["pairs_per_s"]
    out = source(OVERLAP_TABLES, r["command"], when(r))
    out += (
        f"\n{r['pairs']} pairs within {t['radius_m']:g} m of a {t['frames']}-scan town "
        f"(seed {t['seed']}, {t['sensor']}), one process, both ways alternating.\n\n"
    )
    rows = [
        ["the definition written plainly (float64 points, up to generator 1.6)", rate["plain"]],
        ["shipped (float32 (3, N) rows, `pixel_index`)", rate["shipped"]],
    ]
    out += table(["overlap table", "pairs/s"], [[k, f"{v:.0f}"] for k, v in rows])
    out += (
        f"\nShipped / plain: {r['speedup']:.2f}×. The tables differ by at most "
        f"{a['max_abs_difference']:.1e} (mean {a['mean_abs_difference']:.1e}; "
        f"{100 * a['share_of_pairs_that_differ']:.1f} % of the pairs differ at all); "
        f"pairs on the other side of 0.3: {a['pairs_across_0_3']}.\n"
    )
    return out


# eval-real of the shipped file and its one-view twin (label → report names)
REAL_ONE_PASS = {
    "the shipped file, three views": ("real-shipped-kitti", "real-shipped-nuscenes"),
    "the one-view twin, aligned columns": ("real-one-view-kitti", "real-one-view-nuscenes"),
}


def real_one_pass() -> str:
    """The shipped file and its one-view twin on real scans: turn invariance, odd → even
    retrieval, KITTI queries thinned to 32 and 16 rings."""
    from figures_bev import real_table

    return real_table(REAL_ONE_PASS, described="as each file describes a scan")


RENDERERS: dict[str, Callable[[], str]] = {
    "overlap-tables": overlap_tables,
    "training-speed": training_speed,
    "mounts-val": mounts("val"),
    "mounts-test": mounts("test"),
    "sensor-like": sensor_like,
    "sensor-runs": sensor_runs,
    "sensor-runs-mounts": sensor_runs_mounts,
    "sensor-align": sensor_align,
    "sensor-align-towns": sensor_align_towns,
    "model-tables": model_tables,
    "calibration": calibration,
    "service": service,
    "encoder": encoder,
    "views": views,
    "real-one-pass": real_one_pass,
}
