"""docs/architecture.md matches the code: every module it names imports (and every name it
gives inside one exists), and every service module is on the page."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "architecture.md"
PACKAGES = ("overlapmamba",)


def _named() -> set[str]:
    pattern = rf"`((?:{'|'.join(PACKAGES)})(?:\.[A-Za-z_][A-Za-z0-9_]*)*)`"
    return set(re.findall(pattern, PAGE.read_text()))


def test_every_name_on_the_page_exists():
    missing = []
    for name in sorted(_named()):
        try:
            importlib.import_module(name)
        except ModuleNotFoundError:
            module, _, attr = name.rpartition(".")
            try:
                if not hasattr(importlib.import_module(module), attr):
                    missing.append(name)
            except ModuleNotFoundError:
                missing.append(name)
    assert len(_named()) > 60 and not missing, missing


def test_every_service_module_is_on_the_page():
    named = _named()
    modules = []
    for path in sorted((ROOT / "overlapmamba" / "service").rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        if parts[-1] != "__init__":
            modules.append(".".join(parts))
    absent = [m for m in modules if m not in named]
    assert not absent, f"docs/architecture.md does not name {absent}"
