"""``overlapmamba`` — data tools, training and export, evaluation, and the service, as four
command groups assembled here: data (``overlapmamba.cli.data``, and the synthetic world's
``overlapmamba.cli.synthetic``), ``overlapmamba.cli.model``, ``overlapmamba.cli.evaluation``
and ``overlapmamba.cli.ops``.

Commands are thin: they parse options, call the library, and turn library errors into a red
message and exit code 2 (bad input) instead of a traceback (``overlapmamba.cli.common``).
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any

import typer

from overlapmamba.cli import data, evaluation, model, ops, synthetic

app = typer.Typer(
    name="overlapmamba",
    help="LiDAR place recognition with OverlapMamba: data tools, training, export and serving.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
for group in (data, synthetic, model, evaluation, ops):
    app.add_typer(group.app)


# Commands that train or run the network on whole sequences: they restart once with glibc's
# huge-page malloc tunable (overlapmamba/train/runtime.py says why and what it measured).
_HEAVY = {"train", "eval", "eval-real", "report"}


def _one_line(showwarning: Callable[..., None]) -> Callable[..., None]:
    """``warnings.showwarning`` that prints an old setting's or flag's name in use as one line
    naming both names (it pointed at pydantic's source and printed that line too)."""
    from overlapmamba.core.renamed import DeprecatedName

    def show(message: Warning | str, category: type[Warning], *args: Any, **kwargs: Any) -> None:
        if issubclass(category, DeprecatedName):
            print(f"warning: {message}", file=sys.stderr)
            return
        showwarning(message, category, *args, **kwargs)

    return show


def main() -> None:
    import warnings

    warnings.showwarning = _one_line(warnings.showwarning)
    if len(sys.argv) > 1 and sys.argv[1] in _HEAVY:
        from overlapmamba.train.runtime import reexec_with_hugepages

        reexec_with_hugepages()
    app()
