"""``overlapmamba`` service commands: serve, settings, API keys, map backups and the data
folder's doctor. None imports PyTorch."""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated, Any, NoReturn

import typer
from rich.markup import escape
from rich.table import Table

from overlapmamba.cli.common import (
    command_group,
    console,
    out,
)

app, command = command_group("Service")


def _service_settings(config: Path | None, **overrides: Any) -> Any:
    from pydantic import ValidationError

    from overlapmamba.service.settings import load_settings

    try:
        return load_settings(config, **overrides)
    except ValidationError as err:  # where and why, never the input: it may hold a key
        where = "; ".join(
            f"{'.'.join(str(p) for p in e['loc']) or 'settings'}: {e['msg']}"
            for e in err.errors(include_url=False, include_input=False)
        )
        _refuse(f"invalid service settings: {where}")
    except ValueError as err:
        _refuse(f"invalid service settings: {err}")


def _dotted(overrides: dict[str, Any]) -> list[str]:
    """The settings ``overrides`` gives (a value that is not None), by dotted name."""
    names = []
    for key, value in overrides.items():
        if isinstance(value, dict):
            names += [f"{key}.{sub}" for sub, v in value.items() if v is not None]
        elif value is not None:
            names.append(key)
    return names


def _refuse(message: str) -> NoReturn:
    """A fault the command meets before it starts: one line naming it, exit 2 (not the
    usage text and a box, which a service's log keeps as five lines)."""
    console.print(f"[bold red]error:[/] {escape(message)}")
    raise typer.Exit(2)


def _stopped_while_starting(signum: int, frame: Any) -> None:
    console.print("stopped before the service started (SIGTERM)")
    raise SystemExit(128 + signum)


@contextlib.contextmanager
def _stoppable_start() -> Iterator[None]:
    """SIGTERM ends what runs inside (serve's checks and the model's load); the handler
    before it is back after, however the block ends."""
    import signal

    before = signal.signal(signal.SIGTERM, _stopped_while_starting)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, before)


ConfigOpt = Annotated[
    Path | None,
    typer.Option(
        "--config", help="TOML settings file (also OVERLAPMAMBA_CONFIG); env OVERLAPMAMBA_*"
    ),
]
DataDirOpt = Annotated[
    Path | None, typer.Option("--data-dir", help="where maps live \\[default: ./data]")
]


@command(
    "serve",
    epilog="Examples:\n\n  overlapmamba serve\n\n"
    "  overlapmamba serve --host 0.0.0.0 --port 8080 --config service.toml\n\n"
    "  OVERLAPMAMBA_BATCHING__MAX_BATCH=4 overlapmamba serve --data-dir /var/lib/om",
)
def serve_cmd(
    host: Annotated[str | None, typer.Option(help="bind address \\[default: 127.0.0.1]")] = None,
    port: Annotated[int | None, typer.Option(min=0, max=65535, help="\\[default: 8000]")] = None,
    data_dir: DataDirOpt = None,
    model: Annotated[
        Path | None,
        typer.Option(help="exported .onnx encoder \\[default: models/overlapmamba-hdl64.onnx]"),
    ] = None,
    config: ConfigOpt = None,
    insecure: Annotated[
        bool, typer.Option("--insecure", help="allow a non-loopback host without API keys")
    ] = False,
    index_backend: Annotated[
        str | None,
        typer.Option(
            "--index-backend", help="faiss (embedded, in --data-dir) or qdrant \\[default: faiss]"
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
    # Until uvicorn takes the signals over, a SIGTERM ends the start: as a container's PID 1
    # the process has no default action for it, so a stop sent during the seconds the
    # checks and the model's load take was lost, and `docker stop` waited for its SIGKILL.
    with _stoppable_start():
        from overlapmamba.service.app import run
        from overlapmamba.service.settings import shadowed, unknown_variables

        for var, near in unknown_variables(os.environ):  # a misspelt one would change nothing
            hint = f"; did you mean {near}?" if near else ""
            why = f"{escape(var)} is not a setting and is ignored{hint}"
            console.print(f"[yellow]warning:[/] {why}")
        qdrant = {"url": qdrant_url, "api_key": qdrant_api_key, "path": qdrant_path}
        overrides: dict[str, Any] = {
            "host": host,
            "port": port,
            "data_dir": data_dir,
            "model": model,
            "insecure": insecure or None,
            "log_format": log_format,
            "index": {"backend": index_backend} if index_backend else None,
            "qdrant": {k: v for k, v in qdrant.items() if v is not None} or None,
        }
        given = [  # --qdrant-api-key is its variable's (typer reads it), not a flag's
            key for key in _dotted(overrides) if key != "qdrant.api_key"
        ]
        for var, key in shadowed(config, os.environ, given):  # the image's ENV over a file's
            console.print(  # never the value: it may be a key
                f"[yellow]warning:[/] {escape(var)} overrides {key} in "
                "the config file (the environment wins over the file; unset the variable, or set "
                "the value there)"
            )
        settings = _service_settings(config, **overrides)
        try:
            settings.check_binding()
        except ValueError as err:
            console.print(f"[bold red]error:[/] {escape(str(err))}")
            raise typer.Exit(2) from None
        if not settings.model.is_file():
            missing = escape(str(settings.model))
            console.print(f"[bold red]error:[/] model file {missing} does not exist")
            raise typer.Exit(2)
        _preflight(settings, _check_model_file(settings.model))
    run(settings)  # uvicorn's handlers from here; then the ones before, as it found them


def _preflight(settings: Any, meta: Any) -> None:
    """What the service's start-up would otherwise meet only inside uvicorn (a traceback,
    exit 3), refused here in one line with exit 2: the model's calibration against the
    settings, the second stage it serves, the sensor files, and the data folder (made, and
    not in use by another service)."""
    from overlapmamba.core.errors import LidarCoreError
    from overlapmamba.service.backup import BackupError, data_dir_lock
    from overlapmamba.service.calibration import resolve
    from overlapmamba.service.ranking import rerank_params
    from overlapmamba.service.sensors import Sensors

    try:
        serving, _ = resolve(settings, meta)
        rerank_params(serving.rerank, meta)
        Sensors(meta, serving.sensors.files)
        if serving.index.backend == "faiss":
            with data_dir_lock(serving.data_dir):
                pass
    except (BackupError, LidarCoreError, ValueError) as err:
        console.print(f"[bold red]error:[/] {escape(str(err))}")
        raise typer.Exit(2) from None


def _check_model_file(path: Path) -> Any:
    """Refuse, in one line and before uvicorn starts, a model file the service cannot
    serve (not ONNX, truncated, an ONNX graph without an encoder's metadata, or one whose
    graph does not do what its metadata says), where the start-up would otherwise end in a
    traceback, or say ready and fail every scan; else its metadata."""
    from overlapmamba.service.calibration import read_model_metadata
    from overlapmamba.service.encoder import Encoder, ModelLoadError

    try:
        meta = read_model_metadata(path)
    except Exception as err:
        console.print(
            f"[bold red]error:[/] {path} is not an encoder the service can serve "
            f"({type(err).__name__}: {escape(str(err))}); expected an .onnx file written by "
            "`overlapmamba export`, e.g. models/overlapmamba-hdl64.onnx"
        )
        raise typer.Exit(2) from None
    try:  # its graph against its metadata, once (the service's own load does it again)
        Encoder(path, intra_op_threads=1, scan_kernel=False)
    except ModelLoadError as err:
        console.print(f"[bold red]error:[/] {escape(str(err))}")
        raise typer.Exit(2) from None
    return meta


@command("dump-config", epilog="Example:\n\n  overlapmamba dump-config --config service.toml")
def dump_config_cmd(config: ConfigOpt = None) -> None:
    """Print the merged service settings (defaults, file, environment) as JSON, with the
    thresholds the service answers with for its model: the model file's calibration unless
    a setting overrides (where each came from goes to stderr)."""
    from overlapmamba.service.calibration import read_model_metadata, resolve

    settings = _service_settings(config)
    try:
        meta = read_model_metadata(settings.model)
    except Exception as err:
        console.print(
            f"[yellow]note:[/] {escape(str(settings.model))}: {escape(str(err))}; "
            "its calibration is not shown"
        )
    else:
        try:
            settings, used = resolve(settings, meta)
        except ValueError as err:
            console.print(f"[bold red]error:[/] {escape(str(err))}")
            raise typer.Exit(2) from None
        for key, t in used.items():
            console.print(f"{key} = {t.value} ({t.source})", markup=False)
    out.print_json(settings.model_dump_json())


@command("hash-key", epilog="Example:\n\n  overlapmamba hash-key --role robot --name r1")
def hash_key_cmd(
    name: Annotated[str, typer.Option(help="a name for the key, shown in logs")] = "key",
    role: Annotated[str, typer.Option(help="robot, mapper, viewer or admin")] = "robot",
    key: Annotated[
        str | None, typer.Option(help="hash this key instead of generating a new one")
    ] = None,
    as_json: Annotated[
        bool,
        typer.Option(
            "--json",
            help="print the entry as JSON, for OVERLAPMAMBA_AUTH__KEYS (a JSON list of them)",
        ),
    ] = False,
    maps: Annotated[
        str | None,
        typer.Option(help="robot keys: the maps it may insert into, comma-separated"),
    ] = None,
    query_maps: Annotated[
        str | None,
        typer.Option(
            help="robot keys: the maps it may query, observe and stream against besides "
            "--maps, comma-separated (unset: any map)"
        ),
    ] = None,
) -> None:
    """Make an API key: prints the key once (on stderr), and its entry for the settings (its
    hash): TOML for a config file, or with --json one item of OVERLAPMAMBA_AUTH__KEYS."""
    from pydantic import ValidationError

    from overlapmamba.service.auth import ROLE_ACTIONS, hash_key, new_key
    from overlapmamba.service.settings import ApiKey

    if role not in ROLE_ACTIONS:
        raise typer.BadParameter(f"role {role!r}; allowed: {', '.join(ROLE_ACTIONS)}")
    if key is not None and not key.strip():
        raise typer.BadParameter(
            "--key is empty; give the key to hash, or leave --key out for a new one",
            param_hint="--key",
        )
    secret = key or new_key()
    entry: dict[str, object] = {"name": name, "role": role, "sha256": hash_key(secret)}
    for field, value in (("maps", maps), ("query_maps", query_maps)):
        if value is not None:
            entry[field] = [m.strip() for m in value.split(",") if m.strip()]
    try:
        ApiKey.model_validate(entry)  # what serve would refuse (maps on a mapper key)
    except ValidationError as err:
        raise typer.BadParameter("; ".join(e["msg"] for e in err.errors())) from None
    if key is None:
        console.print(f"key (shown once, give it to the client): [bold]{secret}[/]")
    if as_json:
        out.print(json.dumps(entry, separators=(",", ":")), markup=False, soft_wrap=True)
        return
    # a JSON string is a TOML basic string, a JSON list of them a TOML array: a name with
    # quotes or backslashes stays TOML
    lines = ["[[auth.keys]]", *(f"{k} = {json.dumps(v)}" for k, v in entry.items())]
    out.print("\n".join(lines), markup=False)


@command(
    "export-map",
    epilog="Example:\n\n  overlapmamba export-map town backups/town.sqlite --data-dir data",
)
def export_map_cmd(
    map_id: Annotated[str, typer.Argument(help="the map to back up")],
    out_file: Annotated[Path, typer.Argument(help="the backup file to write (new)")],
    data_dir: DataDirOpt = None,
    config: ConfigOpt = None,
) -> None:
    """Back up a map (its durable store), consistently, even while the service runs. The
    data folder is the service's (--data-dir, else its settings: OVERLAPMAMBA_DATA_DIR, the
    config file)."""
    from overlapmamba.service.backup import BackupError, export_map
    from overlapmamba.service.errors import ServiceError

    folder = _service_settings(config, data_dir=data_dir).data_dir
    try:
        r = export_map(folder, map_id, out_file)
    except (BackupError, ServiceError) as err:
        console.print(f"[bold red]error:[/] {escape(str(err))}")
        raise typer.Exit(2) from None
    out.print(f"exported map {r['map_id']}: {r['keyframes']} keyframes, {r['bytes']} bytes")


@command(
    "import-map",
    epilog="Example:\n\n  overlapmamba import-map town backups/town.sqlite --data-dir data",
)
def import_map_cmd(
    map_id: Annotated[str, typer.Argument(help="the map to create from the backup")],
    src: Annotated[Path, typer.Argument(help="a file written by export-map")],
    data_dir: DataDirOpt = None,
    replace: Annotated[bool, typer.Option("--replace", help="overwrite an existing map")] = False,
    config: ConfigOpt = None,
) -> None:
    """Restore a map from a backup. The service must be stopped; its next start indexes it.
    The data folder is the service's, as for export-map."""
    from overlapmamba.service.backup import BackupError, import_map
    from overlapmamba.service.errors import ServiceError

    folder = _service_settings(config, data_dir=data_dir).data_dir
    try:
        r = import_map(folder, map_id, src, replace=replace)
    except (BackupError, ServiceError) as err:
        console.print(f"[bold red]error:[/] {escape(str(err))}")
        raise typer.Exit(2) from None
    out.print(f"imported map {r['map_id']}: {r['keyframes']} keyframes (model {r['model_id']})")


@command(
    "doctor",
    epilog="Examples:\n\n  overlapmamba doctor --data-dir /data\n\n"
    "  overlapmamba doctor --data-dir /data --json > doctor.json",
)
def doctor_cmd(
    data_dir: DataDirOpt = None,
    model: Annotated[
        Path | None,
        typer.Option(help="the model the service serves \\[default: the configured one]"),
    ] = None,
    config: ConfigOpt = None,
    max_snapshot_age_h: Annotated[
        float, typer.Option(min=0, help="warn when a snapshot with writes since is older")
    ] = 24.0,
    as_json: Annotated[bool, typer.Option("--json", help="print the findings as JSON")] = False,
) -> None:
    """Check a data folder: store vs index counts, snapshots (readable, complete, age), model
    id consistency, leftovers of interrupted operations. Exit code 1 if anything is broken."""

    from overlapmamba.service.doctor import diagnose, diagnose_backend

    settings = _service_settings(config, data_dir=data_dir, model=model)
    model_id = dim = None
    model_error = None
    if settings.model.is_file():
        from overlapmamba.service.encoder import Encoder

        try:  # the kernel's timing at load is the service's business, not the doctor's
            enc = Encoder(settings.model, intra_op_threads=1, scan_kernel=False)
            model_id, dim = enc.model_id, enc.dim
        except Exception as err:  # a file that is not an encoder: a finding, not a crash
            model_error = f"model {settings.model} cannot be loaded: {err}"
    if settings.index.backend == "qdrant":
        from overlapmamba.service.backends.factory import open_backend

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
    if model_error is not None:
        report.add(None, "model", "error", f"{model_error}: ids not checked")
    elif model_id is None:  # asked for by name and absent is an error; the default, a warning
        found = f"model {settings.model} not found: ids not checked"
        report.add(None, "model", "warn" if model is None else "error", found)
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
