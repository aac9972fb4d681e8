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
LIDAR_CORE_MODULES = [
    "lidar_core",
    "lidar_core.errors",
    "lidar_core.sensors",
    "lidar_core.points",
    "lidar_core.io",
    "lidar_core.projection",
    "lidar_core.poses",
    "lidar_core.datasets",
    "lidar_core.datasets.kitti",
    "lidar_core.datasets.pcd_folder",
    "lidar_core.overlap",
    "lidar_core.metrics",
    "lidar_core.visualize",
    "lidar_core.yaw",
    "lidar_core.scan_kernel",
]


def _modules_after_import(*names: str) -> set[str]:
    code = (
        "import importlib, json, sys\n"
        f"for n in {list(names)!r}: importlib.import_module(n)\n"
        "print(json.dumps(sorted(sys.modules)))"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return set(json.loads(res.stdout))


def _roots(mods: set[str]) -> set[str]:
    return {m.split(".")[0] for m in mods}


def test_shared_core_imports_no_heavy_or_sibling_package():
    roots = _roots(_modules_after_import(*LIDAR_CORE_MODULES))
    forbidden = set(HEAVY) | {"service", "model_export", "client", "overlapmamba"}
    assert not roots & forbidden, f"lidar_core pulled in {sorted(roots & forbidden)}"


@pytest.mark.parametrize(
    ("package", "forbidden"),
    [
        # Each map backend loads only its own engine; the app loads the configured one.
        ("service.app", {"torch", "model_export", "client", "qdrant_client"}),
        (
            "service.backends.faiss.backend",
            {"torch", "model_export", "client", "onnxruntime", "qdrant_client"},
        ),
        (
            "service.backends.qdrant.backend",
            {"torch", "model_export", "client", "onnxruntime", "faiss"},
        ),
        ("service.logs", set(HEAVY) | {"model_export", "client"}),
        ("service.backup", {"torch", "model_export", "client", "onnxruntime", "faiss"}),
        ("client", {"torch", "onnxruntime", "faiss", "service", "model_export"}),
        ("client.cli", {"torch", "onnxruntime", "faiss", "service", "model_export", "matplotlib"}),
        ("client.fleet", {"torch", "onnxruntime", "faiss", "service", "model_export"}),
        ("overlapmamba.cli", set(HEAVY) | {"service", "model_export", "client"}),
        # The simulator needs trimesh/embreex, never torch: data can be made without it.
        (
            "lidar_synth.generate",
            {"torch", "onnxruntime", "faiss", "service", "client", "model_export"},
        ),
    ],
)
def test_package_boundaries(package, forbidden):
    roots = _roots(_modules_after_import(package))
    assert not roots & forbidden, f"{package} pulled in {sorted(roots & forbidden)}"
