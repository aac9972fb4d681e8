"""Where a benchmark's figures go: reports/, each JSON with its provenance inside.

Every benchmark writes its JSON under reports/ by default (never to an ignored folder), so a
figure in the README, the model card or docs/ is a file in the repository that names the
command, the commit, the machine and the date that made it (docs/render.py renders them).
Imports the standard library only, so any benchmark may use it.
"""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
REPORTS = ROOT / "reports"
CORES = os.cpu_count() or 1


def shown_path(path: Path) -> str:
    """``path`` as a report records it: relative to the checkout when inside it (as a clone
    has it), else as given (a model or a drive elsewhere on the machine)."""
    full = path.resolve()
    return str(full.relative_to(ROOT)) if full.is_relative_to(ROOT) else str(path)


def _git(*args: str) -> str:
    import subprocess

    try:
        done = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, timeout=10)
    except OSError:
        return ""
    return done.stdout.strip()


def _commit() -> str:
    commit = _git("rev-parse", "HEAD") or "unknown"
    if _git("status", "--porcelain", "--untracked-files=no"):
        commit += "-dirty"
    return commit


# the code a benchmark runs is the code it started with: its commit is read when the
# benchmark imports this module, not when it writes (a long run may outlive a commit)
STARTED_AT = _commit()


def provenance() -> dict[str, object]:
    """Where a figure came from: the command, the commit the run started from (``-dirty``
    with local changes), the machine (CPU model, cores) and the time it was written."""
    import platform
    import shlex
    import sys
    from datetime import UTC, datetime

    commit = STARTED_AT
    cpu = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    script = Path(sys.argv[0]).resolve()
    shown = str(script.relative_to(ROOT)) if script.is_relative_to(ROOT) else sys.argv[0]
    return {
        "command": "python " + shlex.join([shown, *sys.argv[1:]]),
        "commit": commit,
        "machine": {"cpu": cpu, "cores": CORES},
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
    }


def write_report(path: Path, record: dict[str, Any], **dumps: Any) -> None:
    """Write a benchmark's JSON: ``record`` with its provenance (command, commit, machine,
    date) first. Every benchmark writes under reports/ by default, so a figure in the docs is
    a file in the repository, never one in an ignored folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({**provenance(), **record}, indent=2, **dumps) + "\n")
