"""How ``overlapmamba-client`` shows things: progress bars, poses and matrices, the stats
table."""

from __future__ import annotations

from typing import Any

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table


def progress(console: Console) -> Progress:
    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[rate]:.1f} scans/s · {task.fields[latency]:.0f} ms"),
        TimeElapsedColumn(),
        console=console,
    )


def pose_text(T: np.ndarray | None) -> str:
    if T is None:
        return ""
    return f"{T[0, 3]:.2f}, {T[1, 3]:.2f} / {np.degrees(np.arctan2(T[1, 0], T[0, 0])):.1f}"


def matrix_text(T: np.ndarray | None) -> str:
    if T is None:
        return "  (none)"
    return "\n".join("  " + "  ".join(f"{x:9.4f}" for x in row) for row in T)


def _fixed(x: float | None, digits: int) -> str:
    """A figure, or – where the service has none yet (no query, no request)."""
    return "–" if x is None else f"{x:.{digits}f}"


def stats_table(s: dict[str, Any]) -> Table:
    table = Table(title=f"model {s.get('model_id')} · up {s.get('uptime_s', 0):.0f} s")
    table.add_column("metric")
    table.add_column("value", justify="right")
    for key in ("keyframes", "inserts", "queries", "loop_closures"):
        if key in s:
            table.add_row(key, str(s[key]))
    table.add_row("loop-closure rate", _fixed(s.get("loop_closure_rate"), 3))
    v = s.get("verification") or {}
    if v:
        table.add_row("candidates verified / rejected", f"{v['verified']} / {v['rejected']}")
    table.add_row("queries/s (1 min)", _fixed(s.get("queries_per_s_1m"), 2))
    for stage, p in s.get("latency_ms", {}).items():
        table.add_row(f"{stage} p50 / p99 ms", f"{_fixed(p['p50'], 1)} / {_fixed(p['p99'], 1)}")
    for name, r in s.get("robots", {}).items():
        table.add_row(f"robot {name}", f"{r['observations']} obs, {r['loop_closures']} loops")
    if "map" in s:
        table.add_row("map keyframes", str(s["map"].get("keyframes")))
    return table


def fleet_table(report: Any, robots: int, rate: float) -> Table:
    """A fleet run's report (:class:`overlapmamba.client.fleet.FleetReport`), as printed."""
    table = Table(title=f"fleet: {robots} robots × {rate:g} Hz for {report.duration_s:.1f} s")
    table.add_column("metric")
    table.add_column("value", justify="right")
    lat = report.latency_ms
    rows = [
        ("observations", str(report.observations)),
        ("throughput (obs/s)", f"{report.throughput_per_s:.2f}"),
        (
            "latency p50 / p95 / p99 ms",
            " / ".join("—" if lat[q] is None else f"{lat[q]:.0f}" for q in ("p50", "p95", "p99")),
        ),
        ("errors", ", ".join(f"{k}: {v}" for k, v in report.errors.items()) or "none"),
        (
            "tries refused, then retried",
            ", ".join(f"{k}: {v}" for k, v in report.retried.items()) or "none",
        ),
        ("keyframes inserted", str(report.inserted)),
        ("loop closures accepted", str(report.loop_closures)),
        ("of which verified (with a relative pose)", str(report.verified_closures)),
    ]
    if report.correct is not None:
        rows += [
            ("correct (ground truth)", str(report.correct)),
            ("queries with a loop available", str(report.queries_with_loop)),
            ("precision", "n/a" if report.precision is None else f"{report.precision:.3f}"),
            ("recall", "n/a" if report.recall is None else f"{report.recall:.3f}"),
        ]
    if report.pose_error:
        t, y = report.pose_error["translation_m"], report.pose_error["yaw_deg"]
        rows += [
            ("pose error median / p90 (m)", f"{t['median']:.3f} / {t['p90']:.3f}"),
            ("yaw error median / p90 (°)", f"{y['median']:.2f} / {y['p90']:.2f}"),
        ]
    if report.covariance:
        c = report.covariance
        rows.append(
            (
                "inside their 95% ellipsoid (covariance)",
                f"{c['inside_95']:.3f} of {int(c['closures'])} right verified closures",
            )
        )
    for name, value in rows:
        table.add_row(name, value)
    return table


def report_skipped(skipped: list[str], frames: int) -> None:
    """After a drive: the scans left out because they could not be read, on stderr (the
    first few reasons); a drive none of whose scans could be read is an error (exit 2)."""
    if not skipped:
        return
    if len(skipped) == frames:
        raise ValueError(f"none of the {frames} scans could be read; the first: {skipped[0]}")
    err = Console(stderr=True)
    err.print(
        f"[yellow]note:[/] {len(skipped)} of {frames} scans could not be read and were left out:",
    )
    for why in skipped[:5]:
        err.print(f"  {why}", markup=False)
    if len(skipped) > 5:
        err.print(f"  … and {len(skipped) - 5} more")


def note_unposed(drive: Any) -> None:
    """Before a drive: how many of its scans go without a pose (none near their stamps), and
    how many of its pose samples were left out as no pose."""
    bad = getattr(drive.seq, "bad_pose_samples", 0)
    if bad:
        Console(stderr=True).print(
            f"[yellow]note:[/] {bad} odometry or /tf samples were left out as no pose (a zero "
            "or non-finite quaternion or position, an unnamed frame); where they were on the "
            "LiDAR's chain, its scans near them take the poses around them",
        )
    if drive.unposed:
        why = (
            "started later, paused, or its samples there were left out"
            if bad
            else ("started later, or paused")
        )
        Console(stderr=True).print(
            f"[yellow]note:[/] {drive.unposed} of {len(drive)} scans have no pose sample "
            f"within 0.1 s of their stamp (the odometry or /tf {why}): they are sent without "
            "a pose",
        )
