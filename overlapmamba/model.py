"""``overlapmamba`` model commands: train, evaluate (sequences, real scans), export to ONNX
and the model report. Each needs PyTorch (the train extra)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer
from rich.table import Table

from lidar_core.rerank import Rerank
from lidar_core.views import MAX_VIEWS
from overlapmamba.common import (
    check_torch,
    command_group,
    command_line,
    errors_table,
    friendly_errors,
    metrics_table,
    out,
)

app, command = command_group("Model")

# eval's second stage by default: the service's (lidar_core.rerank.Rerank's defaults).
RERANK_DEFAULT = f"{Rerank().k},{Rerank().weight:g}"


def _second_stage(text: str) -> Rerank:
    """--rerank's value, or a usage error naming what is allowed."""
    try:
        return Rerank.parse(text)
    except ValueError as bad:
        raise typer.BadParameter(str(bad), param_hint="--rerank") from None


@command(
    "train",
    epilog="Examples:\n\n  overlapmamba train --data data/synth/train --val data/synth/val "
    "--out runs/om\n\n  overlapmamba train --out runs/om --resume --epochs 20\n\n"
    "  overlapmamba train --data A --data B --val V --out runs/x --config cfg.toml\n\n"
    "  overlapmamba train --preset default   (the shipped model; writes runs/default)",
)
@friendly_errors
def train_cmd(
    output: Annotated[
        Path | None,
        typer.Option("--out", "-o", help="run folder (checkpoints, metrics); --preset: runs/NAME"),
    ] = None,
    preset: Annotated[
        str | None,
        typer.Option(
            help="named recipe with its data and configs, e.g. default (the shipped model); "
            "the list is in model_export/presets.py, and an unknown name prints it"
        ),
    ] = None,
    data: Annotated[
        list[Path] | None,
        typer.Option(
            "--data",
            help="training sequence (repeat for several); needs "
            "ground_truth/overlaps.npz as gen-data writes it",
        ),
    ] = None,
    val: Annotated[Path | None, typer.Option(help="validation sequence")] = None,
    config: Annotated[
        Path | None, typer.Option(help=".json/.toml with [model] and [train] sections")
    ] = None,
    epochs: Annotated[
        int | None, typer.Option(min=1, help="total epochs (extends on --resume)")
    ] = None,
    epoch_scans: Annotated[int | None, typer.Option(min=1, help="scans per epoch")] = None,
    batch_size: Annotated[
        int | None,
        typer.Option(
            min=2,
            help="a multiple of the group size (4 by default: anchor, 2 positives, 1 near miss)",
        ),
    ] = None,
    lr: Annotated[float | None, typer.Option(min=0.0)] = None,
    loss: Annotated[str | None, typer.Option(help="imtrihard or triplet")] = None,
    seed: Annotated[int | None, typer.Option(min=0)] = None,
    device: Annotated[str | None, typer.Option(help="cpu or cuda")] = None,
    init: Annotated[
        Path | None,
        typer.Option(
            help="start from this network: a checkpoint (.pt) or an exported encoder (.onnx, "
            "weights recovered exactly; needs freeze_bn, which it sets)"
        ),
    ] = None,
    resume: Annotated[bool, typer.Option("--resume", help="continue the run in --out")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no progress bars")] = False,
) -> None:
    """Train OverlapMamba on synthetic sequences; validate, checkpoint and plot every epoch."""
    check_torch()
    from model_export.model import OverlapMambaConfig
    from model_export.train import TrainConfig, load_config_file, train

    overrides = {
        k: v
        for k, v in dict(
            epoch_scans=epoch_scans,
            batch_size=batch_size,
            lr=lr,
            loss=loss,
            seed=seed,
            device=device,
            init=None if init is None else str(init),
            freeze_bn=True if init is not None and init.suffix == ".onnx" else None,
        ).items()
        if v is not None
    }
    model_cfg = train_cfg = None
    if preset is not None:
        from model_export.presets import get_preset

        if resume or config is not None or data or val:
            raise typer.BadParameter(
                "--preset fixes the data and configs: drop --data/--val/--config/--resume "
                "(resume a preset run with --out runs/NAME --resume)"
            )
        recipe = get_preset(preset)
        data, val = [Path(d) for d in recipe.data], Path(recipe.val)
        missing = [p for p in (*data, val) if not (p / "manifest.json").is_file()]
        if missing:
            raise typer.BadParameter(
                f"preset {preset!r} needs {', '.join(map(str, missing))}: run `make data` "
                "(or overlapmamba gen-data DIR --preset train|val) from the repository root"
            )
        model_cfg = OverlapMambaConfig.from_dict(recipe.model)
        train_cfg = TrainConfig.from_dict({**recipe.train, **overrides})
        output = output or Path("runs") / preset
    elif resume:
        if config is not None or overrides or data or val:
            raise typer.BadParameter(
                "--resume continues the run as configured: give only --out and --epochs"
            )
    else:
        if not data or val is None:
            raise typer.BadParameter("give --data (at least one) and --val, or --resume")
        model_d, train_d = load_config_file(config) if config else ({}, {})
        train_cfg = TrainConfig.from_dict({**train_d, **overrides})
        try:  # a run from --init takes its network's config unless [model] says otherwise
            model_cfg = (
                OverlapMambaConfig.from_dict(model_d) if model_d or not train_cfg.init else None
            )
        except (TypeError, ValueError) as err:
            raise typer.BadParameter(f"[model] config: {err}") from None
    if output is None:
        raise typer.BadParameter("give --out (the run folder), or a --preset")
    history = train(
        data or [],
        val,
        output,
        model_cfg,
        train_cfg,
        resume=resume,
        epochs=epochs,
        progress=not quiet,
    )
    if history:
        out.print(
            metrics_table(f"Validation after epoch {history[-1]['epoch']}", history[-1]["val"])
        )
    out.print(f"checkpoints, metrics.json and curves.png in {output}")


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
    plot: Annotated[Path | None, typer.Option(help="write PR curves here (.png)")] = None,
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
    import json

    from lidar_core.datasets import open_recording
    from model_export.evaluate import evaluate_checkpoint, plot_pr

    def open_sequence(path: Path) -> Any:  # a sequence folder, or a ROS recording with poses
        named = database_sensor if path == database else sensor
        return open_recording(
            path, topic=topic, odometry=odometry, tf=tf, need_poses=True, sensor=named
        )

    second = _second_stage(rerank)
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
    staged = f" + yaw re-rank (top {second.k}, weight {second.weight:g})"
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
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(ev.record, indent=2) + "\n")
    if plot is not None and ev.results:
        plot_pr(ev.results, plot, f"{name}: loop closure" + (staged if second.on else ""))
    if json_out or plot:
        out.print(f"wrote {', '.join(str(p) for p in (json_out, plot) if p)}")


@command(
    "export",
    epilog="Examples:\n\n  overlapmamba export runs/om/best.pt --out models/overlapmamba-hdl64.onnx"
    "\n\n  overlapmamba export runs/om/best.pt --out fp32.onnx --weights float32"
    "\n\n  overlapmamba export models/overlapmamba-hdl64.onnx --views 2 --out two-views.onnx",
)
@friendly_errors
def export_cmd(
    checkpoint: Annotated[
        Path,
        typer.Argument(
            help="a .pt written by train; or an exported .onnx, to write the same graph with "
            "another --views"
        ),
    ],
    out_path: Annotated[Path, typer.Option("--out", help="the .onnx file to write")],
    weights: Annotated[
        str, typer.Option(help="storage of the large head matrix: int8 or float32")
    ] = "int8",
    views: Annotated[
        int,
        typer.Option(
            min=1,
            max=MAX_VIEWS,
            help="sub-column views that describe a scan: its descriptor is the mean of this "
            "many projections, each turned by a further 1/views of a column (a continuous "
            "turn then barely moves it; the encoder runs this many times per scan)",
        ),
    ] = 1,
) -> None:
    """ONNX encoder (scan as Scan loops) with its metadata, verified against PyTorch."""
    check_torch()
    from model_export.checkpoint import load_model
    from model_export.export import export_onnx
    from model_export.model import OverlapMamba
    from model_export.modelfile import with_views

    if out_path.suffix != ".onnx":
        raise typer.BadParameter(f"--out must end in .onnx, got {out_path.name!r}")
    if checkpoint.suffix == ".onnx":
        if weights != "int8":
            raise typer.BadParameter(
                "an exported encoder keeps its weights as they are; --weights applies to a .pt",
                param_hint="--weights",
            )
        meta = with_views(checkpoint, out_path, views)
        out.print(
            f"wrote {out_path}: the graph of {checkpoint} with {meta.views} view(s) per scan, "
            f"model id {meta.model_id}"
        )
        return
    model, profile, ckpt = load_model(checkpoint)
    assert isinstance(model, OverlapMamba)  # load_model gives an encoder only for .onnx
    res = export_onnx(model, profile, out_path, checkpoint=ckpt, weight_format=weights, views=views)
    meta, v = res.metadata, res.verification
    table = Table(title=f"exported {res.path}", show_header=False)
    for key, value in (
        ("model id", meta.model_id),
        ("weights", f"{meta.weights}, large matrices {meta.weight_format}"),
        ("sensor", f"{profile.name} {profile.height}×{profile.width}"),
        ("views per scan", str(meta.views)),
        ("file", f"{res.size_bytes / 1e6:.1f} MB, {res.nodes} nodes, {res.scan_nodes} Scan"),
        (
            "descriptor vs PyTorch",
            f"max abs {v['descriptor_max_abs']:.2e}, min cosine {v['descriptor_min_cosine']:.6f}",
        ),
        ("yaw features vs PyTorch", f"max abs {v['yaw_features_max_abs']:.2e}"),
        ("source", meta.source_commit),
        ("time", f"{res.seconds:.1f} s"),
    ):
        table.add_row(key, value)
    out.print(table)


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
    import json

    from lidar_core.datasets import open_sequence
    from model_export.checkpoint import load_model
    from model_export.realscans import eval_real

    try:
        counts = tuple(int(b) for b in beams.split(",")) if beams else ()
    except ValueError:
        raise typer.BadParameter(f"--beams {beams!r}: whole numbers, e.g. 32,16") from None
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
        rows.append(
            (
                f"odd→even Recall@1 / @5 + yaw re-rank (top {rr['k']}, weight {rr['weight']:g})",
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
        json_out.write_text(json.dumps(record, indent=2) + "\n")
        out.print(f"wrote {json_out}")


def _known_sensor(name: str) -> str:
    from lidar_core.sensors.catalogue import catalogue_name

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
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no progress bars")] = False,
) -> None:
    """Model-card tables I–IV, cross-session recall and real-scan checks: JSON, Markdown, PNG."""
    check_torch()
    from model_export.presets import SECOND_SESSION, TEST_DATA
    from model_export.report import build_report

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
    report = build_report(runs, tests, out_dir, progress=not quiet, sessions=sessions)
    for note in report["notes"]:
        out.print(f"[yellow]note:[/] {note}")
    for label, subs in report["table1"].items():
        out.print(metrics_table(f"test towns (mean of {len(tests)}): {label}", subs))
    out.print(f"wrote {out_dir}/report.json, tables.md, pr_test.png")
