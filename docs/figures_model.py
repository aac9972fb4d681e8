"""The model's and the encoder's tables, and the service's calibrated thresholds
(``docs/figures_kit.py`` says how the tables are made)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from figures_kit import ROOT, load, ms, source, table, when

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
    http = r.get("http", {})
    lanes = (http.get("defaults") or {}).get("lanes")
    if lanes:
        out += (
            f"\nBoth sides of the overhead ratio run {http['intra_op_threads']} onnxruntime "
            f"thread(s) a call, as each of the server's {lanes} lanes does by default; the "
            "sgemm runs on every core.\n"
        )
    return out + _then_and_now(http)


def _then_and_now(http: dict[str, Any]) -> str:
    """The batching the http part's servers ran with, beside today's defaults where they
    differ: a run's "defaults" are its day's."""
    from overlapmamba.service.settings import BatchSettings

    then, now = http.get("defaults") or {}, BatchSettings()
    if (then.get("max_batch"), then.get("max_wait_ms")) in (
        (None, None),
        (now.max_batch, now.max_wait_ms),
    ):
        return ""
    return (
        f"\nThe http part's servers ran with that day's defaults: `max_batch` "
        f"{then.get('max_batch', '?')}, `max_wait_ms` {then.get('max_wait_ms', '?')}, "
        f"{http.get('intra_op_threads', '?')} onnxruntime threads a call. Today's: "
        f"`max_batch` {now.max_batch} a lane, `max_wait_ms` {now.max_wait_ms:g}, `lanes` "
        f"{now.lanes or 'one a core'}; the fleet and end-to-end tables measure those.\n"
    )


# ---- encoder -------------------------------------------------------------------------------
ENCODER = "reports/service/encoder-narrow.json"
VARIANTS = {
    "shipped file (served)": "the shipped file as the service loads it ({path}), its {views} "
    "views a scan",
    "c-kernel": "C-kernel path, forced (the rows below: one set of random weights), one pass",
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
        path = v.get("scan_path", "")
        if v.get("scan_path_t1") and v["scan_path_t1"].split(" (")[0] != path.split(" (")[0]:
            path = f"{v['scan_path_t1'].split(' (')[0]} at 1 thread, {path.split(' (')[0]} at 2"
        peer = r.get("peer") or {}
        views = v.get("views") or (
            peer.get("views") if peer.get("model_id") == v.get("model_id") else "?"
        )
        rows.append(
            [
                label.format(path=path.split(" (")[0] if path else "?", views=views),
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
        ours = ""
        if "one_pass_model_id" in p:
            ours = (
                f"as shipped `{p['model_id']}` ({p['scan_path'].split(' (')[0]}), one pass "
                f"`{p['one_pass_model_id']}` ({p['one_pass_scan_path'].split(' (')[0]})"
            )
        out += (
            f"\nAgainst the OverlapTransformer-style peer ({p['peer_params'] / 1e6:.1f} M "
            f"parameters; ours {p['ours_params'] / 1e6:.1f} M{', ' + ours if ours else ''}), "
            "interleaved, 2 threads, ms a scan:\n\n"
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
TOKENS_FILE = "models/overlapmamba-hdl64-tokens.onnx"


def _which_files(r: dict[str, Any]) -> str:
    """What the views report's columns were, against the files shipped: each variant's
    scan path where it recorded one, and a column whose model id no shipped file has."""
    from overlapmamba.service.calibration import read_model_metadata

    shipped = read_model_metadata(ROOT / TOKENS_FILE).model_id
    out = ""
    if r["model_ids"].get("tokens") not in (None, shipped):
        out += (
            f" The tokens column is the benchmark's own export (`{r['model_ids']['tokens']}`), "
            f"not the shipped tokens file (`{shipped}`)."
        )
    paths = r.get("scan_paths")
    if paths:
        out += " Scan paths: " + "; ".join(f"{k}: {v.split(' (')[0]}" for k, v in paths.items())
        out += "."
    else:
        out += (
            " Which scan path each variant took (C kernel or portable graph, chosen at each "
            "load) was not recorded."
        )
    return out


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
    out += f"\n{r['scans']}, {r['reps']} repetitions, medians a scan (× one view)."
    out += _which_files(r) + "\n\n"
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
    note = (
        "\nThese tables compare the training runs' checkpoints (`best.pt`), each in one view "
        'and one stage. The run marked "(shipped)" has the shipped file\'s weights; the file '
        "runs them with its sub-column views, and its own figures, as the service answers, are "
        "the headline table (`reports/model/two-stage/report.json`) and the sections below "
        "that name the file.\n"
    )
    return source(MODEL_TABLES, "overlapmamba report") + note + "\n" + text


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
    "model-tables": model_tables,
    "calibration": calibration,
    "service": service,
    "encoder": encoder,
    "views": views,
    "real-one-pass": real_one_pass,
}
