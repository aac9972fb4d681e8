"""The measured tables of the documentation, each rendered from the JSON a command wrote.

One function per ``<!-- render NAME -->`` block (``docs/render.py`` pastes them; ``make docs``
rewrites them, ``tests/test_docs_figures.py`` fails on a stale one). Each table opens with the
JSON it reads and the command that wrote it; nothing here types a measured number.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]


def _load(rel: str) -> dict[str, Any]:
    return json.loads((ROOT / rel).read_text())


def _source(rel: str, command: str, when: str | None = None) -> str:
    at = f" ({when})" if when else ""
    return f"<!-- from {rel}{at}, written by `{command}`; rendered by `make docs` -->\n"


def _when(r: dict[str, Any]) -> str | None:
    """The date a report records (newer reports: ``date``; older: ``when``), if any."""
    for key in ("date", "when"):
        if isinstance(r.get(key), str):
            return r[key][:10]
    return None


def _table(head: list[str], rows: list[list[Any]]) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def _ms(x: float) -> str:
    return f"{x:.1f} ms"


def _f3(x: float | None) -> str:
    return "—" if x is None else f"{x:.3f}"


# ---- service -------------------------------------------------------------------------------
BENCH = "reports/service/bench.json"


def service() -> str:
    """The serving benchmark's own summary: each goal, what this run measured, met or not."""
    r = _load(BENCH)
    rows = [[s["goal"], s["measured"], s["status"]] for s in r["summary"]]
    parts = "; ".join(f"{k}: {v}" for k, v in r.get("parts_measured", {}).items())
    out = _source(BENCH, "make bench (python benchmarks/serving.py)")
    out += "\n" + _table(["goal", "measured", "status"], rows)
    if parts:
        out += f"\nParts: {parts}.\n"
    return out


# ---- encoder -------------------------------------------------------------------------------
ENCODER = "reports/service/encoder-narrow.json"
VARIANTS = {
    "c-kernel (served)": "served (C-kernel path), one pass",
    "scan-loop": "portable graph (ONNX `Scan` loops)",
    "no-scan": "the same graph with the scan removed (yardstick)",
    "torch eager": "PyTorch, eager",
}


def encoder() -> str:
    """One encoder pass per variant at B = 1 and 8, and the peer comparison as the product
    runs (the shipped model with its views) beside one pass, interleaved."""
    r = _load(ENCODER)
    rows = []
    for key, label in VARIANTS.items():
        v = r["variants"].get(key)
        if v is None:
            continue
        rows.append(
            [
                label,
                _ms(v["b1_t1"]["median_ms"]),
                _ms(v["b1_t2"]["median_ms"]),
                _ms(v["b8_t2_per_scan_ms"]),
            ]
        )
    out = _source(ENCODER, "python benchmarks/encoder.py --narrow", _when(r))
    out += f"\nMachine: {r['machine'].get('cpu', '?')}, {r['machine']['cores']} cores; "
    out += f"{r['inputs']}; medians.\n\n"
    out += _table(
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
                    _ms(x["ours_views_ms_per_scan"]),
                    _ms(x["ours_ms_per_scan"]),
                    _ms(x["peer_ms_per_scan"]),
                    f"{x['ours_views_over_peer']:.2f}×",
                    f"{x['ours_over_peer']:.2f}×",
                ]
            )
        out += _table(
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
    """The shipped model's sub-column views against one view, interleaved."""
    r = _load(VIEWS)
    rows = [
        [
            x["threads"],
            f"encode, {x['scans_per_call']} a call" if "scans_per_call" in x else x["stage"],
            _ms(x["one view"]["median_ms"]),
            _ms(x["shipped"]["median_ms"]),
            f"{x['shipped']['median_ms'] / x['one view']['median_ms']:.2f}×",
        ]
        for x in r["rows"]
    ]
    out = _source(VIEWS, "python benchmarks/views.py", _when(r))
    out += f"\n{r['scans']}, {r['reps']} repetitions, medians a scan.\n\n"
    return out + _table(
        ["threads", "what", "one view", f"shipped ({r['views']} views)", "ratio"], rows
    )


# ---- verification --------------------------------------------------------------------------
VERIFY = "reports/service/verify-test.json"


def verify() -> str:
    """Verified loop closures on the test towns at the service's thresholds."""
    r = _load(VERIFY)
    rows = []
    for t in r["towns"]:
        v, d = t["verified"], t["descriptor"]
        rows.append(
            [
                Path(t["town"]).name,
                t["queries"],
                t["with_loop"],
                v["accepted"],
                f"{v['precision']:.3f}",
                f"{v['recall']:.3f}",
                f"{d['recall@1']:.3f}",
                f"{d['recall@5']:.3f}",
                f"{v['registered_per_query']:.1f}",
                _ms(t["verify_ms"]["median"]),
            ]
        )
    th = r["thresholds"]
    gate = th.get("gate_distance", th.get("max_distance"))  # older files: max_distance
    out = _source(
        VERIFY,
        "python benchmarks/verify_threshold.py --town data/synth/test --town data/synth/test-b "
        "--town data/synth/test-c",
        _when(r),
    )
    out += (
        f"\nModel {r['model_id']}; thresholds: fitness ≥ {th['min_fitness']}, rmse ≤ "
        f"{th['max_rmse_m']} m, descriptor gate {gate}. A closure is correct when its pose is "
        "within 1 m and 2° of the truth; recall counts queries with a loop.\n\n"
    )
    return out + _table(
        [
            "town",
            "queries",
            "with loop",
            "accepted",
            "precision",
            "recall",
            "answer Recall@1",
            "Recall@5",
            "registered a query",
            "verify p50",
        ],
        rows,
    )


REGISTRATION = "reports/service/registration.json"


def registration() -> str:
    """Relative poses on real KITTI 00, and what verification costs a query over HTTP."""
    r = _load(REGISTRATION)
    h = r["http"]
    rows = [
        [
            "translation error",
            f"{r['t_err']['median'] * 100:.1f} cm",
            f"{r['t_err']['p90'] * 100:.1f} cm",
            f"{r['t_err']['max'] * 100:.1f} cm",
        ],
        [
            "yaw error",
            f"{r['yaw_err']['median']:.3f}°",
            f"{r['yaw_err']['p90']:.3f}°",
            f"{r['yaw_err']['max']:.3f}°",
        ],
        [
            "fitness",
            f"{r['fitness']['median']:.3f}",
            f"{r['fitness']['p90']:.3f}",
            f"{r['fitness']['max']:.3f}",
        ],
        [
            "registration time",
            _ms(r["register_ms"]["median"]),
            _ms(r["register_ms"]["p90"]),
            _ms(r["register_ms"]["max"]),
        ],
        [
            "geometry a keyframe",
            f"{r['geometry_bytes']['median'] / 1e3:.1f} KB",
            f"{r['geometry_bytes']['p90'] / 1e3:.1f} KB",
            f"{r['geometry_bytes']['max'] / 1e3:.1f} KB",
        ],
    ]
    out = _source(REGISTRATION, "python benchmarks/registration.py", _when(r))
    out += f"\n{r['scans']}.\n\n" + _table(["", "median", "p90", "max"], rows)
    out += (
        f"\nOver HTTP ({h['queries']} queries, {h['candidates']} candidates verified): a "
        f"query's client time {_ms(h['verify_true']['client_ms'])} with verification against "
        f"{_ms(h['verify_false']['client_ms'])} without (+{h['added_share'] * 100:.0f} %), the "
        f"verify stage {_ms(h['verify_true']['server_verify_ms'])}.\n"
    )
    return out


MAPCLOSURES = "reports/service/mapclosures-test.json"


def mapclosures() -> str:
    """Against MapClosures on the first test town."""
    r = _load(MAPCLOSURES)
    med = lambda xs: sorted(xs)[len(xs) // 2] if xs else float("nan")  # noqa: E731
    out = _source(MAPCLOSURES, "python benchmarks/mapclosures_compare.py", _when(r))
    out += (
        f"\n{Path(r['town']).name}: {r['scans']:,} scans, {r['revisiting_scans']:,} revisiting.\n\n"
    )
    out += _table(
        ["method", "closures", "revisits covered", "translation error p50", "yaw error p50"],
        [
            [
                "MapClosures",
                r["closures"],
                r["covered_revisits"],
                f"{med(r['pose_error_m']) * 100:.1f} cm",
                f"{med(r['yaw_error_deg']):.2f}°",
            ]
        ],
    )
    ours = r.get("ours", {}).get("verified")
    if ours:
        out += (
            f"\nThis service on the same town: {ours['accepted']:,} verified closures, precision "
            f"{ours['precision']:.3f}, recall {ours['recall']:.3f}.\n"
        )
    return out


# ---- deployment ----------------------------------------------------------------------------
SIZING = "reports/deploy/sizing.json"


def sizing() -> str:
    """What a node needs: the encoder's rate, each backend's costs a keyframe, the search
    stage at 10,000 keyframes."""
    r = _load(SIZING)
    out = _source(SIZING, "python benchmarks/sizing.py", _when(r))
    out += f"\n{r['scans']}; project + encode as the service runs it:\n\n"
    out += _table(
        ["threads", "p50 a scan", "scans/s"],
        [[e["threads"], _ms(e["median_ms"]), f"{e['scans_per_s']:.0f}"] for e in r["encoder"]],
    )
    f, q = r["backends"]["faiss"], r["backends"]["qdrant"]
    out += "\n" + _table(
        [
            "backend",
            "keyframes",
            "insert p50",
            "query p50",
            "filtered query p50",
            "disk a keyframe",
        ],
        [
            [
                "FAISS",
                f["n"],
                _ms(f["insert_p50_ms"]),
                _ms(f["query_p50_ms"]),
                _ms(f["filtered_query_p50_ms"]),
                f"{f['store_bytes_per_keyframe'] / 1e3:.1f} KB",
            ],
            [
                "Qdrant (local)",
                q["n"],
                _ms(q["insert_p50_ms"]),
                _ms(q["query_p50_ms"]),
                _ms(q["filtered_query_p50_ms"]),
                f"{q['local_storage_bytes_per_point'] / 1e3:.1f} KB",
            ],
        ],
    )
    rows = []
    for s in r["search_stage"]:
        parts = " / ".join(f"{k} {s[k]['p50_ms']:.2f}" for k in ("index", "rows", "yaw") if k in s)
        rows.append(
            [
                s["load"],
                s["keyframes"],
                s["faiss_threads"],
                f"{s['search']['p50_ms']:.2f} ms",
                f"{s['search']['p90_ms']:.2f} ms",
                parts,
            ]
        )
    out += "\nA scan query's search stage:\n\n"
    return out + _table(
        ["encoder", "keyframes", "FAISS threads", "p50", "p90", "p50 by part (ms)"], rows
    )


def fleet() -> str:
    """The fleet simulator at 1, 4 and 8 robots."""
    rows = []
    for n in (1, 4, 8):
        rel = f"reports/client/fleet-{n}.json"
        if not (ROOT / rel).is_file():
            continue
        r = _load(rel)
        pe = (r.get("pose_error") or {}).get("translation_m")
        rows.append(
            [
                r["robots"],
                r["observations"],
                f"{r['throughput_per_s']:.1f}",
                _ms(r["latency_ms"]["p50"]),
                _ms(r["latency_ms"]["p95"]),
                sum(r["errors"].values()) if r["errors"] else 0,
                _f3(r["precision"]),
                _f3(r["recall"]),
                f"{pe['median'] * 100:.1f} cm" if pe else "—",
            ]
        )
    out = _source(
        "reports/client/fleet-{1,4,8}.json", "overlapmamba-client simulate-fleet --robots N"
    )
    return (
        out
        + "\n"
        + _table(
            [
                "robots",
                "observations",
                "observations/s",
                "p50",
                "p95",
                "errors",
                "precision",
                "recall",
                "pose error p50",
            ],
            rows,
        )
    )


# ---- end to end ----------------------------------------------------------------------------
def e2e() -> str:
    """The end-to-end runs (``make e2e``), one line each from its JSON."""
    rows = []
    load = _load("reports/e2e/load.json")
    fl = load["fleet"]
    rows.append(
        [
            "load (`tests/test_e2e_load.py`)",
            load["when"][:10],
            f"{load['robots']} robots on `{load['drive']}` for {load['duration_s']:.0f} s: "
            f"{fl['throughput_per_s']:.1f} observations/s, p50 {_ms(fl['latency_ms']['p50'])}, "
            f"{load['errors_total']} errors, {load['acknowledged_missing']} keyframes lost; "
            f"verified closures precision {fl['closure_precision']:.3f}, recall "
            f"{fl['closure_recall']:.3f}",
        ]
    )
    crash = _load("reports/e2e/crash.json")
    rows.append(
        [
            "crash (`tests/test_e2e_crash.py`)",
            crash["when"][:10],
            f"{crash['crashes']} SIGKILLs under load; {crash['lost']} acknowledged writes lost; "
            f"ready in {crash['ready_s']['median']:.1f} s median, {crash['ready_s']['max']:.1f} s "
            "at most",
        ]
    )
    fz = _load("reports/e2e/fuzz_schemathesis.json")
    corpus = _load("reports/e2e/fuzz_corpus.json")
    rows.append(
        [
            "fuzz (`tests/test_e2e_fuzz.py`)",
            fz["when"][:10],
            f"schemathesis for {fz['budget_s']} s: {fz['test_cases']:,} cases, exit code "
            f"{fz['exit_code']}, server alive: {fz['server_alive']}; {len(corpus['cases'])} "
            f"hostile bodies, all answered 4xx: {corpus['all_4xx']}",
        ]
    )
    auth = _load("reports/e2e/auth_matrix.json")
    rows.append(
        [
            "auth matrix (`tests/test_e2e_auth.py`)",
            auth["when"][:10],
            f"{len(auth['cells'])} routes × {len(auth['roles'])} roles and three wrong keys: "
            "the status of every cell (the test asserts each)",
        ]
    )
    b = _load("reports/e2e/browser.json")
    rows.append(
        [
            "browser (`tests/test_e2e_browser.py`)",
            b["when"][:10],
            f"Chromium {b['chromium_version']}: {len(b['charts_changed'])} of "
            f"{len(b['canvases'])} charts changed between two looks, "
            f"{len(b['page_errors'])} page errors",
        ]
    )
    out = _source("reports/e2e/*.json", "make e2e")
    return out + "\n" + _table(["test", "run", "result"], rows)


LOOP_THRESHOLD = "reports/service/loop_threshold.json"
VERIFY_THRESHOLD = "reports/service/verify_threshold.json"


def calibration() -> str:
    """The service's thresholds as the benchmarks chose them on ``val`` for the shipped model,
    with precision and recall there (old files name them max_distance; the service's names
    are the new ones)."""
    lt, vt = _load(LOOP_THRESHOLD), _load(VERIFY_THRESHOLD)
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
    out = _source(VERIFY_THRESHOLD, vt["command"], _when(vt))
    out += _source(LOOP_THRESHOLD, lt["command"], _when(lt))
    out += f"\nModel {lt['model_id']}, on `{Path(lt['sequence']).name}`:\n\n"
    out += _table(["answer", "setting", "value", "precision on val", "recall on val"], rows)
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


MODEL_TABLES = "reports/model/tables.md"


def model_tables() -> str:
    """The model report's own Markdown (``overlapmamba report`` writes it beside
    report.json), under the command that wrote it."""
    text = (ROOT / MODEL_TABLES).read_text()
    return _source(MODEL_TABLES, "overlapmamba report") + "\n" + text


RENDERERS: dict[str, Callable[[], str]] = {
    "model-tables": model_tables,
    "calibration": calibration,
    "service": service,
    "encoder": encoder,
    "views": views,
    "verify": verify,
    "registration": registration,
    "mapclosures": mapclosures,
    "sizing": sizing,
    "fleet": fleet,
    "e2e": e2e,
}
