"""The measured tables of the documentation, each rendered from the JSON a command wrote:
what they share (reading a report, naming its source, formatting a table).

One function per ``<!-- render NAME -->`` block lives in a ``figures_*.py`` beside this file:
``figures_model.py`` (the model, the encoder, the service's thresholds), ``figures_verify.py``
(verified closures, registration), ``figures_fleet.py`` (sizing, the fleet, the end-to-end
runs), ``figures_runs.py`` (issue 40's training runs on several sensors, mountings),
``figures_input.py``, ``figures_bev.py`` and ``figures_lerp.py`` (the sensor inputs'
experiments), ``figures_pairs.py`` (issue 40's bar across sensors, pair by pair),
``figures_phase.py`` (where a one-view scan's columns start), ``figures_scan.py`` (which scan
path the service picks at load) and the others, each named for what it renders;
``docs/render.py`` pastes them, ``make docs`` rewrites them and
``tests/test_docs_figures.py`` fails on a stale one.
Each table opens with the JSON it reads and the command that wrote it; nothing here types a
measured number.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]


def load(rel: str) -> dict[str, Any]:
    return json.loads((ROOT / rel).read_text())


def source(rel: str, command: str, when: str | None = None) -> str:
    at = f" ({when})" if when else ""
    return f"<!-- from {rel}{at}, written by `{command}`; rendered by `make docs` -->\n"


def when(r: dict[str, Any]) -> str | None:
    """The date a report records (newer reports: ``date``; older: ``when``), if any."""
    for key in ("date", "when"):
        if isinstance(r.get(key), str):
            return r[key][:10]
    return None


def table(head: list[str], rows: list[list[Any]]) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def ms(x: float) -> str:
    return f"{x:.1f} ms"


def f3(x: float | None) -> str:
    return "—" if x is None else f"{x:.3f}"
