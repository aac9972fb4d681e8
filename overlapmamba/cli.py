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


def main() -> None:
    app()
