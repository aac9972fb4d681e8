"""The model report as Markdown (``OUT/tables.md``): Table I per subset and town, where
F1max is lost, across sessions, Tables II–IV and the real-scan checks, from the dict
:func:`overlapmamba.train.report.build_report` writes as ``report.json``."""

from __future__ import annotations

from typing import Any

import numpy as np

from overlapmamba.core.anatomy import FAR_M
from overlapmamba.train.evaluate import SUBSETS


def _fmt(x: Any, digits: int = 3) -> str:
    return "–" if x is None or (isinstance(x, float) and np.isnan(x)) else f"{x:.{digits}f}"


def markdown(report: dict[str, Any]) -> str:
    notes = [f"> Note: {n}" for n in report.get("notes", [])]
    towns = report.get("table1_towns") or {"test": report["table1"]}
    names = list(towns)
    lines = [*notes, *([""] if notes else [])]
    lines += [
        f"### Table I: loop closure on the synthetic test towns (mean over {len(names)}: "
        f"{', '.join(names)})",
        "",
    ]
    lines += [
        "| method | subset | AUC | F1max | Recall@1 | Recall@1% | queries (with loop) "
        "| F1max per town | Recall@1 per town |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for label, subs in report["table1"].items():
        for sub in SUBSETS:
            m = subs[sub]
            per_f1 = " / ".join(_fmt(towns[t][label][sub]["f1max"]) for t in names)
            per_r1 = " / ".join(_fmt(towns[t][label][sub]["recall@1"]) for t in names)
            lines.append(
                f"| {label} | {sub} | {_fmt(m['auc'])} | {_fmt(m['f1max'])} | "
                f"{_fmt(m['recall@1'])} | {_fmt(m['recall@1%'])} | "
                f"{m['queries']} ({m['queries_with_loop']}) | {per_f1} | {per_r1} |"
            )
    errors = report.get("errors")
    if errors:
        lines += [
            "",
            "### Where F1max is lost: each method at its own F1max threshold, per town",
            "",
            "False alarms by the wrong candidate's distance from the query (neighbours: "
            f"within {FAR_M:g} m; "
            "look-alikes: beyond); missed loops by a wrong top-1 or a right one rejected "
            "(`overlapmamba.core.anatomy`).",
            "",
            "| town | method | subset | accepted | true | false alarms (neighbours / "
            "look-alikes) | missed loops (wrong top-1 / rejected) |",
            "|---|---|---|---|---|---|---|",
        ]
        for town, methods in errors.items():
            for label, subs in methods.items():
                for sub in ("same", "reverse"):
                    e = subs[sub]
                    fa, miss = e["false_alarms"], e["missed_loops"]
                    lines.append(
                        f"| {town} | {label} | {sub} | {e['accepted']} | {e['true_closures']} | "
                        f"{fa['total']} ({fa['neighbours']} / {fa['look_alikes']}) | "
                        f"{miss['total']} ({miss['wrong_top1']} / {miss['rejected']}) |"
                    )
    cross = report.get("cross_session")
    if cross:
        lines += [
            "",
            f"### Place recognition across sessions: `{cross['queries']}` against "
            f"`{cross['database']}`",
            "",
            "| method | queries | AR@1 | AR@5 | AR@20 | wrong top-1: distance to the query |",
            "|---|---|---|---|---|---|",
        ]
        for label, r in cross.items():
            if isinstance(r, dict):
                wrong = ", ".join(f"{k}: {v}" for k, v in r.get("wrong_top1", {}).items())
                lines.append(
                    f"| {label} | {r['queries']} | {_fmt(r['ar@1'])} | {_fmt(r['ar@5'])} | "
                    f"{_fmt(r['ar@20'])} | {wrong or '–'} |"
                )
    if report["ablation"]:
        lines += ["", "### Tables II and III: ablations (validation preset, equal budget)", ""]
        lines += [
            "| variant | run | scans seen | params | forward ms (B=1) | F1max all | same | "
            "reverse | Recall@1 all | reverse |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
    for label, r in report["ablation"].items():
        v = r["val"]
        lines.append(
            f"| {label} | `{r['run']}` | {r['scans_seen']} | {r['params'] / 1e6:.2f} M | "
            f"{_fmt(r['forward_ms'], 0)} | {_fmt(v['all']['f1max'])} | "
            f"{_fmt(v['same']['f1max'])} | {_fmt(v['reverse']['f1max'])} | "
            f"{_fmt(v['all']['recall@1'])} | {_fmt(v['reverse']['recall@1'])} |"
        )
    if report["epochs"]:
        lines += ["", "### Table IV: loss and validation F1max per epoch", ""]
        lines += ["| run | loss | epoch | training loss | val F1max | val Recall@1 |"]
        lines += ["|---|---|---|---|---|---|"]
    for label, r in report["epochs"].items():
        for h in r["history"]:
            lines.append(
                f"| {label} | {r['loss']} | {h['epoch']} | {_fmt(h['loss'], 4)} | "
                f"{_fmt(h['f1max'])} | {_fmt(h['recall@1'])} |"
            )
    if report.get("real"):
        lines += ["", "### Real scans (the shipped model)", ""]
        lines += [
            "| scans | sensor (input) | cosine under random yaw (min) | turned copy ÷ 1 m step "
            "(squared distances) | odd→even Recall@1 (radius) | with the yaw re-rank "
            "| Scan Context's | Recall@5 | yaw error vs turned copy (median) "
            "| vs retrieved frame (median) |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for name, r in report["real"].items():
            if "skipped" in r:
                lines.append(f"| {name} | skipped: {r['skipped']} |||||||||")
                continue
            ret, yaw, inv = r["retrieval_odd_to_even"], r["yaw_error_deg"], r["yaw_invariance"]
            lines.append(
                f"| {name} ({r['scans']}) | {r['sensor']} ({r['input']}) | "
                f"{inv['cosine_min']:.5f} | {inv['turned_distance_median']:.2e} ÷ "
                f"{inv['one_metre_step_distance_median']:.2e} = "
                f"{inv['turned_over_one_metre_step']:.2f} | "
                f"{ret['recall@1']:.3f} ({ret['hit_radius_m']:g} m) | "
                f"{_fmt(ret.get('reranked', {}).get('recall@1'))} | "
                f"{ret['scan_context']['recall@1']:.3f} | {ret['recall@5']:.3f} | "
                f"{yaw['vs_turned_copy']['median']:.2f}° | "
                f"{yaw['vs_retrieved_frame']['median']:.2f}° |"
            )
    return "\n".join(lines) + "\n"
