"""The tables ``benchmarks/encoder.py`` prints, read from its record: after a run, or again
from its JSON (``python benchmarks/encoder_tables.py reports/service/encoder-narrow.json``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table


def print_tables(console: Console, record: dict[str, Any]) -> None:
    """The variants, the served encoder against no-scan, the ratios, the FLOPs, the peer
    and onnxruntime's per-operator profile, as ``encoder.py`` records them."""
    source, results, ratios = record["inputs"], record["variants"], record["ratios"]
    yard, peer, profile = record["yardstick_interleaved"], record["peer"], record["op_profile_ms"]
    work, cpu = record["flops"], record["machine"]["cpu"]
    achieved, peak = work["achieved_gflops_b1_t2"], work["peak_gflops_2_cores"]
    table = Table(title=f"ONNX encoder, {source}, onnxruntime {record['onnxruntime']}")
    cols = ["variant", "B=1 1T med/p90 ms", "B=1 2T med/p90 ms", "B=8 2T ms/scan"]
    cols += ["max err desc/yaw", "nodes", "MB", "load s"]
    for c in cols:
        table.add_column(c, justify="right")
    for name, r in results.items():
        table.add_row(
            name,
            f"{r['b1_t1']['median_ms']:.1f} / {r['b1_t1']['p90_ms']:.1f}",
            f"{r['b1_t2']['median_ms']:.1f} / {r['b1_t2']['p90_ms']:.1f}",
            f"{r['b8_t2_per_scan_ms']:.1f}",
            f"{r['descriptor_max_abs']:.1e} / {r['yaw_max_abs']:.1e}"
            if "descriptor_max_abs" in r
            else "—",
            str(r.get("nodes", "—")),
            f"{r['file_mb']:.1f}" if "file_mb" in r else "—",
            f"{r['load_s']:.2f}" if "load_s" in r else "—",
        )
    console.print(table)
    yt = Table(title="served vs no-scan, B=1, interleaved: where the served time goes (ms)")
    for c in ("threads", "served", "no-scan", "ratio", "stages", "kernel", "ratio, free scan"):
        yt.add_column(c, justify="right")
    for th in (1, 2):
        y = yard[f"b1_t{th}"]
        yt.add_row(
            str(th),
            *(f"{y[k]:.2f}" for k in ("served_ms", "noscan_ms", "ratio")),
            *(f"{y[k]:.2f}" if k in y else "—" for k in ("sessions_ms", "kernel_ms")),
            f"{y['ratio_with_a_free_scan']:.2f}" if "ratio_with_a_free_scan" in y else "—",
        )
    console.print(yt)
    rt = Table(title="ratios (goal: scan ÷ no-scan ≤ 1.25 at B=1; B=8 ≥ 1.5× B=1 per scan)")
    rt.add_column("ratio")
    rt.add_column("value", justify="right")
    for k, v in ratios.items():
        rt.add_row(k, f"{v:.2f}")
    console.print(rt)
    console.print(
        f"shipped graph: {work['total_flops'] / 1e9:.2f} GFLOP per scan "
        f"(dense {work['dense_flops'] / 1e9:.2f}, scan {work['scan_flops'] / 1e9:.2f}); "
        f"{achieved:.1f} GFLOP/s at B=1, 2 threads = {100 * work['fraction_of_peak']:.1f}% "
        f"of the {peak:.0f} GFLOP/s peak of 2 cores ({cpu})"
    )
    if peer is not None:
        pt = Table(title="served encoder vs OT-style peer (ONNX, 2 threads, interleaved)")
        v = peer["views"]
        for c in (
            "batch",
            f"ours, {v} views (as shipped) ms/scan",
            "ours, one pass ms/scan",
            "OT-style ms/scan",
            f"ours {v} views ÷ OT",
            "ours one pass ÷ OT",
        ):
            pt.add_column(c, justify="right")
        for b in ("b1", "b8"):
            r = peer[b]
            pt.add_row(
                b.upper(),
                f"{r['ours_views_ms_per_scan']:.1f}",
                f"{r['ours_ms_per_scan']:.1f}",
                f"{r['peer_ms_per_scan']:.1f}",
                f"{r['ours_views_over_peer']:.2f}",
                f"{r['ours_over_peer']:.2f}",
            )
        console.print(pt)
        console.print(
            f"parameters: ours {peer['ours_params'] / 1e6:.2f} M, OT-style "
            f"{peer['peer_params'] / 1e6:.2f} M; files {peer['ours_file_mb']:.1f} / "
            f"{peer['peer_file_mb']:.1f} MB"
        )
    for part, title in (("top_level", "top level"), ("inside_scan", "inside the Scan bodies")):
        rows = profile[part]
        total = sum(rows.values())
        pt = Table(title=f"onnxruntime profile of scan-loop, B=1, 1 thread: {title}")
        for c in ("op type", "ms/run", "share"):
            pt.add_column(c, justify="right")
        for k, v in list(rows.items())[:12]:
            pt.add_row(k, f"{v:.2f}", f"{100 * v / total:.0f}%")
        console.print(pt)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("json", type=Path, help="a record written by benchmarks/encoder.py")
    print_tables(Console(), json.loads(ap.parse_args().json.read_text()))


if __name__ == "__main__":
    main()
