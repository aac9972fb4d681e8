"""Print the requirements of the project's core plus the named extras, one per line, from
pyproject.toml: what the image's hashed lock (``deploy/lock.py``) and its wheelhouse
(``deploy/image.py wheels``) are made from.

    python deploy/requirements.py serve > requirements.txt
"""

from __future__ import annotations

import sys
import tomllib
from pathlib import Path


def requirements(pyproject: Path, extras: list[str]) -> list[str]:
    project = tomllib.loads(pyproject.read_text())["project"]
    optional = project.get("optional-dependencies", {})
    unknown = [e for e in extras if e not in optional]
    if unknown:
        raise SystemExit(f"unknown extras {unknown}; allowed: {sorted(optional)}")
    return list(project["dependencies"]) + [r for e in extras for r in optional[e]]


if __name__ == "__main__":
    here = Path(sys.argv[0]).resolve().parent.parent / "pyproject.toml"
    path = Path("pyproject.toml") if Path("pyproject.toml").is_file() else here
    print("\n".join(requirements(path, sys.argv[1:])))
