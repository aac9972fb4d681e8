"""``overlapmamba`` — data tools, training and export, evaluation, and the service, as four
command groups (``overlapmamba.cli.data``, ``overlapmamba.cli.model``,
``overlapmamba.cli.evaluation``,
``overlapmamba.cli.ops``) assembled here.

Commands are thin: they parse options, call the library, and turn library errors into a red
message and exit code 2 (bad input) instead of a traceback (``overlapmamba.cli.common``).
"""

from __future__ import annotations

import typer

from overlapmamba.cli import data, evaluation, model, ops

app = typer.Typer(
    name="overlapmamba",
    help="LiDAR place recognition with OverlapMamba: data tools, training, export and serving.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
for group in (data, model, evaluation, ops):
    app.add_typer(group.app)


# Commands that train or run the network on whole sequences: they restart once with glibc's
# huge-page malloc tunable (overlapmamba/train/runtime.py says why and what it measured).
_HEAVY = {"train", "eval", "eval-real", "report"}


def main() -> None:
    import sys

    if len(sys.argv) > 1 and sys.argv[1] in _HEAVY:
        from overlapmamba.train.runtime import reexec_with_hugepages

        reexec_with_hugepages()
    app()
