"""The service's data path only goes down: routes → use cases → scan pipeline → parts.

Read from the source (no imports run): a module may import service modules of its own layer
or below, never one above it. The order is the one docs/architecture.md walks through.
Beside the scan path: no module of any package imports another that (through any chain)
imports it back, and HTTP (FastAPI, Starlette, the HTTP schemas) stays at the edge — the app, the
routes and what they alone use."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# top to bottom; modules not listed (settings, errors, stats, schemas, …) are shared leaves
LAYERS = [
    ["overlapmamba.service.app"],
    [
        "overlapmamba.service.api.queries",
        "overlapmamba.service.api.stream",
        "overlapmamba.service.api.descriptors",
        "overlapmamba.service.api.keyframes",
        "overlapmamba.service.api.maps",
        "overlapmamba.service.api.system",
    ],
    ["overlapmamba.service.deps"],
    ["overlapmamba.service.places"],
    ["overlapmamba.service.pipeline"],
    ["overlapmamba.service.batcher", "overlapmamba.service.scans", "overlapmamba.service.encoder"],
    ["overlapmamba.service.fastscan"],
]


# the HTTP edge: what may import fastapi, starlette or overlapmamba.service.schemas
EDGE = {
    "overlapmamba.service.app",
    "overlapmamba.service.deps",
    "overlapmamba.service.auth",
    "overlapmamba.service.bodies",
    "overlapmamba.service.guard",
    "overlapmamba.service.schemas",
}
HTTP = ("fastapi", "starlette", "overlapmamba.service.schemas")


def _source(module: str) -> Path:
    path = ROOT / module.replace(".", "/")
    return path / "__init__.py" if path.is_dir() else path.with_suffix(".py")


def imports(module: str) -> set[str]:
    """Every module ``module`` imports, at any depth of its code, except under
    ``if TYPE_CHECKING:`` (annotations only; nothing runs)."""
    tree = ast.parse(_source(module).read_text())
    skip = {
        id(n)
        for node in ast.walk(tree)
        if isinstance(node, ast.If) and ast.unparse(node.test).endswith("TYPE_CHECKING")
        for body in node.body
        for n in ast.walk(body)
    }
    found = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
    return found


def service_imports(module: str) -> set[str]:
    return {m for m in imports(module) if m.startswith("overlapmamba.service.")}


def service_modules(packages: tuple[str, ...] = ("overlapmamba/service",)) -> list[str]:
    out = []
    for package in packages:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            out.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return out


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
    assert "overlapmamba.service.places" in service_imports("overlapmamba.service.api.queries")
    assert "overlapmamba.service.pipeline" in service_imports("overlapmamba.service.places")
    assert {"overlapmamba.service.batcher", "overlapmamba.service.scans"} <= service_imports(
        "overlapmamba.service.pipeline"
    )
    # routes reach scans only through the use cases, never the pipeline or encoder itself
    for route in LAYERS[1]:
        assert not {
            "overlapmamba.service.pipeline",
            "overlapmamba.service.batcher",
            "overlapmamba.service.encoder",
        } & service_imports(route), route


def test_nothing_below_the_routes_knows_http():
    modules = service_modules()
    assert (
        "overlapmamba.service.backends.faiss.map" in modules
        and "overlapmamba.service.places" in modules
    )
    leaks = [
        f"{m} imports {dep}"
        for m in modules
        if m not in EDGE and not m.startswith("overlapmamba.service.api")
        for dep in sorted(imports(m))
        if dep.startswith(HTTP)
    ]
    assert not leaks, leaks


def test_no_import_loop_in_any_package():
    """Function-level imports count too: a lazy import that closes a loop is still one."""
    modules = service_modules(("overlapmamba",))
    graph = {m: {d for d in imports(m) if d in modules and d != m} for m in modules}
    loops = []

    def visit(m: str, path: list[str]) -> None:
        for dep in sorted(graph[m]):
            if dep in path:
                loops.append(" → ".join([*path[path.index(dep) :], dep]))
            elif dep not in done:
                visit(dep, [*path, dep])
        done.add(m)

    done: set[str] = set()
    for m in graph:
        if m not in done:
            visit(m, [m])
    assert len(modules) > 120 and not loops, loops
