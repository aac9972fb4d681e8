"""``overlapmamba`` data commands: range images, loop ground truth, synthetic towns and
their realism against real scans."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.markup import escape
from rich.table import Table

from overlapmamba.cli.common import (
    MaxRangeOpt,
    SensorOpt,
    check_out_suffix,
    command_group,
    console,
    friendly_errors,
    out,
    sensor_profile,
)
from overlapmamba.core.renamed import REMOVED_IN, DeprecatedName

app, command = command_group("Data")


@command(
    "range-image",
    epilog="Examples:\n\n  overlapmamba range-image 000000.bin --max-range 50 --out depth.npy\n\n"
    "  overlapmamba range-image cloud.pcd --sensor hdl32 --out view.png",
)
@friendly_errors
def range_image(
    scan: Annotated[Path, typer.Argument(exists=True, dir_okay=False, help=".bin, .npy or .pcd")],
    output: Annotated[
        Path,
        typer.Option(
            "--out",
            "-o",
            callback=check_out_suffix,
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

    from overlapmamba.core.io import read_points
    from overlapmamba.core.projection import project, valid_mask

    profile = sensor_profile(
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

        from overlapmamba.core.visualize import colorize

        Image.fromarray(colorize(image, profile, scale=row_scale)).save(output)
    valid = valid_mask(image, profile)
    out.print(
        f"{scan.name}: {len(points)} points → {image.shape[0]}×{image.shape[1]} "
        f"({profile.name}, max range {profile.max_range:g} m), "
        f"{valid.mean():.1%} pixels valid → {output}"
    )


@command(
    "ground-truth",
    epilog="Example:\n\n  overlapmamba ground-truth data/synth/00 --radius 30 --min-overlap 0.3",
)
@friendly_errors
def ground_truth(
    seq_dir: Annotated[Path, typer.Argument(exists=True, file_okay=False, help="sequence folder")],
    kind: Annotated[str, typer.Option(help="auto, kitti or pcd-folder")] = "auto",
    sensor: Annotated[
        str | None, typer.Option("--sensor", "-s", help="default: the sequence's own sensor")
    ] = None,
    max_range: MaxRangeOpt = None,
    exclude_recent_frames: Annotated[
        int, typer.Option(min=0, help="loops need i − j > this (frames)")
    ] = 100,
    exclude_recent: Annotated[
        int | None,
        typer.Option(min=0, hidden=True, help="deprecated: --exclude-recent-frames"),
    ] = None,
    radius: Annotated[float, typer.Option(min=0.0, help="pre-filter distance (m), > 0")] = 30.0,
    min_overlap: Annotated[float, typer.Option(min=0.0, max=1.0)] = 0.3,
    threshold: Annotated[float, typer.Option(min=0.0, help="range agreement τ (m), > 0")] = 1.0,
    cache: Annotated[
        Path | None, typer.Option("--out", "-o", help="cache file (.npz); default: automatic")
    ] = None,
    no_cache: Annotated[
        bool,
        typer.Option("--no-cache", help="always recompute (and, with --out, write it there)"),
    ] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no progress bar")] = False,
) -> None:
    """Compute (or load the cached) loop ground-truth table of a sequence."""
    from overlapmamba.core.datasets import open_sequence
    from overlapmamba.core.overlap import LoopParams, loop_ground_truth

    seq = open_sequence(seq_dir, kind=kind)
    profile = sensor_profile(sensor or seq.sensor or "kitti-hdl64", max_range=max_range)
    target: Path | bool = False if no_cache else (cache if cache is not None else True)
    frames = exclude_recent_frames
    if exclude_recent is not None:
        if exclude_recent_frames != 100:
            raise typer.BadParameter(
                "give --exclude-recent-frames only; --exclude-recent is its old name (deprecated)"
            )
        warnings.warn(  # the flags by name: the setting's (loops.exclude_recent) is not typed
            f"--exclude-recent is deprecated and goes in {REMOVED_IN}: it is now "
            "--exclude-recent-frames",
            DeprecatedName,
            stacklevel=2,
        )
        frames = exclude_recent
    from pydantic import ValidationError

    try:
        loops = LoopParams(
            exclude_recent_frames=frames,
            radius=radius,
            min_overlap=min_overlap,
            threshold=threshold,
        )
    except ValidationError as err:  # --radius 0, --threshold 0
        first = err.errors()[0]
        raise typer.BadParameter(f"--{first['loc'][0]}: {first['msg']}") from None
    gt = loop_ground_truth(
        seq,
        profile,
        loops,
        cache=target,
        progress=not quiet,
    )
    if no_cache and cache is not None:  # recomputed: written where asked
        gt.save(cache)
    where = cache if no_cache and cache is not None else gt.source or "not cached"
    table = Table(title=f"Loop ground truth: {seq.name}", show_header=False)
    for k, v in [
        ("frames", len(seq)),
        ("sensor profile", profile.name),
        ("candidate pairs (< radius, gap > exclude_recent_frames)", len(gt.query)),
        ("loop pairs (overlap > min_overlap)", int(gt.is_loop.sum())),
        ("queries with a loop", int(gt.has_loop().sum())),
        ("cache", str(where)),
    ]:
        table.add_row(k, str(v))
    out.print(table)


@command(
    "sensors",
    epilog="Examples:\n\n  overlapmamba sensors\n\n  overlapmamba sensors --json > sensors.json",
)
def sensors(
    as_json: Annotated[bool, typer.Option("--json", help="every field, as JSON")] = False,
) -> None:
    """The sensor catalogue: the LiDARs scans may come from (the service's `sensor`, the
    simulator's --sensor), with the manual each one's figures come from."""
    import json

    from overlapmamba.core.sensors import CATALOGUE

    if as_json:
        out.print_json(json.dumps({k: s.model_dump(mode="json") for k, s in CATALOGUE.items()}))
        return
    table = Table(title="Sensor catalogue (overlapmamba.core.sensors.catalogue)")
    for col in ("name", "sensor", "beams", "elevations", "columns", "range", "σ"):
        table.add_column(col)
    for s in CATALOGUE.values():
        el = s.elevations_deg
        table.add_row(
            s.name,
            s.title,
            str(s.beams),
            f"{el[0]:+.2f}° … {el[-1]:+.2f}°",
            str(s.columns),
            f"{s.min_range:g}–{s.max_range:g} m",
            f"{s.range_sigma * 100:g} cm",
        )
    out.print(table)


@command(
    "gen-data",
    epilog="Examples:\n\n  overlapmamba gen-data data/synth/train --preset train\n\n"
    "  overlapmamba gen-data data/synth/s42 --seed 42 --frames 1200 --sensor hdl32\n\n"
    "  overlapmamba gen-data data/synth/test-s1 --preset test --session 1   "
    "(a second drive through the test town)\n\n"
    "  overlapmamba gen-data data/synth/test-vlp16-robot --preset test --session 2 "
    "--sensor vlp16 --mount robot --no-ground-truth   (the test town driven again by a "
    "delivery robot's VLP-16)\n\n"
    "Sensors: overlapmamba sensors",
)
@friendly_errors
def gen_data(
    out_dir: Annotated[
        Path, typer.Argument(file_okay=False, help="new, empty folder for the sequence")
    ],
    seed: Annotated[int | None, typer.Option(min=0, help="world and drive seed")] = None,
    session: Annotated[
        int | None,
        typer.Option(
            min=0,
            max=1000,
            help="0: the town's first drive; k > 0: another drive through the same town "
            "(own route, parked cars, traffic, people, noise); default 0, or the preset's",
        ),
    ] = None,
    frames: Annotated[
        int | None, typer.Option(min=2, max=100_000, help="scans to simulate")
    ] = None,
    sensor: Annotated[
        str | None,
        typer.Option(
            help="a catalogue sensor (`overlapmamba sensors`; default kitti-hdl64, or the preset's)"
        ),
    ] = None,
    mount: Annotated[
        str | None,
        typer.Option(help="car, robot, amr or backpack (default car, or the preset's)"),
    ] = None,
    mount_height: Annotated[
        float | None,
        typer.Option(min=0.1, max=5.0, help="sensor above the road, m (default: the mount's)"),
    ] = None,
    mount_pitch: Annotated[
        float | None,
        typer.Option(min=-30.0, max=30.0, help="degrees, positive looks down ahead"),
    ] = None,
    mount_roll: Annotated[
        float | None,
        typer.Option(min=-30.0, max=30.0, help="degrees, positive raises the left side"),
    ] = None,
    firing_phase: Annotated[
        str | None,
        typer.Option(
            help="locked: the head fires at the same azimuths every turn (default, or the "
            "preset's); drifting: each scan's firings start a random fraction of a spacing "
            "later, as a real head's drift"
        ),
    ] = None,
    preset: Annotated[
        str | None,
        typer.Option(help="a preset (train, val, test, …): fixed seed, size and sensor"),
    ] = None,
    split: Annotated[
        str | None,
        typer.Option(help="train, val or test (recorded in the manifest; default train)"),
    ] = None,
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
    from pydantic import ValidationError

    from overlapmamba.synth.config import GenConfig
    from overlapmamba.synth.generate import generate
    from overlapmamba.synth.presets import preset as get_preset
    from overlapmamba.synth.workers import WorkerError

    rig: dict[str, Any] = {
        k: v
        for k, v in (
            ("sensor", sensor),
            ("mount", mount),
            ("mount_height", mount_height),
            ("mount_pitch_deg", mount_pitch),
            ("mount_roll_deg", mount_roll),
            ("firing_phase", firing_phase),
        )
        if v is not None
    }
    if preset is not None:
        if seed is not None or frames is not None or nodes is not None or split is not None:
            raise typer.BadParameter(
                "--preset fixes seed, frames, town size and split; drop "
                "--seed/--frames/--nodes/--split or drop --preset"
            )
        try:
            cfg = get_preset(preset)
        except ValueError as err:
            raise typer.BadParameter(str(err)) from None
        changes: dict = dict(rig)
        if gt_radius is not None:
            changes["gt_radius"] = gt_radius
        if session is not None:  # 0 too: the town's first drive of a later drive's preset
            changes["session"] = session
        try:  # validated, unlike model_copy
            cfg = GenConfig.model_validate({**cfg.model_dump(), **changes})
        except ValidationError as err:
            raise typer.BadParameter(err.errors()[0]["msg"].removeprefix("Value error, ")) from None
    else:
        if seed is None or frames is None:
            raise typer.BadParameter("give --seed and --frames, or a --preset")
        try:
            cfg = GenConfig(
                seed=seed,
                session=session or 0,
                frames=frames,
                split=split or "train",
                world={"nx": nodes, "ny": nodes} if nodes else {},
                gt_radius=30.0 if gt_radius is None else gt_radius,
                **rig,
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
    except OSError as err:  # a file where a folder should be, no permission, a full disk
        if (out_dir / ".incomplete").exists():  # it failed while writing: not a usage error
            why = escape(f"{out_dir}: {err.strerror or err} ({out_dir} is incomplete: delete it)")
            console.print(f"[bold red]error:[/] {why}")
            raise typer.Exit(1) from None
        raise typer.BadParameter(f"{out_dir}: {err.strerror or err}") from None
    except WorkerError as err:
        why = escape(f"{err} ({out_dir} is incomplete: delete it)")
        console.print(f"[bold red]error:[/] {why}")
        raise typer.Exit(1) from None
    except KeyboardInterrupt:  # said as a failure is: the folder is a dead partial run
        if (out_dir / ".incomplete").exists():
            where = escape(str(out_dir))
            console.print(f"[yellow]interrupted:[/] {where} is incomplete: delete it")
        raise typer.Exit(130) from None
    c, t = manifest["counts"], manifest["timing_s"]
    m = cfg.mounting()
    table = Table(title=f"Synthetic sequence: {out_dir}", show_header=False)
    rows = [
        (
            "seed / session / sensor / split",
            f"{cfg.seed} / {cfg.session} / {cfg.sensor} / {cfg.split}",
        ),
        (
            "mounting",
            f"{cfg.mount}, {m.height:.2f} m, pitch {m.pitch_deg:g}°, roll {m.roll_deg:g}°",
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


REFERENCE_SCANS = "../shared/data/kitti00_overlapnet_reference"


@command(
    "sim-report",
    epilog="Example:\n\n  overlapmamba sim-report --synthetic data/synth/val --out reports/realism",
)
@friendly_errors
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
        Path | None,
        typer.Option(
            file_okay=False,
            exists=True,
            help="folder with the real scans that carry intensity [default: "
            f"{REFERENCE_SCANS}, where it exists; without it, no intensity row]",
            show_default=False,
        ),
    ] = None,
    scans: Annotated[int, typer.Option(min=2, help="scans to use from each side")] = 50,
    output: Annotated[
        Path, typer.Option("--out", "-o", help="folder for realism.json/.png")
    ] = Path("reports/realism"),
) -> None:
    """Compare synthetic scans with real KITTI scans: beams, ranges, empties, ground, intensity."""
    from overlapmamba.synth import realism

    # one named must be there (a typo read as "no intensity"); the default only where it is
    reference = reference or Path(REFERENCE_SCANS)
    rep = realism.report(real, synthetic, reference, scans, output)
    rows, cap = rep["rows"], rep["compared_within_m"]
    table = Table(
        title=f"Synthetic vs real ({rep['scans']['real']} real, {rep['scans']['synthetic']} "
        "synthetic scans, "
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
