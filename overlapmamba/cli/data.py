"""``overlapmamba`` data commands: range images, loop ground truth and the sensor catalogue
(the synthetic world's commands are in ``overlapmamba.cli.synthetic``)."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from overlapmamba.cli.common import (
    MaxRangeOpt,
    SensorOpt,
    check_out_suffix,
    command_group,
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
