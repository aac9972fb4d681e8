"""``overlapmamba`` model commands: train and export to ONNX (evaluation and the model
report: ``overlapmamba.cli.evaluation``). Each needs PyTorch (the train extra)."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.table import Table

from overlapmamba.cli.common import (
    check_torch,
    command_group,
    friendly_errors,
    metrics_table,
    out,
)
from overlapmamba.core.sensors.input import MODES
from overlapmamba.core.views import COLUMN_PHASES, MAX_VIEWS

MEET = ("descriptors", "tokens")  # export --meet: where a scan's sub-column views meet

app, command = command_group("Model")


@command(
    "train",
    epilog="Examples:\n\n  overlapmamba train --data data/synth/train --val data/synth/val "
    "--out runs/om\n\n  overlapmamba train --out runs/om --resume --epochs 20\n\n"
    "  overlapmamba train --data A --data B --val V --out runs/x --config cfg.toml\n\n"
    "  overlapmamba train --preset narrow-hn   (the shipped model; writes runs/narrow-hn)",
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
            help="named recipe with its data and configs, e.g. narrow-hn (the shipped model); "
            "the list is in overlapmamba/train/presets.py, and an unknown name prints it"
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
        Path | None, typer.Option(help=".json/.toml with \\[model] and \\[train] sections")
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
    from overlapmamba.train.model import OverlapMambaConfig
    from overlapmamba.train.train import TrainConfig, load_config_file, train

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
        from overlapmamba.train.presets import get_preset

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
        if config is not None or set(overrides) - {"device"} or data or val:
            raise typer.BadParameter(
                "--resume continues the run as configured: give only --out, --epochs and "
                "--device (a run may move between a GPU machine and a CPU one)"
            )
    else:
        if not data or val is None:
            raise typer.BadParameter("give --data (at least one) and --val, or --resume")
        model_d, train_d = load_config_file(config) if config else ({}, {})
        train_cfg = TrainConfig.from_dict({**train_d, **overrides})
        try:  # a run from --init takes its network's config, changed where [model] says
            if model_d and train_cfg.init:
                from overlapmamba.train.train_inputs import start_config

                model_d = {**start_config(train_cfg, None).to_dict(), **model_d}
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
        move_to=device if resume else None,
        progress=not quiet,
    )
    if history:
        out.print(
            metrics_table(f"Validation after epoch {history[-1]['epoch']}", history[-1]["val"])
        )
    out.print(f"checkpoints, metrics.json and curves.png in {output}")


@command(
    "export",
    epilog="Examples:\n\n  overlapmamba export runs/om/best.pt --out models/overlapmamba-hdl64.onnx"
    "\n\n  overlapmamba export runs/om/best.pt --out fp32.onnx --weights float32"
    "\n\n  overlapmamba export models/overlapmamba-hdl64.onnx --views 2 --out two-views.onnx"
    "\n\n  overlapmamba export models/overlapmamba-hdl64.onnx --views 1 --column-phase aligned "
    "--out one-pass.onnx"
    "\n\n  overlapmamba export models/overlapmamba-hdl64.onnx --views 3 --meet tokens "
    "--out tokens.onnx"
    "\n\n  overlapmamba export runs/bev-long/encoder.onnx --first-stage mixed:0.75:32:sqrt "
    "--out mixed.onnx",
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
        int | None,
        typer.Option(
            min=1,
            max=MAX_VIEWS,
            help="sub-column views that describe a scan: its descriptor is the mean of this "
            "many projections, each turned by a further 1/views of a column (a continuous "
            "turn then barely moves it; the encoder runs this many times per scan) "
            "[default: an .onnx's own, else 1]",
            show_default=False,
        ),
    ] = None,
    meet: Annotated[
        str | None,
        typer.Option(
            help="where a scan's views meet: 'descriptors' (the encoder runs once a view and "
            "their descriptors are averaged) or 'tokens' (the per-column stem runs once a "
            "view, their tokens are averaged and the blocks and head run once a scan: "
            "the graph is traced anew and its input holds --views images a scan) "
            "[default: an .onnx's own, else descriptors]",
            show_default=False,
        ),
    ] = None,
    sensor_input: Annotated[
        str | None,
        typer.Option(
            "--sensor-input",
            help="how scans become the model's input (overlapmamba.core.sensors.input): "
            "elevation, elevation-lerp (another sensor's scan made into the model's own beams), "
            "elevation-fill (elevation, another sensor's one-column gaps filled), "
            "elevation-reach (elevation-fill, every scan cut at 50 m), "
            "rows, common (every sensor's scan, the model's own too, thinned to "
            "common beams), structure (common, above the ground, within 50 m), bev (a polar "
            "bird's-eye occupancy of every scan), bev-soft (bev, each return shared between "
            "its two nearest columns) or bev-span (bev, each cell how much of its column its "
            "returns' spans cover); default: the "
            "network's own (a .pt's config, an .onnx's metadata)",
        ),
    ] = None,
    column_phase: Annotated[
        str | None,
        typer.Option(
            "--column-phase",
            help="where a scan's columns start (overlapmamba.core.views): 'sensor' (its own "
            "azimuth) or 'aligned' (the scan's mean bearing at a column centre, so a turned "
            "scan's image is the plain one rolled by whole columns: turn invariance in one "
            "pass); default: the source's (a .pt: sensor)",
        ),
    ] = None,
    first_stage: Annotated[
        str | None,
        typer.Option(
            "--first-stage",
            help="write a first stage into the graph as its descriptor "
            "(overlapmamba.core.yaw_spectrum): spectrum:BINS:COMPRESS (the yaw features' "
            "magnitude spectrum over azimuth) or mixed:A:BINS:COMPRESS (joined to the "
            "network's descriptor, A the spectrum's share of a squared distance); "
            "'descriptor' on an .onnx carrying a first stage takes it out again; "
            "default: the network's descriptor",
        ),
    ] = None,
    reduce: Annotated[
        str | None,
        typer.Option(
            "--reduce",
            help="reduce the descriptor (a first stage's vector) to K floats by its principal "
            "directions fitted on --fit-on towns, or to K1+K2: a mixed stage's network "
            "descriptor to K1 and its spectrum to K2 (overlapmamba.train.reduce_head)",
        ),
    ] = None,
    fit_on: Annotated[
        list[Path] | None,
        typer.Option("--fit-on", help="validation town --reduce is fitted on (repeat for more)"),
    ] = None,
) -> None:
    """ONNX encoder (scan as Scan loops) with its metadata, verified against PyTorch."""
    check_torch()
    from overlapmamba.train.checkpoint import load_model
    from overlapmamba.train.export import export_onnx
    from overlapmamba.train.model import OverlapMamba, meeting_views
    from overlapmamba.train.modelfile import (
        load_encoder,
        with_column_phase,
        with_sensor_input,
        with_views,
    )
    from overlapmamba.train.recover import with_token_views
    from overlapmamba.train.spectrum_head import (
        check_source,
        with_first_stage,
        without_first_stage,
    )

    if out_path.suffix != ".onnx":
        raise typer.BadParameter(f"--out must end in .onnx, got {out_path.name!r}")
    if out_path.is_dir():  # found only at the end, after the work, as a traceback
        raise typer.BadParameter(f"--out {out_path} is a folder; give the .onnx file to write")
    work = out_path.with_name(f"{out_path.stem}.part.onnx")  # the steps' file, beside --out
    if checkpoint.resolve() in (out_path.resolve(), work.resolve()):
        what = "is" if checkpoint.resolve() == out_path.resolve() else f"works in {work.name},"
        raise typer.BadParameter(
            f"--out {out_path} {what} the file export reads; write another file (then move "
            "it over this one, if that is what you want)",
            param_hint="--out",
        )
    # rewriting an exported file changes only what is asked: its views and where they meet
    # stay its own (a sensor input asked of the three-view file made it one view, unsaid)
    source = load_encoder(checkpoint)[1] if checkpoint.suffix == ".onnx" else None
    if views is None:
        views = 1 if source is None else source.views
    if meet is None:
        meet = "tokens" if source is not None and source.graph_views > 1 else "descriptors"
    if meet not in MEET:
        raise typer.BadParameter(
            f"--meet must be one of {', '.join(MEET)}, got {meet!r}", param_hint="--meet"
        )
    token_views = views if meet == "tokens" else 1
    stage, strip = None, False
    if first_stage is not None:
        from overlapmamba.core.yaw_spectrum import FirstStage

        try:
            stage = FirstStage.parse(first_stage)
        except ValueError as err:
            raise typer.BadParameter(str(err), param_hint="--first-stage") from None
        if checkpoint.suffix == ".onnx":  # refused before anything is written to --out
            source = load_encoder(checkpoint)[1]
            if stage.mix == 0.0 and source.first_stage != "descriptor":
                stage, strip = None, True  # back to the network's own descriptor
            else:
                check_source(source, checkpoint, stage)
    if sensor_input is not None and sensor_input not in MODES:
        raise typer.BadParameter(
            f"--sensor-input must be one of {', '.join(MODES)}, got {sensor_input!r}",
            param_hint="--sensor-input",
        )
    if column_phase is not None and column_phase not in COLUMN_PHASES:
        raise typer.BadParameter(
            f"--column-phase must be one of {', '.join(COLUMN_PHASES)}, got {column_phase!r}",
            param_hint="--column-phase",
        )
    if (reduce is None) != (not fit_on):
        raise typer.BadParameter(
            "--reduce and --fit-on go together: the floats to keep and the validation towns "
            "their directions are fitted on",
            param_hint="--reduce",
        )
    if reduce is not None:
        from overlapmamba.train.reduce_head import parse_reduction

        try:
            parse_reduction(reduce)
        except ValueError as err:
            raise typer.BadParameter(str(err), param_hint="--reduce") from None
    # every step writes to one work file beside --out (work, above), renamed over it at the
    # end: a step that fails (a town that does not open, a reduction the file cannot take)
    # leaves --out as it was, never a file that looks whole

    def finish(meta: Any) -> Any:
        """The steps every source ends with (a first stage, a reduction), then --out
        replaced by the work file in one rename: whole, or as it was."""
        if stage is not None:
            meta = with_first_stage(work, work, stage)
        if reduce is not None:
            from overlapmamba.train.reduce_head import reduce_file

            shown = f"{checkpoint} (as written for {out_path.name})"
            meta = reduce_file(work, work, reduce, fit_on or [], shown=shown)
        os.replace(work, out_path)
        return meta

    if checkpoint.suffix == ".onnx":
        if weights != "int8":
            raise typer.BadParameter(
                "an exported encoder keeps its weights as they are; --weights applies to a .pt",
                param_hint="--weights",
            )
        try:
            src = checkpoint
            if strip:
                without_first_stage(checkpoint, work)
                src = work
            if token_views > 1 or load_encoder(src)[1].graph_views > 1:
                # the graph itself changes: traced anew from the file's recovered weights
                with_token_views(src, work, token_views)
                src = work
            meta = with_views(src, work, views)
            # back to the sensor's columns first, so that a bird's-eye input may follow
            if column_phase == "sensor":
                meta = with_column_phase(work, column_phase)
            if sensor_input is not None:
                meta = with_sensor_input(work, sensor_input)  # type: ignore[arg-type]
            if column_phase == "aligned":
                meta = with_column_phase(work, column_phase)
            meta = finish(meta)
        finally:
            with contextlib.suppress(OSError):  # never in place of the error that ended it
                work.unlink(missing_ok=True)
        out.print(
            f"wrote {out_path}: the weights of {checkpoint} with {meta.views} view(s) per scan"
            f"{f' met at the {meet}' if meta.views > 1 else ''}, "
            f"columns {meta.column_phase}, "
            f"sensor input {meta.sensor_input}, descriptor {meta.first_stage} "
            f"({meta.descriptor_dim}-d), model id {meta.model_id}"
        )
        return
    model, profile, ckpt = load_model(checkpoint)
    assert isinstance(model, OverlapMamba)  # load_model gives an encoder only for .onnx
    model = meeting_views(model, token_views)
    try:
        res = export_onnx(model, profile, work, checkpoint=ckpt, weight_format=weights, views=views)
        meta, v = res.metadata, res.verification
        if sensor_input is not None and sensor_input != meta.sensor_input:
            meta = with_sensor_input(work, sensor_input)  # type: ignore[arg-type]
        if column_phase is not None and column_phase != meta.column_phase:
            meta = with_column_phase(work, column_phase)
        meta = finish(meta)
    finally:
        with contextlib.suppress(OSError):  # never in place of the error that ended it
            work.unlink(missing_ok=True)
    table = Table(title=f"exported {out_path}", show_header=False)
    for key, value in (
        ("model id", meta.model_id),
        ("weights", f"{meta.weights}, large matrices {meta.weight_format}"),
        ("sensor", f"{profile.name} {profile.height}×{profile.width}"),
        ("views per scan", f"{meta.views}, met at the {meet}" if meta.views > 1 else "1"),
        ("columns", meta.column_phase),
        ("sensor input", meta.sensor_input),
        ("descriptor", f"{meta.first_stage}, {meta.descriptor_dim}-d"),
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
