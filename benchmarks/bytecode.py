"""Process start-up with and without the packages' bytecode: what `make` buys by letting
Python write it.

Where ``PYTHONDONTWRITEBYTECODE`` is set (these development machines set it), Python never
writes ``.pyc`` files, so every process compiles each module it imports from source. The
Makefile clears the variable for every command it runs, so the first process to import a
module writes its bytecode and later ones read it. The test suite starts many processes:
two workers, the background towns, worker pools, servers, CLIs, one per package-boundary
check.

This starts fresh interpreters of this venv doing what those processes do first (import the
service's app, the training loop with its optimiser, the CLI), each ``--repeats`` times and
alternating the two ways so that both meet the same machine:

- ``bytecode``: as under ``make`` (``PYTHONDONTWRITEBYTECODE`` cleared; one untimed run
  first writes whatever ``.pyc`` files were missing);
- ``source``: ``PYTHONPYCACHEPREFIX`` pointed at an empty folder and
  ``PYTHONDONTWRITEBYTECODE=1``, so no ``.pyc`` is found or written: every import compiles.

It reports each process's median wall time both ways and their ratio, and whether the venv
holds bytecode (after the untimed runs it should). Writes
reports/deploy/bytecode.json.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from reports_kit import REPORTS, ROOT, write_report

# What the suite's processes import first, as one line of Python each.
PROCESSES = {
    "service app": "import overlapmamba.service.app",
    "training loop": (
        "import torch, overlapmamba.train.train; "
        "torch.optim.Adam([torch.zeros(1, requires_grad=True)])"
    ),
    "command line": "import overlapmamba.cli",
}


def _timed(code: str, env: dict[str, str]) -> float:
    t = time.perf_counter()
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, check=True)
    return time.perf_counter() - t


def venv_has_bytecode() -> bool:
    """Whether the installed torch has its ``.pyc`` files."""
    import importlib.util

    spec = importlib.util.find_spec("torch")
    if spec is None or spec.origin is None:
        return False
    return any((Path(spec.origin).parent / "__pycache__").glob("*.pyc"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", type=Path, default=REPORTS / "deploy" / "bytecode.json")
    args = ap.parse_args()
    if args.repeats < 1:
        ap.error(f"--repeats must be at least 1; got {args.repeats}")

    base = {k: v for k, v in os.environ.items() if k != "PYTHONPYCACHEPREFIX"}
    base["PYTHONDONTWRITEBYTECODE"] = ""  # as the Makefile runs every command
    rows = {}
    with tempfile.TemporaryDirectory(prefix="no-bytecode-") as empty:
        source = {**base, "PYTHONPYCACHEPREFIX": empty, "PYTHONDONTWRITEBYTECODE": "1"}
        for name, code in PROCESSES.items():
            _timed(code, base)  # missing .pyc written; the files into the page cache
            times: dict[str, list[float]] = {"bytecode": [], "source": []}
            for _ in range(args.repeats):
                times["bytecode"].append(_timed(code, base))
                times["source"].append(_timed(code, source))
            med = {k: statistics.median(v) for k, v in times.items()}
            rows[name] = {
                "code": code,
                "seconds": med,
                "all_seconds": times,
                "source_over_bytecode": med["source"] / med["bytecode"],
            }
            print(f"{name:14s} bytecode {med['bytecode']:.2f} s  source {med['source']:.2f} s")
    write_report(
        args.json,
        {
            "benchmark": "bytecode",
            "venv_has_bytecode": venv_has_bytecode(),
            "pythondontwritebytecode_set": bool(os.environ.get("PYTHONDONTWRITEBYTECODE")),
            "repeats": args.repeats,
            "processes": rows,
        },
    )


if __name__ == "__main__":
    main()
