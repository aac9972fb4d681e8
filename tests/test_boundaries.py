"""Import boundaries, checked in fresh interpreters (house style §2)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

HEAVY = [
    "torch",
    "onnxruntime",
    "faiss",
    "qdrant_client",
    "onnx",
    "trimesh",
    "sklearn",
    "matplotlib",
]
CORE_MODULES = [
    "overlapmamba.core",
    "overlapmamba.core.errors",
    "overlapmamba.core.sensors",
    "overlapmamba.core.points",
    "overlapmamba.core.io",
    "overlapmamba.core.projection",
    "overlapmamba.core.poses",
    "overlapmamba.core.datasets",
    "overlapmamba.core.datasets.kitti",
    "overlapmamba.core.datasets.pcd_folder",
    "overlapmamba.core.overlap",
    "overlapmamba.core.metrics",
    "overlapmamba.core.visualize",
    "overlapmamba.core.yaw",
    "overlapmamba.core.scan_kernel",
]


def _modules_after_import(*names: str) -> set[str]:
    code = (
        "import importlib, json, sys\n"
        f"for n in {list(names)!r}: importlib.import_module(n)\n"
        "print(json.dumps(sorted(sys.modules)))"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return set(json.loads(res.stdout))


UNITS = {"cli", "core", "synth", "train", "service", "client"}
CORE, SYNTH, TRAIN, SERVICE, CLIENT, CLI = (
    "overlapmamba.core",
    "overlapmamba.synth",
    "overlapmamba.train",
    "overlapmamba.service",
    "overlapmamba.client",
    "overlapmamba.cli",
)


def _roots(mods: set[str]) -> set[str]:
    """Each module's unit: a third-party package's top level, or one of overlapmamba's
    packages (``overlapmamba.core``, ``.train``, …; the bare namespace is its own unit)."""
    out = set()
    for m in mods:
        parts = m.split(".")
        if parts[0] == "overlapmamba" and len(parts) > 1 and parts[1] in UNITS:
            out.add(".".join(parts[:2]))
        else:
            out.add(parts[0])
    return out


def test_shared_core_imports_no_heavy_or_sibling_package():
    roots = _roots(_modules_after_import(*CORE_MODULES))
    forbidden = set(HEAVY) | {SERVICE, TRAIN, CLIENT, CLI, SYNTH}
    assert not roots & forbidden, f"overlapmamba.core pulled in {sorted(roots & forbidden)}"


@pytest.mark.parametrize(
    ("package", "forbidden"),
    [
        # Each map backend loads only its own engine; the app loads the configured one.
        (f"{SERVICE}.app", {"torch", TRAIN, CLIENT, SYNTH, "qdrant_client"}),
        (
            f"{SERVICE}.backends.faiss.backend",
            {"torch", TRAIN, CLIENT, "onnxruntime", "qdrant_client"},
        ),
        (f"{SERVICE}.backends.qdrant.backend", {"torch", TRAIN, CLIENT, "onnxruntime", "faiss"}),
        (f"{SERVICE}.logs", set(HEAVY) | {TRAIN, CLIENT}),
        (f"{SERVICE}.backup", {"torch", TRAIN, CLIENT, "onnxruntime", "faiss"}),
        (CLIENT, {"torch", "onnxruntime", "faiss", SERVICE, TRAIN}),
        (f"{CLIENT}.cli", {"torch", "onnxruntime", "faiss", SERVICE, TRAIN, "matplotlib"}),
        (f"{CLIENT}.fleet", {"torch", "onnxruntime", "faiss", SERVICE, TRAIN}),
        (CLI, set(HEAVY) | {SERVICE, TRAIN, CLIENT, SYNTH}),
        # The simulator needs trimesh/embreex, never torch: data can be made without it.
        (f"{SYNTH}.generate", {"torch", "onnxruntime", "faiss", SERVICE, CLIENT, TRAIN}),
        # The namespace itself is empty: importing a part never imports the others.
        ("overlapmamba", set(HEAVY) | {CORE, SYNTH, TRAIN, SERVICE, CLIENT, CLI}),
    ],
)
def test_package_boundaries(package, forbidden):
    roots = _roots(_modules_after_import(package))
    assert not roots & forbidden, f"{package} pulled in {sorted(roots & forbidden)}"
