"""What the ``overlapmamba`` command groups share: consoles, option types, the error wrapper
that turns library errors into a red message and exit code 2, and small table helpers."""

from __future__ import annotations

from collections.abc import Callable
from functools import wraps
from pathlib import Path
from typing import Annotated, Any, TypeVar

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from overlapmamba.core.errors import LidarCoreError

# no emoji: rich reads ":a:" in a message (mixed:A:BINS) as one, and escape() does not stop it
console = Console(stderr=True, soft_wrap=True, emoji=False)
out = Console(emoji=False)

F = TypeVar("F", bound=Callable[..., Any])


def friendly_errors(func: F) -> F:
    """Library errors, and a file the system refuses (an output under a file, a folder
    given for a file, no permission, a full disk), as one red line and exit 2, not a
    traceback."""

    @wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except LidarCoreError as err:
            console.print(f"[bold red]error:[/] {escape(err.message)}")
            raise typer.Exit(2) from None
        except OSError as err:
            console.print(f"[bold red]error:[/] {escape(os_error(err))}")
            raise typer.Exit(2) from None

    return wrapper  # type: ignore[return-value]


def os_error(err: OSError) -> str:
    """What the system refused, and on which file(s): ``cannot use PATH: Not a directory``."""
    paths = [str(p) for p in (err.filename, err.filename2) if p is not None]
    if isinstance(err, FileExistsError | NotADirectoryError) and paths:
        for p in Path(paths[0]).parents if isinstance(err, NotADirectoryError) else [paths[0]]:
            if Path(p).is_file():  # a file where a folder is needed on the way
                return f"cannot use {paths[0]}: {p} is a file, not a folder"
    if not paths:  # not a file's (a fork, too many open files): said as the system said it
        return f"{type(err).__name__}: {err}"
    return f"cannot use {' → '.join(paths)}: {err.strerror or err}"


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


def command_line(command: str, **options: Any) -> str:
    """``overlapmamba COMMAND --option value …`` for the options given (None and False
    left out, True as a bare flag; underscores become dashes): what a JSON was written by."""
    import shlex

    words = ["overlapmamba", command]
    for name, value in options.items():
        flag = "--" + name.replace("_", "-")
        if value is None or value is False:
            continue
        words += [flag] if value is True else [flag, str(value)]
    return shlex.join(words)


def sensor_profile(sensor: str, **overrides: Any) -> Any:
    from overlapmamba.core.sensors import get_profile

    return get_profile(sensor).replace(**overrides)


def check_out_suffix(path: Path) -> Path:
    if path.suffix.lower() not in {".npy", ".png"}:
        raise typer.BadParameter(f"{path.name}: allowed output suffixes are .npy and .png")
    return path


def metrics_table(title: str, results: dict[str, dict[str, Any]]) -> Table:
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


def errors_table(title: str, errors: dict[str, dict[str, Any]]) -> Table:
    """:func:`overlapmamba.core.anatomy.errors_at_f1max` per subset, one row each (four columns, so
    that it fits an 80-column terminal)."""
    table = Table(title=title)
    for col in (
        "revisits",
        "accepted (true)",
        "false alarms: near / far",
        "missed: wrong / rejected",
    ):
        table.add_column(col, justify="right" if col != "revisits" else "left")
    for name, e in errors.items():
        fa, miss = e["false_alarms"], e["missed_loops"]
        table.add_row(
            name,
            f"{e['accepted']} ({e['true_closures']})",
            f"{fa['total']}: {fa['neighbours']} / {fa['look_alikes']}",
            f"{miss['total']}: {miss['wrong_top1']} / {miss['rejected']}",
        )
    return table


def check_torch() -> None:
    try:
        import torch  # noqa: F401
    except ImportError:
        console.print(
            "[bold red]error:[/] training and evaluation need PyTorch: "
            "pip install -e '.[train]' (make test installs it)"
        )
        raise typer.Exit(2) from None


def command_group(panel: str) -> tuple[typer.Typer, Callable[..., Any]]:
    """A command group's Typer app and its ``command`` decorator, which lists the group's
    commands under ``panel`` in ``overlapmamba --help`` (the groups are merged into one
    app by ``overlapmamba.cli``)."""
    app = typer.Typer()

    def command(*args: Any, **kwargs: Any) -> Any:
        return app.command(*args, rich_help_panel=panel, **kwargs)

    return app, command
