"""``overlapmamba`` evaluation commands: a model on generated sequences (loop closure, across
sessions and sensors), on real scans, and the model card's report over the training presets'
runs. Each needs PyTorch (the train extra)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer
from rich.table import Table

from overlapmamba.cli.common import (
    check_torch,
    command_group,
    command_line,
    errors_table,
    friendly_errors,
    metrics_table,
    out,
)
from overlapmamba.core.outfiles import check_outputs, write_whole
from overlapmamba.core.rerank import Rerank

app, command = command_group("Model")

# eval's second stage by default: the service's (overlapmamba.core.rerank.Rerank's defaults).
RERANK_DEFAULT = f"{Rerank().shortlist},{Rerank().weight:g}"


def _second_stage(text: str) -> Rerank:
    """--rerank's value, or a usage error naming what is allowed."""
    try:
        return Rerank.parse(text)
    except ValueError as bad:
        raise typer.BadParameter(str(bad), param_hint="--rerank") from None


@command(
    "eval",
    epilog="Examples:\n\n  overlapmamba eval --checkpoint runs/om/best.pt "
    "--sequence data/synth/test --json test.json --plot pr.png\n\n"
    "  overlapmamba eval --checkpoint runs/om/best.pt --sequence data/synth/test-s1 "
    "--database data/synth/test   (second session against the first: AR@1/5/20)\n\n"
    "  overlapmamba eval --checkpoint models/overlapmamba-hdl64.onnx --sequence "
    "data/synth/test-s1-vlp16 --database data/synth/test-os1-128   (a VLP-16's drive "
    "against an OS1-128's map: across sensors)\n\n"
    "  overlapmamba eval --checkpoint models/overlapmamba-hdl64.onnx --sequence "
    "data/synth/test-vlp16 --scan-context   (a VLP-16 town, Scan Context beside)",
)
@friendly_errors
def eval_cmd(
    checkpoint: Annotated[
        Path, typer.Option(help="a .pt written by train, or an exported .onnx (the shipped model)")
    ],
    sequence: Annotated[
        Path,
        typer.Option(
            help="sequence with loops (e.g. the test preset), or a ROS recording (.bag, "
            "rosbag2, .mcap) with --odometry or --tf"
        ),
    ],
    database: Annotated[
        Path | None,
        typer.Option(
            help="another session of the same town, of any sensor: also query --sequence's "
            "scans against it (place recognition across sessions, AR@1/5/20, with Scan "
            "Context beside); a --sequence without a loop table is evaluated this way only"
        ),
    ] = None,
    sensor: Annotated[
        str | None,
        typer.Option(
            help="the catalogue sensor --sequence was recorded with (`overlapmamba sensors`); "
            "default: what its manifest says; a KITTI folder without one is KITTI's HDL-64E, "
            "any other recording the model's own sensor"
        ),
    ] = None,
    database_sensor: Annotated[str | None, typer.Option(help="the same for --database")] = None,
    scan_context: Annotated[
        bool,
        typer.Option("--scan-context", help="also Scan Context's loop closure on --sequence"),
    ] = False,
    json_out: Annotated[Path | None, typer.Option("--json", help="write the metrics here")] = None,
    plot: Annotated[
        Path | None,
        typer.Option(help="write PR curves here (.png, .pdf, .svg, …: what matplotlib writes)"),
    ] = None,
    rerank: Annotated[
        str,
        typer.Option(
            help="second stage, as the service answers: re-rank the K nearest descriptors by "
            "d² − WEIGHT · aligned yaw-feature correlation ('K,WEIGHT' or 'off'); reported "
            "beside the descriptor-only numbers"
        ),
    ] = RERANK_DEFAULT,
    topic: Annotated[
        str | None, typer.Option(help="ROS recordings: the PointCloud2 topic (if several)")
    ] = None,
    odometry: Annotated[
        str | None,
        typer.Option(help="ROS recordings: the nav_msgs/Odometry topic giving the poses"),
    ] = None,
    tf: Annotated[
        str | None,
        typer.Option(
            "--tf",
            help="ROS recordings: poses from /tf in this fixed frame (FIXED or FIXED:CHILD; "
            "CHILD defaults to the scans' frame)",
        ),
    ] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no progress bars")] = False,
) -> None:
    """Loop-closure AUC, F1max, Recall@1 and Recall@1%: all, same- and reverse-direction.
    A ROS recording is evaluated like a sequence: its odometry or /tf gives the poses, and the
    loop ground truth is computed from its scans and poses (the default protocol)."""
    check_torch()

    from overlapmamba.core.datasets import open_recording
    from overlapmamba.train.evaluate import evaluate_checkpoint, plot_pr

    def open_sequence(path: Path) -> Any:  # a sequence folder, or a ROS recording with poses
        named = database_sensor if path == database else sensor
        return open_recording(
            path, topic=topic, odometry=odometry, tf=tf, need_poses=True, sensor=named
        )

    second = _second_stage(rerank)
    _check_outputs(json_out, plot)  # before the evaluation's minutes, not after
    ev = evaluate_checkpoint(
        checkpoint,
        sequence,
        open_sequence,
        database=database,
        rerank=second,
        scan_context=scan_context,
        progress=not quiet,
    )
    name, scans = ev.sequence
    staged = f" + yaw re-rank (top {second.shortlist}, weight {second.weight:g})"
    runs = [("", "")] + ([(staged, "_reranked")] if second.on else [])
    if "metrics" not in ev.record:
        runs = []
        out.print(f"{name} has no loop table: evaluated against {database} only")
    s = ev.record["sensor"]
    out.print(f"{name}: {s['sensor']} scans, {s['input']} into the model's input")
    has_sc = "metrics_scan_context" in ev.record
    runs_sc = [(" — Scan Context", "_scan_context")] if has_sc else []
    for title, key in runs + runs_sc:
        out.print(
            metrics_table(
                f"{checkpoint.name}{title} on {name} ({scans} scans)", ev.record["metrics" + key]
            )
        )
    for title, key in runs:
        far = ev.record["errors" + key]["all"]["far_m"]
        out.print(
            errors_table(
                f"Where F1max is lost{title}, at each subset's threshold: false alarms near (a "
                f"neighbour within {far:g} m) or far (a look-alike); missed loops with a wrong "
                "top-1, or a right one rejected",
                ev.record["errors" + key],
            )
        )
    if ev.database is not None:
        cross = ev.record["cross_session"]
        table = Table(
            title=f"Across sessions: {name} against {ev.database[0]} ({ev.database[1]} scans); "
            f"queries with a database scan within {cross['model']['radius_m']:g} m count"
        )
        bands = " / ".join(cross["model"]["wrong_top1"])
        for col in ("method", "queries", "AR@1", "AR@5", "AR@20", f"wrong top-1 at {bands}"):
            table.add_column(col, justify="left" if col == "method" else "right")
        rows = [("OverlapMamba", cross["model"])]
        if "model_reranked" in cross:
            rows.append((f"OverlapMamba{staged}", cross["model_reranked"]))
        for label, r in (*rows, ("Scan Context", cross["scan_context"])):
            table.add_row(
                label,
                str(r["queries"]),
                *(f"{r[f'ar@{n}']:.3f}" for n in (1, 5, 20)),
                " / ".join(str(v) for v in r["wrong_top1"].values()),
            )
        out.print(table)
    if json_out is not None:
        ev.record["command"] = command_line(
            "eval",
            checkpoint=checkpoint,
            sequence=sequence,
            database=database,
            sensor=sensor,
            database_sensor=database_sensor,
            scan_context=scan_context,
            rerank=None if rerank == RERANK_DEFAULT else rerank,
            topic=topic,
            odometry=odometry,
            tf=tf,
            json=json_out,
        )
        _write_json(json_out, ev.record)
    if plot is not None and ev.results:
        plot_pr(ev.results, plot, f"{name}: loop closure" + (staged if second.on else ""))
    if json_out or plot:
        out.print(f"wrote {', '.join(str(p) for p in (json_out, plot) if p)}")


def _check_outputs(json_out: Path | None, plot: Path | None) -> None:
    """Where the results go, checked (their folders made) before the work that makes them;
    a plot in any format matplotlib writes."""
    formats = None
    if plot is not None:
        from matplotlib.backend_bases import FigureCanvasBase

        formats = FigureCanvasBase.get_supported_filetypes()
    try:
        check_outputs(("--json", json_out, None), ("--plot", plot, formats))
    except ValueError as err:
        raise typer.BadParameter(str(err)) from None


def _write_json(path: Path, record: dict[str, Any]) -> None:
    """Strict JSON (never NaN), written whole or not at all."""
    from overlapmamba.train.health import strict_json

    write_whole(path, strict_json(record, indent=2) + "\n")


@command(
    "eval-real",
    epilog="Examples:\n\n  overlapmamba eval-real --checkpoint runs/om/best.pt --json real.json"
    "\n\n  overlapmamba eval-real --checkpoint models/overlapmamba-hdl64.onnx --beams 32,16   "
    "(KITTI queries thinned to 32 and 16 rings against whole scans)\n\n"
    "  overlapmamba eval-real --checkpoint models/overlapmamba-hdl64.onnx --sequence "
    "../shared/data/nuscenes_scene0061 --sensor hdl32 --hit-radius 6",
)
@friendly_errors
def eval_real_cmd(
    checkpoint: Annotated[
        Path, typer.Option(help="a .pt written by train, or an exported .onnx (the shipped model)")
    ],
    sequence: Annotated[Path, typer.Option(help="real KITTI-layout sequence")] = Path(
        "../shared/data/kitti00_0000-0100"
    ),
    seed: Annotated[int, typer.Option(min=0, help="seed of the random yaw angles")] = 0,
    hit_radius: Annotated[float, typer.Option(min=0.1, help="retrieval hit radius (m)")] = 3.0,
    json_out: Annotated[Path | None, typer.Option("--json", help="write the metrics here")] = None,
    rerank: Annotated[
        str,
        typer.Option(
            help="odd→even retrieval's second stage, as the service answers ('K,WEIGHT' or "
            "'off'); reported beside the descriptor-only numbers"
        ),
    ] = RERANK_DEFAULT,
    sensor: Annotated[
        str | None,
        typer.Option(
            "--sensor",
            "--profile",
            help="the catalogue sensor the scans come from (e.g. hdl32 for the nuScenes scans; "
            "default: KITTI's HDL-64E); they enter the model as that sensor's scans",
        ),
    ] = None,
    beams: Annotated[
        str | None,
        typer.Option(
            help="also retrieval with the queries thinned to these ring counts ('32,16': every "
            "second and fourth ring, found by elevation) against whole scans, and each thinned "
            "scan's cosine to its whole self"
        ),
    ] = None,
) -> None:
    """Real scans: yaw invariance at random angles, odd→even retrieval, yaw-estimate error;
    with --beams, the same queries with fewer rings."""
    check_torch()

    from overlapmamba.core.datasets import open_sequence
    from overlapmamba.train.checkpoint import load_model
    from overlapmamba.train.realscans import eval_real

    try:
        counts = tuple(int(b) for b in beams.split(",")) if beams else ()
    except ValueError:
        raise typer.BadParameter(f"--beams {beams!r}: whole numbers, e.g. 32,16") from None
    _check_outputs(json_out, None)
    model, profile, _ = load_model(checkpoint)
    seq = open_sequence(sequence, **({"sensor": _known_sensor(sensor)} if sensor else {}))
    second = _second_stage(rerank)
    try:
        r = eval_real(
            model, profile, seq, seed=seed, hit_radius=hit_radius, rerank=second, beams=counts
        )
    except ValueError as err:
        raise typer.BadParameter(str(err)) from None
    inv, ret, yaw = r["yaw_invariance"], r["retrieval_odd_to_even"], r["yaw_error_deg"]
    table = Table(title=f"{checkpoint.name} on real scans: {seq.name} ({r['scans']} scans)")
    table.add_column("check")
    table.add_column("result", justify="right")
    rows = [
        (
            "descriptor cosine under random yaw (min / mean)",
            f"{inv['cosine_min']:.6f} / {inv['cosine_mean']:.6f}",
        ),
        (
            "turned-copy distance / distance between different scans",
            f"{inv['turned_over_other_distance']:.2e}",
        ),
        (
            "turned-copy distance / 1 m step distance (squared, medians)",
            f"{inv['turned_distance_median']:.2e} / {inv['one_metre_step_distance_median']:.2e}"
            f" = {inv['turned_over_one_metre_step']:.3f}",
        ),
        (
            f"odd→even Recall@1 (hit within {ret['hit_radius_m']:g} m), Scan Context's",
            f"{ret['recall@1']:.3f}, {ret['scan_context']['recall@1']:.3f}",
        ),
        (
            "odd→even Recall@5, Scan Context's",
            f"{ret['recall@5']:.3f}, {ret['scan_context']['recall@5']:.3f}",
        ),
    ]
    if "reranked" in ret:
        rr = ret["reranked"]
        top = rr.get("shortlist", rr.get("k"))  # "k" in reports written before the rename
        rows.append(
            (
                f"odd→even Recall@1 / @5 + yaw re-rank (top {top}, weight {rr['weight']:g})",
                f"{rr['recall@1']:.3f} / {rr['recall@5']:.3f}",
            )
        )
    for name, key in (("turned copy", "vs_turned_copy"), ("retrieved frame", "vs_retrieved_frame")):
        e = yaw[key]
        rows.append(
            (
                f"yaw error vs {name} (median / p90 / max, °)",
                f"{e['median']:.2f} / {e['p90']:.2f} / {e['max']:.2f}",
            )
        )
    rows.insert(0, ("sensor (into the model's input)", f"{r['sensor']} ({r['input']})"))
    for b, t in r.get("thinned", {}).items():
        for how in ("declared", "undeclared"):
            x = t[how]
            rows.append(
                (
                    f"{b} rings, {how} ({x['input']}): Recall@1 / @5, cosine to whole "
                    "(median / min)",
                    f"{x['recall@1']:.3f} / {x['recall@5']:.3f}, "
                    f"{x['cosine_to_full']['median']:.3f} / {x['cosine_to_full']['min']:.3f}",
                )
            )
    for k, v in rows:
        table.add_row(k, v)
    out.print(table)
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        cmd = command_line(
            "eval-real",
            checkpoint=checkpoint,
            sequence=sequence,
            sensor=sensor,
            seed=seed or None,
            hit_radius=None if hit_radius == 3.0 else hit_radius,
            rerank=None if rerank == RERANK_DEFAULT else rerank,
            beams=beams,
            json=json_out,
        )
        record = {"command": cmd, "checkpoint": str(checkpoint), **r}
        _write_json(json_out, record)
        out.print(f"wrote {json_out}")


def _known_sensor(name: str) -> str:
    from overlapmamba.core.sensors.catalogue import catalogue_name

    return catalogue_name(name)


@command(
    "report",
    epilog="Example (after `make data` and the training presets):\n\n"
    "  overlapmamba report --runs runs --test data/synth/test --test data/synth/test-b "
    "--test data/synth/test-c --second-session data/synth/test-s1 --out reports/model",
)
@friendly_errors
def report_cmd(
    runs: Annotated[Path, typer.Option(help="folder holding the preset runs")] = Path("runs"),
    test: Annotated[
        list[Path] | None,
        typer.Option(
            help="test town with loops (repeat for several; default: the test, test-b and "
            "test-c presets that exist, with test-s1 as the second session)"
        ),
    ] = None,
    second_session: Annotated[
        Path | None,
        typer.Option(
            help="a second drive through the first --test town: queried against it "
            "(AR@1/5/20 across sessions)"
        ),
    ] = None,
    out_dir: Annotated[Path, typer.Option("--out", help="report folder")] = Path("reports/model"),
    model: Annotated[
        Path | None,
        typer.Option(
            help="the exported encoder the shipped row and the real-scan checks read when the "
            "shipped run's best.pt is not under --runs (default: models/overlapmamba-hdl64.onnx;"
            " e.g. the one-view twin)"
        ),
    ] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no progress bars")] = False,
) -> None:
    """Model-card tables I–IV, cross-session recall and real-scan checks: JSON, Markdown, PNG."""
    check_torch()
    from overlapmamba.train.presets import SECOND_SESSION, TEST_DATA
    from overlapmamba.train.report import SHIPPED_ONNX, build_report

    if model is not None and (model.suffix != ".onnx" or not model.is_file()):
        raise typer.BadParameter(f"--model {model}: give an exported encoder (.onnx) that exists")

    tests = test or [Path(t) for t in TEST_DATA if (Path(t) / "manifest.json").is_file()]
    tests = tests or [Path(TEST_DATA[0])]  # none yet: the message below says what to run
    if (
        second_session is None
        and test is None
        and (Path(SECOND_SESSION) / "manifest.json").is_file()
    ):
        second_session = Path(SECOND_SESSION)
    for t in [*tests, *([second_session] if second_session else [])]:
        if not (t / "manifest.json").is_file():
            raise typer.BadParameter(f"{t} is not a generated sequence: run `make data` first")
    sessions = (tests[0], second_session) if second_session else None
    report = build_report(
        runs,
        tests,
        out_dir,
        progress=not quiet,
        sessions=sessions,
        shipped_onnx=model or SHIPPED_ONNX,
    )
    for note in report["notes"]:
        out.print(f"[yellow]note:[/] {note}")
    for label, subs in report["table1"].items():
        out.print(metrics_table(f"test towns (mean of {len(tests)}): {label}", subs))
    out.print(f"wrote {out_dir}/report.json, tables.md, pr_test.png")
