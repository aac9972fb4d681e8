"""The service's data path only goes down: routes → use cases → scan pipeline → parts.

Read from the source (no imports run): a module may import service modules of its own layer
or below, never one above it. The order is the one README "One /observe" walks through."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# top to bottom; modules not listed (settings, errors, stats, schemas, …) are shared leaves
LAYERS = [
    ["service.app"],
    [
        "service.api.queries",
        "service.api.descriptors",
        "service.api.keyframes",
        "service.api.maps",
        "service.api.system",
    ],
    ["service.deps"],
    ["service.core"],
    ["service.pipeline"],
    ["service.batcher", "service.bodies", "service.encoder"],
    ["service.fastscan"],
]


def service_imports(module: str) -> set[str]:
    tree = ast.parse((ROOT / (module.replace(".", "/") + ".py")).read_text())
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
    return {m for m in found if m.startswith("service.")}


def test_the_scan_path_only_imports_downward():
    level = {m: i for i, layer in enumerate(LAYERS) for m in layer}
    upward = [
        f"{m} imports {dep}"
        for m, i in level.items()
        for dep in sorted(service_imports(m))
        if level.get(dep, len(LAYERS)) < i
    ]
    assert not upward, upward
    # and the path is really wired through these layers
    assert "service.core" in service_imports("service.api.queries")
    assert "service.pipeline" in service_imports("service.core")
    assert {"service.batcher", "service.bodies"} <= service_imports("service.pipeline")
    # routes reach scans only through the use cases, never the pipeline or encoder itself
    for route in LAYERS[1]:
        assert not {"service.pipeline", "service.batcher", "service.encoder"} & service_imports(
            route
        ), route
