"""``overlapmamba`` commands for the synthetic world: simulate a town and a drive through it
(``gen-data``), and compare its scans with real ones (``sim-report``). Listed with the data
commands."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer
from rich.markup import escape
from rich.table import Table

from overlapmamba.cli.common import command_group, console, friendly_errors, out

app, command = command_group("Data")


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
