"""``overlapmamba`` — server and training tasks.

Commands are thin: they parse options, call the library, and turn library errors into a red
message and exit code 2 (bad input) instead of a traceback.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import wraps
from pathlib import Path
from typing import Annotated, Any, TypeVar

import typer
from rich.console import Console
from rich.table import Table

from lidar_core.errors import LidarCoreError

app = typer.Typer(
    name="overlapmamba",
    help="LiDAR place recognition with OverlapMamba: data tools, training, export and serving.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
console = Console(stderr=True, soft_wrap=True)
out = Console()

F = TypeVar("F", bound=Callable[..., Any])


def _friendly_errors(func: F) -> F:
    @wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except LidarCoreError as err:
            console.print(f"[bold red]error:[/] {err.message}")
            raise typer.Exit(2) from None

    return wrapper  # type: ignore[return-value]


SensorOpt = Annotated[
    str,
    typer.Option(
        "--sensor", "-s", help="Built-in profile (kitti-hdl64, hdl32) or a .json/.toml profile."
    ),
]
MaxRangeOpt = Annotated[
    float | None,
    typer.Option("--max-range", min=0.01, help="Override the profile's max range (m)."),
]


def _profile(sensor: str, **overrides: Any) -> Any:
    from lidar_core.sensors import get_profile

    return get_profile(sensor).replace(**overrides)


def _check_out_suffix(path: Path) -> Path:
    if path.suffix.lower() not in {".npy", ".png"}:
        raise typer.BadParameter(f"{path.name}: allowed output suffixes are .npy and .png")
    return path


@app.command(
    "range-image",
    epilog="Examples:\n\n  overlapmamba range-image 000000.bin --max-range 50 --out depth.npy\n\n"
    "  overlapmamba range-image cloud.pcd --sensor hdl32 --out view.png",
)
@_friendly_errors
def range_image(
    scan: Annotated[Path, typer.Argument(exists=True, dir_okay=False, help=".bin, .npy or .pcd")],
    output: Annotated[
        Path,
        typer.Option(
            "--out",
            "-o",
            callback=_check_out_suffix,
            help="X.npy (H×W float32 metres) or X.png (a colourised view for people).",
        ),
    ],
    sensor: SensorOpt = "kitti-hdl64",
    max_range: MaxRangeOpt = None,
    min_range: Annotated[float | None, typer.Option(min=0.0)] = None,
    fov_up: Annotated[float | None, typer.Option(help="degrees")] = None,
    fov_down: Annotated[float | None, typer.Option(help="degrees")] = None,
    height: Annotated[int | None, typer.Option(min=1)] = None,
    width: Annotated[int | None, typer.Option(min=1)] = None,
    empty_value: Annotated[
        float | None, typer.Option(help="value of pixels with no return")
    ] = None,
    row_scale: Annotated[int, typer.Option(min=1, max=16, help="PNG row repeat")] = 4,
) -> None:
    """Project one scan to a range image (paper eq. 4; the nearest point wins each pixel)."""
    import numpy as np

    from lidar_core.io import read_points
    from lidar_core.projection import project, valid_mask

    profile = _profile(
        sensor,
        max_range=max_range,
        min_range=min_range,
        fov_up_deg=fov_up,
        fov_down_deg=fov_down,
        height=height,
        width=width,
        empty_value=empty_value,
    )
    points = read_points(scan)
    image = project(points, profile)
    output.parent.mkdir(parents=True, exist_ok=True)
    if output.suffix.lower() == ".npy":
        np.save(output, image)
    else:
        from PIL import Image

        from lidar_core.visualize import colorize

        Image.fromarray(colorize(image, profile, scale=row_scale)).save(output)
    valid = valid_mask(image, profile)
    out.print(
        f"{scan.name}: {len(points)} points → {image.shape[0]}×{image.shape[1]} "
        f"({profile.name}, max range {profile.max_range:g} m), "
        f"{valid.mean():.1%} pixels valid → {output}"
    )


@app.command(
    "ground-truth",
    epilog="Example:\n\n  overlapmamba ground-truth data/synth/00 --radius 30 --min-overlap 0.3",
)
@_friendly_errors
def ground_truth(
    seq_dir: Annotated[Path, typer.Argument(exists=True, file_okay=False, help="sequence folder")],
    kind: Annotated[str, typer.Option(help="auto, kitti or pcd-folder")] = "auto",
    sensor: Annotated[
        str | None, typer.Option("--sensor", "-s", help="default: the sequence's own sensor")
    ] = None,
    max_range: MaxRangeOpt = None,
    exclude_recent: Annotated[int, typer.Option(min=0, help="loops need i − j > this")] = 100,
    radius: Annotated[float, typer.Option(min=0.0, help="pre-filter distance (m)")] = 30.0,
    min_overlap: Annotated[float, typer.Option(min=0.0, max=1.0)] = 0.3,
    threshold: Annotated[float, typer.Option(min=0.0, help="range agreement τ (m)")] = 1.0,
    cache: Annotated[
        Path | None, typer.Option("--out", "-o", help="cache file (.npz); default: automatic")
    ] = None,
    no_cache: Annotated[bool, typer.Option("--no-cache", help="always recompute")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no progress bar")] = False,
) -> None:
    """Compute (or load the cached) loop ground-truth table of a sequence."""
    from lidar_core.datasets import open_sequence
    from lidar_core.overlap import default_cache_path, loop_ground_truth

    seq = open_sequence(seq_dir, kind=kind)
    profile = _profile(sensor or seq.sensor or "kitti-hdl64", max_range=max_range)
    target: Path | bool = False if no_cache else (cache if cache is not None else True)
    gt = loop_ground_truth(
        seq,
        profile,
        exclude_recent=exclude_recent,
        radius=radius,
        min_overlap=min_overlap,
        threshold=threshold,
        cache=target,
        progress=not quiet,
    )
    where = (
        "not cached"
        if target is False
        else cache
        if cache is not None
        else default_cache_path(seq, gt.params["fingerprint"])
    )
    table = Table(title=f"Loop ground truth: {seq.name}", show_header=False)
    for k, v in [
        ("frames", len(seq)),
        ("sensor profile", profile.name),
        ("candidate pairs (< radius, gap > exclude_recent)", len(gt.query)),
        ("loop pairs (overlap > min_overlap)", int(gt.is_loop.sum())),
        ("queries with a loop", int(gt.has_loop().sum())),
        ("cache", str(where)),
    ]:
        table.add_row(k, str(v))
    out.print(table)


@app.command(
    "gen-data",
    epilog="Examples:\n\n  overlapmamba gen-data data/synth/train --preset train\n\n"
    "  overlapmamba gen-data data/synth/s42 --seed 42 --frames 1200 --sensor hdl32\n\n"
    "  overlapmamba gen-data data/synth/test-s1 --preset test --session 1   "
    "(a second drive through the test town)",
)
@_friendly_errors
def gen_data(
    out_dir: Annotated[
        Path, typer.Argument(file_okay=False, help="new, empty folder for the sequence")
    ],
    seed: Annotated[int | None, typer.Option(min=0, help="world and drive seed")] = None,
    session: Annotated[
        int,
        typer.Option(
            min=0,
            max=1000,
            help="0: the town's first drive; k > 0: another drive through the same town "
            "(own route, parked cars, traffic, people, noise)",
        ),
    ] = 0,
    frames: Annotated[
        int | None, typer.Option(min=2, max=100_000, help="scans to simulate")
    ] = None,
    sensor: Annotated[str, typer.Option(help="kitti-hdl64 or hdl32")] = "kitti-hdl64",
    preset: Annotated[
        str | None, typer.Option(help="train, val or test: fixed seed, size and sensor")
    ] = None,
    split: Annotated[
        str, typer.Option(help="train, val or test (recorded in the manifest)")
    ] = "train",
    nodes: Annotated[
        int | None, typer.Option(min=2, max=20, help="street-grid nodes per side (town size)")
    ] = None,
    gt_radius: Annotated[
        float | None,
        typer.Option(
            min=1.0,
            max=200.0,
            help="pairwise overlaps for pairs closer than this (m; default 30, or the preset's)",
        ),
    ] = None,
    no_ground_truth: Annotated[
        bool, typer.Option("--no-ground-truth", help="skip the overlap tables")
    ] = False,
    workers: Annotated[int, typer.Option(min=1, max=64, help="processes (one per core)")] = 2,
    stall_timeout: Annotated[
        float,
        typer.Option(
            min=1.0, help="seconds without a finished scan or chunk before a worker counts as stuck"
        ),
    ] = 600.0,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no progress bars")] = False,
) -> None:
    """Simulate a synthetic town and a drive with revisits; write a KITTI-layout sequence."""
    from model_export.synth.generate import GenConfig, generate
    from model_export.synth.presets import preset as get_preset
    from model_export.synth.workers import WorkerError

    if preset is not None:
        if seed is not None or frames is not None or nodes is not None:
            raise typer.BadParameter(
                "--preset fixes seed, frames and town size; drop --seed/--frames/--nodes "
                "or drop --preset"
            )
        try:
            cfg = get_preset(preset)
        except ValueError as err:
            raise typer.BadParameter(str(err)) from None
        if gt_radius is not None:
            cfg = cfg.model_copy(update={"gt_radius": gt_radius})
        if session:
            cfg = cfg.model_copy(update={"session": session})
    else:
        if seed is None or frames is None:
            raise typer.BadParameter("give --seed and --frames, or a --preset")
        from pydantic import ValidationError

        try:
            cfg = GenConfig(
                seed=seed,
                session=session,
                frames=frames,
                sensor=sensor,
                split=split,
                world={"nx": nodes, "ny": nodes} if nodes else {},
                gt_radius=30.0 if gt_radius is None else gt_radius,
            )
        except ValidationError as err:
            raise typer.BadParameter(err.errors()[0]["msg"].removeprefix("Value error, ")) from None
    try:
        manifest = generate(
            out_dir,
            cfg,
            workers=workers,
            ground_truth=not no_ground_truth,
            progress=not quiet,
            stall_timeout_s=stall_timeout,
        )
    except FileExistsError as err:
        raise typer.BadParameter(str(err)) from None
    except WorkerError as err:
        console.print(f"[bold red]error:[/] {err} ({out_dir} is incomplete: delete it)")
        raise typer.Exit(1) from None
    c, t = manifest["counts"], manifest["timing_s"]
    table = Table(title=f"Synthetic sequence: {out_dir}", show_header=False)
    rows = [
        (
            "seed / session / sensor / split",
            f"{cfg.seed} / {cfg.session} / {cfg.sensor} / {cfg.split}",
        ),
        ("scans", c["frames"]),
        ("points per scan (mean)", f"{c['points_per_scan']['mean']:.0f}"),
        (
            "drive",
            f"{c['drive']['length_m']:.0f} m at {c['drive']['speed_mps']['mean']:.1f} m/s mean",
        ),
        (
            "town",
            f"{c['world']['street_km']} km of street, {c['world']['static_triangles']} triangles",
        ),
        (
            "simulation",
            f"{t['simulate']:.1f} s ({t['scans_per_s']:.1f} scans/s, {workers} workers)",
        ),
    ]
    if "ground_truth" in c:
        g = c["ground_truth"]
        rows += [
            ("overlap pairs", f"{g['pairs_within_radius']} ({t['ground_truth']:.1f} s)"),
            ("revisiting scans", f"{g['queries_with_loop']} ({g['reverse_fraction']:.0%} reverse)"),
            ("longest revisit gap", f"{g['max_revisit_gap_frames']} frames"),
        ]
    for k, v in rows:
        table.add_row(k, str(v))
    out.print(table)


@app.command(
    "sim-report",
    epilog="Example:\n\n  overlapmamba sim-report --synthetic data/synth/val --out reports/realism",
)
@_friendly_errors
def sim_report(
    synthetic: Annotated[
        Path | None,
        typer.Option(
            exists=True, file_okay=False, help="synthetic sequence (default: generate one)"
        ),
    ] = None,
    real: Annotated[Path, typer.Option(help="real KITTI sequence folder")] = Path(
        "../shared/data/kitti00_0000-0100"
    ),
    reference: Annotated[
        Path, typer.Option(help="folder with the real scans that carry intensity")
    ] = Path("../shared/data/kitti00_overlapnet_reference"),
    scans: Annotated[int, typer.Option(min=1, help="scans to use from each side")] = 50,
    output: Annotated[
        Path, typer.Option("--out", "-o", help="folder for realism.json/.png")
    ] = Path("reports/realism"),
) -> None:
    """Compare synthetic scans with real KITTI scans: beams, ranges, empties, ground, intensity."""
    import json
    import tempfile

    import numpy as np

    from model_export.synth import realism

    real_dir = real / "velodyne"
    if not real_dir.is_dir():
        raise typer.BadParameter(f"{real_dir} does not exist; point --real at a KITTI sequence")
    real_paths = sorted(real_dir.glob("*.bin"))[:scans]
    with tempfile.TemporaryDirectory() as tmp:
        if synthetic is None:
            from model_export.synth.generate import GenConfig, generate

            synthetic = Path(tmp) / "synthetic"
            generate(
                synthetic, GenConfig(seed=4242, frames=scans), ground_truth=False, progress=False
            )
        syn_paths = sorted((synthetic / "velodyne").glob("*.bin"))[:scans]
        if not syn_paths:
            raise typer.BadParameter(f"{synthetic} holds no velodyne/*.bin scans")
        # Compare within the real data's range: its files may be clipped (KITTI here: 80 m).
        cap = min(120.0, np.ceil(realism.max_range_of(real_paths)))
        r_stats = realism.scan_stats(real_paths, max_range=cap)
        s_stats = realism.scan_stats(syn_paths, max_range=cap)
    ref_paths = sorted(reference.glob("*.bin")) if reference.is_dir() else []
    i_stats = realism.scan_stats(ref_paths, max_range=cap) if ref_paths else None
    rows = realism.compare(r_stats, s_stats, i_stats)
    output.mkdir(parents=True, exist_ok=True)
    (output / "realism.json").write_text(
        json.dumps(
            {
                "rows": rows,
                "compared_within_m": cap,
                "real": r_stats,
                "synthetic": s_stats,
                "real_intensity": i_stats,
            },
            indent=2,
        )
        + "\n"
    )
    realism.plot(r_stats, s_stats, i_stats, output / "realism.png")
    table = Table(
        title=f"Synthetic vs real ({len(real_paths)} real, {len(syn_paths)} synthetic scans, "
        f"points within {cap:g} m)"
    )
    for col in ("statistic", "real", "synthetic", "gap"):
        table.add_column(col)

    def fmt(v: Any) -> str:
        return "—" if v is None else f"{v:.3g}" if isinstance(v, float) else str(v)

    for row in rows:
        table.add_row(
            row["statistic"],
            fmt(row["real"]),
            fmt(row["synthetic"]),
            f"{fmt(row['gap'])} ({row['gap_kind']})",
        )
    out.print(table)
    out.print(f"wrote {output / 'realism.json'} and {output / 'realism.png'}")


def _metrics_table(title: str, results: dict[str, dict[str, Any]]) -> Table:
    table = Table(title=title)
    for col in ("revisits", "queries", "with loop", "AUC", "F1max", "Recall@1", "Recall@1%"):
        table.add_column(col, justify="right" if col != "revisits" else "left")
    for name, m in results.items():
        table.add_row(
            name,
            str(m["queries"]),
            str(m["queries_with_loop"]),
            *(f"{m[k]:.3f}" for k in ("auc", "f1max", "recall@1", "recall@1%")),
        )
    return table


def _check_torch() -> None:
    try:
        import torch  # noqa: F401
    except ImportError:
        console.print(
            "[bold red]error:[/] training and evaluation need PyTorch: "
            "pip install -e '.[train]' (make test installs it)"
        )
        raise typer.Exit(2) from None


@app.command(
    "train",
    epilog="Examples:\n\n  overlapmamba train --data data/synth/train --val data/synth/val "
    "--out runs/om\n\n  overlapmamba train --out runs/om --resume --epochs 20\n\n"
    "  overlapmamba train --data A --data B --val V --out runs/x --config cfg.toml\n\n"
    "  overlapmamba train --preset default   (the shipped model; writes runs/default)",
)
@_friendly_errors
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
    resume: Annotated[bool, typer.Option("--resume", help="continue the run in --out")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no progress bars")] = False,
) -> None:
    """Train OverlapMamba on synthetic sequences; validate, checkpoint and plot every epoch."""
    _check_torch()
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
        try:
            model_cfg = OverlapMambaConfig.from_dict(model_d)
        except (TypeError, ValueError) as err:
            raise typer.BadParameter(f"[model] config: {err}") from None
        train_cfg = TrainConfig.from_dict({**train_d, **overrides})
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
            _metrics_table(f"Validation after epoch {history[-1]['epoch']}", history[-1]["val"])
        )
    out.print(f"checkpoints, metrics.json and curves.png in {output}")


@app.command(
    "eval",
    epilog="Examples:\n\n  overlapmamba eval --checkpoint runs/om/best.pt "
    "--sequence data/synth/test --json test.json --plot pr.png\n\n"
    "  overlapmamba eval --checkpoint runs/om/best.pt --sequence data/synth/test-s1 "
    "--database data/synth/test   (second session against the first: AR@1/5/20)",
)
@_friendly_errors
def eval_cmd(
    checkpoint: Annotated[Path, typer.Option(help="a .pt written by train")],
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
            help="first session of the same town: also query --sequence's scans against it "
            "(place recognition across sessions, AR@1/5/20, with Scan Context beside)"
        ),
    ] = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="write the metrics here")] = None,
    plot: Annotated[Path | None, typer.Option(help="write PR curves here (.png)")] = None,
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
    _check_torch()
    import json

    from lidar_core.datasets import open_recording

    def open_sequence(path: Path) -> Any:  # a sequence folder, or a ROS recording with poses
        return open_recording(path, topic=topic, odometry=odometry, tf=tf, need_poses=True)

    from model_export.checkpoint import load_model
    from model_export.evaluate import describe, loop_closure, plot_pr, sequence_loops, summary
    from model_export.rangecache import range_images

    model, profile, _ = load_model(checkpoint)
    seq = open_sequence(sequence)
    if database is not None:  # refuse a wrong pair before the long part
        from model_export.sessions import check_sessions

        check_sessions(open_sequence(database), seq)
    gt = sequence_loops(seq, profile, progress=not quiet)
    desc, _ = describe(model, range_images(seq, profile, progress=not quiet))
    results = loop_closure(desc, gt)
    metrics = summary(results)
    out.print(_metrics_table(f"{checkpoint.name} on {seq.name} ({len(seq)} scans)", metrics))
    record: dict = {"checkpoint": str(checkpoint), "sequence": str(sequence), "metrics": metrics}
    if database is not None:
        from model_export.evaluate import cross_session

        db = open_sequence(database)
        both = cross_session([("model", model, profile)], db, seq, progress=not quiet)
        cross = {"model": both["networks"]["model"], "scan_context": both["scan_context"]}
        record["database"], record["cross_session"] = str(database), cross
        table = Table(
            title=f"Across sessions: {seq.name} against {db.name} ({len(db)} scans); queries "
            f"with a database scan within {cross['model']['radius_m']:g} m count"
        )
        for col in ("method", "queries", "AR@1", "AR@5", "AR@20"):
            table.add_column(col, justify="left" if col == "method" else "right")
        for name, r in (("OverlapMamba", cross["model"]), ("Scan Context", cross["scan_context"])):
            table.add_row(name, str(r["queries"]), *(f"{r[f'ar@{n}']:.3f}" for n in (1, 5, 20)))
        out.print(table)
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(record, indent=2) + "\n")
    if plot is not None:
        plot_pr(results, plot, f"{seq.name}: loop closure")
    if json_out or plot:
        out.print(f"wrote {', '.join(str(p) for p in (json_out, plot) if p)}")


@app.command(
    "export",
    epilog="Examples:\n\n  overlapmamba export runs/om/best.pt --out models/overlapmamba-hdl64.onnx"
    "\n\n  overlapmamba export runs/om/best.pt --out fp32.onnx --weights float32",
)
@_friendly_errors
def export_cmd(
    checkpoint: Annotated[Path, typer.Argument(help="a .pt written by train")],
    out_path: Annotated[Path, typer.Option("--out", help="the .onnx file to write")],
    weights: Annotated[
        str, typer.Option(help="storage of the large head matrix: int8 or float32")
    ] = "int8",
) -> None:
    """ONNX encoder (scan as Scan loops) with its metadata, verified against PyTorch."""
    _check_torch()
    from model_export.checkpoint import load_model
    from model_export.export import export_onnx

    if out_path.suffix != ".onnx":
        raise typer.BadParameter(f"--out must end in .onnx, got {out_path.name!r}")
    model, profile, ckpt = load_model(checkpoint)
    res = export_onnx(model, profile, out_path, checkpoint=ckpt, weight_format=weights)
    meta, v = res.metadata, res.verification
    table = Table(title=f"exported {res.path}", show_header=False)
    for key, value in (
        ("model id", meta.model_id),
        ("weights", f"{meta.weights}, large matrices {meta.weight_format}"),
        ("sensor", f"{profile.name} {profile.height}×{profile.width}"),
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


@app.command(
    "eval-real",
    epilog="Example:\n\n  overlapmamba eval-real --checkpoint runs/om/best.pt --json real.json",
)
@_friendly_errors
def eval_real_cmd(
    checkpoint: Annotated[Path, typer.Option(help="a .pt written by train")],
    sequence: Annotated[Path, typer.Option(help="real KITTI-layout sequence")] = Path(
        "../shared/data/kitti00_0000-0100"
    ),
    seed: Annotated[int, typer.Option(min=0, help="seed of the random yaw angles")] = 0,
    hit_radius: Annotated[float, typer.Option(min=0.1, help="retrieval hit radius (m)")] = 3.0,
    json_out: Annotated[Path | None, typer.Option("--json", help="write the metrics here")] = None,
    profile_name: Annotated[
        str | None,
        typer.Option(
            "--profile",
            help="project with this sensor profile instead of the model's (e.g. hdl32 for the "
            "nuScenes scans; rows are repeated up to the model's height)",
        ),
    ] = None,
) -> None:
    """Real scans: yaw invariance at random angles, odd→even retrieval, yaw-estimate error."""
    _check_torch()
    import json

    from lidar_core.datasets import open_sequence
    from model_export.checkpoint import load_model
    from model_export.evaluate import eval_real

    model, profile, _ = load_model(checkpoint)
    if profile_name is not None:
        profile = _profile(profile_name)
    seq = open_sequence(sequence)
    try:
        r = eval_real(model, profile, seq, seed=seed, hit_radius=hit_radius)
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
    for name, key in (("turned copy", "vs_turned_copy"), ("retrieved frame", "vs_retrieved_frame")):
        e = yaw[key]
        rows.append(
            (
                f"yaw error vs {name} (median / p90 / max, °)",
                f"{e['median']:.2f} / {e['p90']:.2f} / {e['max']:.2f}",
            )
        )
    for k, v in rows:
        table.add_row(k, v)
    out.print(table)
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps({"checkpoint": str(checkpoint), **r}, indent=2) + "\n")
        out.print(f"wrote {json_out}")


@app.command(
    "report",
    epilog="Example (after `make data` and the training presets):\n\n"
    "  overlapmamba report --runs runs --test data/synth/test --test data/synth/test-b "
    "--test data/synth/test-c --second-session data/synth/test-s1 --out reports/model",
)
@_friendly_errors
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
    _check_torch()
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
        out.print(_metrics_table(f"test towns (mean of {len(tests)}): {label}", subs))
    out.print(f"wrote {out_dir}/report.json, tables.md, pr_test.png")


def _service_settings(config: Path | None, **overrides: Any) -> Any:
    from pydantic import ValidationError

    from service.settings import load_settings

    try:
        return load_settings(config, **overrides)
    except (ValidationError, ValueError) as err:
        raise typer.BadParameter(f"invalid service settings: {err}") from None


ConfigOpt = Annotated[
    Path | None,
    typer.Option(
        "--config", help="TOML settings file (also OVERLAPMAMBA_CONFIG); env OVERLAPMAMBA_*"
    ),
]
DataDirOpt = Annotated[
    Path | None, typer.Option("--data-dir", help="where maps live [default: ./data]")
]


@app.command(
    "serve",
    epilog="Examples:\n\n  overlapmamba serve\n\n"
    "  overlapmamba serve --host 0.0.0.0 --port 8080 --config service.toml\n\n"
    "  OVERLAPMAMBA_BATCHING__MAX_BATCH=4 overlapmamba serve --data-dir /var/lib/om",
)
def serve_cmd(
    host: Annotated[str | None, typer.Option(help="bind address [default: 127.0.0.1]")] = None,
    port: Annotated[int | None, typer.Option(min=0, max=65535, help="[default: 8000]")] = None,
    data_dir: DataDirOpt = None,
    model: Annotated[
        Path | None,
        typer.Option(help="exported .onnx encoder [default: models/overlapmamba-hdl64.onnx]"),
    ] = None,
    config: ConfigOpt = None,
    insecure: Annotated[
        bool, typer.Option("--insecure", help="allow a non-loopback host without API keys")
    ] = False,
    index_backend: Annotated[
        str | None,
        typer.Option(
            "--index-backend", help="faiss (embedded, in --data-dir) or qdrant [default: faiss]"
        ),
    ] = None,
    qdrant_url: Annotated[
        str | None, typer.Option("--qdrant-url", help="the Qdrant server, e.g. http://qdrant:6333")
    ] = None,
    qdrant_api_key: Annotated[
        str | None,
        typer.Option(
            "--qdrant-api-key",
            envvar="OVERLAPMAMBA_QDRANT__API_KEY",
            show_envvar=True,
            help="Qdrant's API key (prefer the environment variable: argv is visible)",
        ),
    ] = None,
    qdrant_path: Annotated[
        Path | None,
        typer.Option("--qdrant-path", help="Qdrant's embedded local mode in this folder (trials)"),
    ] = None,
    log_format: Annotated[
        str | None, typer.Option("--log-format", help="json (one object per line) or text")
    ] = None,
) -> None:
    """Run the place-recognition HTTP service (uvicorn). SIGTERM drains requests in flight
    and snapshots the maps before it exits."""
    from service.app import run

    qdrant = {"url": qdrant_url, "api_key": qdrant_api_key, "path": qdrant_path}
    settings = _service_settings(
        config,
        host=host,
        port=port,
        data_dir=data_dir,
        model=model,
        insecure=insecure or None,
        log_format=log_format,
        index={"backend": index_backend} if index_backend else None,
        qdrant={k: v for k, v in qdrant.items() if v is not None} or None,
    )
    try:
        settings.check_binding()
    except ValueError as err:
        console.print(f"[bold red]error:[/] {err}")
        raise typer.Exit(2) from None
    if not settings.model.is_file():
        console.print(f"[bold red]error:[/] model file {settings.model} does not exist")
        raise typer.Exit(2)
    run(settings)


@app.command("dump-config", epilog="Example:\n\n  overlapmamba dump-config --config service.toml")
def dump_config_cmd(config: ConfigOpt = None) -> None:
    """Print the merged service settings (defaults, file, environment) as JSON."""
    settings = _service_settings(config)
    out.print_json(settings.model_dump_json())


@app.command("hash-key", epilog="Example:\n\n  overlapmamba hash-key --role robot --name r1")
def hash_key_cmd(
    name: Annotated[str, typer.Option(help="a name for the key, shown in logs")] = "key",
    role: Annotated[str, typer.Option(help="robot, mapper, viewer or admin")] = "robot",
    key: Annotated[
        str | None, typer.Option(help="hash this key instead of generating a new one")
    ] = None,
) -> None:
    """Make an API key: prints the key once, and the TOML to put in the settings (its hash)."""
    from service.auth import ROLE_ACTIONS, hash_key, new_key

    if role not in ROLE_ACTIONS:
        raise typer.BadParameter(f"role {role!r}; allowed: {', '.join(ROLE_ACTIONS)}")
    secret = key or new_key()
    if key is None:
        console.print(f"key (shown once, give it to the client): [bold]{secret}[/]")
    out.print(
        f'[[auth.keys]]\nname = "{name}"\nrole = "{role}"\nsha256 = "{hash_key(secret)}"',
        markup=False,
    )


@app.command(
    "export-map",
    epilog="Example:\n\n  overlapmamba export-map town backups/town.sqlite --data-dir data",
)
def export_map_cmd(
    map_id: Annotated[str, typer.Argument(help="the map to back up")],
    out_file: Annotated[Path, typer.Argument(help="the backup file to write (new)")],
    data_dir: DataDirOpt = None,
) -> None:
    """Back up a map (its durable store), consistently, even while the service runs."""
    from service.backup import BackupError, export_map
    from service.errors import ServiceError

    try:
        r = export_map(data_dir or Path("data"), map_id, out_file)
    except (BackupError, ServiceError) as err:
        console.print(f"[bold red]error:[/] {err}")
        raise typer.Exit(2) from None
    out.print(f"exported map {r['map_id']}: {r['keyframes']} keyframes, {r['bytes']} bytes")


@app.command(
    "import-map",
    epilog="Example:\n\n  overlapmamba import-map town backups/town.sqlite --data-dir data",
)
def import_map_cmd(
    map_id: Annotated[str, typer.Argument(help="the map to create from the backup")],
    src: Annotated[Path, typer.Argument(help="a file written by export-map")],
    data_dir: DataDirOpt = None,
    replace: Annotated[bool, typer.Option("--replace", help="overwrite an existing map")] = False,
) -> None:
    """Restore a map from a backup. The service must be stopped; its next start indexes it."""
    from service.backup import BackupError, import_map
    from service.errors import ServiceError

    try:
        r = import_map(data_dir or Path("data"), map_id, src, replace=replace)
    except (BackupError, ServiceError) as err:
        console.print(f"[bold red]error:[/] {err}")
        raise typer.Exit(2) from None
    out.print(f"imported map {r['map_id']}: {r['keyframes']} keyframes (model {r['model_id']})")


@app.command(
    "doctor",
    epilog="Examples:\n\n  overlapmamba doctor --data-dir /data\n\n"
    "  overlapmamba doctor --data-dir /data --json > doctor.json",
)
def doctor_cmd(
    data_dir: DataDirOpt = None,
    model: Annotated[
        Path | None,
        typer.Option(help="the model the service serves [default: the configured one]"),
    ] = None,
    config: ConfigOpt = None,
    max_snapshot_age_h: Annotated[
        float, typer.Option(min=0, help="warn when a snapshot with writes since is older")
    ] = 24.0,
    as_json: Annotated[bool, typer.Option("--json", help="print the findings as JSON")] = False,
) -> None:
    """Check a data folder: store vs index counts, snapshots (readable, complete, age), model
    id consistency, leftovers of interrupted operations. Exit code 1 if anything is broken."""
    from rich.table import Table

    from service.doctor import diagnose, diagnose_backend

    settings = _service_settings(config, data_dir=data_dir, model=model)
    model_id = dim = None
    if settings.model.is_file():
        from service.encoder import Encoder

        enc = Encoder(settings.model, intra_op_threads=1)
        model_id, dim = enc.model_id, enc.dim
    if settings.index.backend == "qdrant":
        from service.backends.factory import open_backend

        backend = open_backend(settings, model_id=model_id or "", dim=dim or 0)
        try:
            report = diagnose_backend(backend, model_id=model_id, dim=dim)
        finally:
            backend.close()
    else:
        report = diagnose(
            settings.data_dir,
            model_id=model_id,
            dim=dim,
            max_snapshot_age_s=max_snapshot_age_h * 3600,
            settings=settings.index,
        )
    if model_id is None:
        report.add(None, "model", "warn", f"model {settings.model} not found: ids not checked")
    if as_json:
        out.print_json(report.to_json())
    else:
        table = Table(title=f"overlapmamba doctor: {report.data_dir}")
        for col in ("map", "check", "status", "finding"):
            table.add_column(col)
        colour = {"ok": "green", "warn": "yellow", "error": "bold red"}
        for f in report.findings:
            table.add_row(f.map_id or "-", f.check, f"[{colour[f.status]}]{f.status}[/]", f.message)
        out.print(table)
        out.print("healthy" if report.healthy else "[bold red]problems found[/]")
    if not report.healthy:
        raise typer.Exit(1)


# Commands that train or run the network on whole sequences: they restart once with glibc's
# huge-page malloc tunable (model_export/runtime.py says why and what it measured).
_HEAVY = {"train", "eval", "eval-real", "report"}


def main() -> None:
    import sys

    if len(sys.argv) > 1 and sys.argv[1] in _HEAVY:
        from model_export.runtime import reexec_with_hugepages

        reexec_with_hugepages()
    app()
