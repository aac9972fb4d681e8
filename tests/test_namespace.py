"""One namespace: the installed project is the package ``overlapmamba`` and nothing else, so
it installs beside any other project (kiss-icp, httpx and qdrant-client each install one
name too); its console scripts stay ``overlapmamba`` and ``overlapmamba-client``."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.timeout(300)
def test_the_wheel_installs_one_top_level_package(tmp_path):
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "-q",
            "-w",
            str(tmp_path),
            str(ROOT),
        ],
        capture_output=True,
        text=True,
        timeout=280,
    )
    if done.returncode != 0 and "No module named pip" in done.stderr:
        pytest.skip("this venv has no pip to build a wheel with")
    assert done.returncode == 0, done.stderr[-2000:]
    (wheel,) = tmp_path.glob("overlapmamba-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert tops == {"overlapmamba"}, sorted(tops)
    for part in ("core", "synth", "train", "service", "client", "cli"):
        assert f"overlapmamba/{part}/__init__.py" in names, part
    # what is not Python comes along: the scan kernel's C source, the dashboard, py.typed
    assert "overlapmamba/core/csrc/selective_scan.c" in names
    assert "overlapmamba/service/static/dashboard.html" in names
    assert "overlapmamba/py.typed" in names
    info = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
    scripts = zipfile.ZipFile(wheel).read(info).decode()
    assert "overlapmamba = overlapmamba.cli:main" in scripts
    assert "overlapmamba-client = overlapmamba.client.cli:main" in scripts
