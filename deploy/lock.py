"""Write constraints.txt, the lock: the exact version of every package a virtual environment
holds (by default the one running this), which ``make test``, ``make serve`` and the
Dockerfile install with (``-c constraints.txt``), so a fresh machine and an image get the
versions the suite passed with, not whatever was released since.

    make lock      # .venv upgraded to the newest releases pyproject.toml allows, then this

Run ``make test`` on the result before committing it.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
HEADER = """\
# The lock: every package of the tested environment (.venv: the project and its serve,
# train, client and dev extras) at the version the suite passed with. make test, make serve
# and the Dockerfile install with it (-c constraints.txt). Written by `make lock`
# (deploy/lock.py), which first upgrades .venv to the newest releases pyproject.toml allows;
# run `make test` before committing a new one.
"""
# the installers (the venv module's pip, the Makefile's uv) and the build tools a freeze
# leaves out, which pip list gives. setuptools is pinned: the image builds the source with
# it (no build isolation), so a new release cannot break or change a build unasked.
SKIP = ("pip", "uv", "wheel", "distribute")


def pins(frozen: str) -> list[str]:
    """``name==version`` lines of a freeze, sorted, the installers and editables left out."""
    out = []
    for line in frozen.splitlines():
        name, sep, version = line.partition("==")
        if not sep or not version or name.strip().lower() in SKIP:
            continue  # an editable (-e …), a URL, a comment
        out.append(f"{name.strip()}=={version.strip()}")
    return sorted(out, key=str.lower)


def freeze(python: str = sys.executable) -> str:
    """``python``'s environment as ``name==version`` lines, editables left out. ``pip list``,
    not ``pip freeze``: a package installed from a file or a URL is ``name @ URL`` in a
    freeze, which :func:`pins` leaves out, so the next lock dropped its pin."""
    return subprocess.run(
        [python, "-m", "pip", "list", "--format=freeze", "--exclude-editable"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout


def main(python: str = sys.executable) -> None:
    lines = pins(freeze(python))
    if not lines:
        raise SystemExit(f"{python} holds no packages: nothing to lock")
    target = ROOT / "constraints.txt"
    tmp = target.with_suffix(".tmp")
    tmp.write_text(HEADER + "\n".join(lines) + "\n")
    tmp.replace(target)
    print(f"constraints.txt: {len(lines)} packages from {python}")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else sys.executable)
