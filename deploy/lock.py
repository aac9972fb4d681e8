"""Write constraints.txt, the lock: the exact version of every package a virtual environment
holds (by default the one running this), which ``make test`` and ``make serve`` install with
(``-c constraints.txt``), so a fresh machine gets the versions the suite passed with, not
whatever was released since.

Then deploy/requirements-serve.txt, what the image installs: the ``serve`` extra's whole
closure and the build backend at the lock's versions, each with the SHA-256 of every file
PyPI holds for it (``uv pip compile --generate-hashes --universal``, for the image's Python
3.11 on any platform). The Dockerfile installs it with ``pip --require-hashes``, from the
wheelhouse or from PyPI: a file that is not the one locked (a mirror's, a proxy's, a
re-upload) fails the build instead of entering the image. Writing it asks PyPI (or the
index uv is configured with) for the hashes.

    make lock      # .venv upgraded to the newest releases pyproject.toml allows, then this

Run ``make test`` on the result before committing it.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
HEADER = """\
# The lock: every package of the tested environment (.venv: the project and its serve,
# train, client and dev extras) at the version the suite passed with. make test and make
# serve install with it (-c constraints.txt); the image installs deploy/requirements-serve.txt,
# its serve set with hashes. Written by `make lock` (deploy/lock.py), which first upgrades
# .venv to the newest releases pyproject.toml allows; run `make test` before committing it.
"""
# the installers (the venv module's pip, the Makefile's uv) and the build tools a freeze
# leaves out, which pip list gives. setuptools is pinned: the image builds the source with
# it (no build isolation), so a new release cannot break or change a build unasked.
SKIP = ("pip", "uv", "wheel", "distribute")
SERVE_LOCK = ROOT / "deploy" / "requirements-serve.txt"
SERVE_HEADER = """\
# What the image installs (Dockerfile: pip install --require-hashes): the serve extra's
# whole closure and the build backend, at the versions of constraints.txt, each with the
# SHA-256 of every file PyPI holds for that version (Python 3.11, any platform). Written by
# `make lock` (deploy/lock.py) from pyproject.toml and constraints.txt; do not edit.
"""


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


def serve_lock(uv: str, constraints: Path = ROOT / "constraints.txt") -> str:
    """deploy/requirements-serve.txt's text: the ``serve`` requirements of pyproject.toml and
    setuptools (the image builds the source with it), resolved at the versions of
    ``constraints`` with their hashes by ``uv``."""
    sys.path.insert(0, str(ROOT / "deploy"))
    from requirements import requirements  # deploy/requirements.py

    wanted = [*requirements(ROOT / "pyproject.toml", ["serve"]), "setuptools"]
    with tempfile.TemporaryDirectory(prefix="om-lock-") as tmp:
        src = Path(tmp) / "serve.in"
        src.write_text("\n".join(wanted) + "\n")
        cmd = [uv, "pip", "compile", str(src), "-c", str(constraints)]
        cmd += ["--generate-hashes", "--universal", "--python-version", "3.11"]
        cmd += ["--no-header", "--no-annotate", "--quiet"]
        out = subprocess.run(cmd, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"uv pip compile failed (it asks the package index):\n{out.stderr}")
    return SERVE_HEADER + out.stdout


def find_uv(python: str) -> str:
    """The uv beside ``python`` (the Makefile's, in .venv), else the one on PATH."""
    beside = Path(python).parent / "uv"
    found = str(beside) if beside.is_file() else shutil.which("uv")
    if found is None:
        raise SystemExit(f"no uv beside {python} or on PATH: pip install uv")
    return found


def main(python: str = sys.executable) -> None:
    lines = pins(freeze(python))
    if not lines:
        raise SystemExit(f"{python} holds no packages: nothing to lock")
    target = ROOT / "constraints.txt"
    tmp = target.with_suffix(".tmp")
    tmp.write_text(HEADER + "\n".join(lines) + "\n")
    try:  # the hashed lock from the new one; neither replaced unless both are made
        text = serve_lock(find_uv(python), tmp)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    serve_tmp = SERVE_LOCK.with_suffix(".tmp")
    serve_tmp.write_text(text)
    tmp.replace(target)
    serve_tmp.replace(SERVE_LOCK)
    print(f"constraints.txt: {len(lines)} packages from {python}")
    n = sum(1 for line in text.splitlines() if "==" in line)
    print(f"{SERVE_LOCK.relative_to(ROOT)}: {n} packages with their hashes")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else sys.executable)
