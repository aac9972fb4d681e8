"""Figures a reader sees come from the command that measured them: a table a command writes
under reports/ is included in the documents as it is, between markers naming the file, and
this test fails when a copy differs from its file (or a marked block lost its file)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = (ROOT / "README.md", ROOT / "models" / "README.md", ROOT / "docs" / "deploy.md")
BLOCK = re.compile(r"<!-- include (\S+) -->\n(.*?)<!-- end include \1 -->\n", re.S)


def _blocks() -> list[tuple[Path, str, str]]:
    return [(doc, m[1], m[2]) for doc in DOCS for m in BLOCK.finditer(doc.read_text())]


def test_the_measured_tables_are_in_their_documents():
    included = {(str(doc.relative_to(ROOT)), name) for doc, name, _ in _blocks()}
    assert {
        ("README.md", "reports/model/sensors.md"),
        ("models/README.md", "reports/model/sensors.md"),
        ("docs/deploy.md", "reports/deploy/image.md"),
    } <= included


@pytest.mark.parametrize("doc,name,text", _blocks(), ids=lambda x: str(x)[-40:])
def test_an_included_table_is_its_file(doc, name, text):
    path = ROOT / name
    assert path.is_file(), f"{doc.name} includes {name}, which does not exist"
    assert text == path.read_text(), (
        f"{doc.relative_to(ROOT)}'s copy of {name} differs from the file: paste the file "
        "between the markers again (it is written by the command its first line names)"
    )
