"""MkDocs hooks: the pages that live outside docs/ join the site where their links expect them.

README.md becomes the home page (its ``docs/x.md`` links become ``x.md``), CHANGELOG.md the
changelog, the model card ``models/README.md``, and every file under reports/ is served at
``reports/…`` so the pages' ``../reports/…`` links (right when read on a forge) resolve in the
site too. Strict mode then checks every one of those links and anchors.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from mkdocs.structure.files import File, Files, InclusionLevel

ROOT = Path(__file__).resolve().parents[1]
OUTSIDE = {"index.md": "README.md", "changelog.md": "CHANGELOG.md"}


def on_files(files: Files, config: Any) -> Files:
    for uri, src in OUTSIDE.items():
        files.append(File.generated(config, uri, abs_src_path=str(ROOT / src)))
    card = ROOT / "models" / "README.md"
    files.append(File.generated(config, "models/README.md", abs_src_path=str(card)))
    for path in sorted((ROOT / "reports").rglob("*")):
        if path.is_file():
            uri = path.relative_to(ROOT).as_posix()
            # a report's own Markdown table is linked from the pages, not a page of the nav
            inclusion = (
                InclusionLevel.NOT_IN_NAV if uri.endswith(".md") else InclusionLevel.UNDEFINED
            )
            files.append(File.generated(config, uri, abs_src_path=str(path), inclusion=inclusion))
    return files


def on_page_markdown(markdown: str, page: Any, config: Any, files: Files) -> str:
    uri = page.file.src_uri
    if uri in OUTSIDE:  # a root page: its links to docs/ are the site's own pages
        markdown = re.sub(r"\]\(docs/", "](", markdown)
        return re.sub(r"\]\(CHANGELOG\.md", "](changelog.md", markdown)
    if uri == "models/README.md":  # the model card: docs/ pages are the site's root pages
        markdown = re.sub(r"\]\(\.\./docs/", "](../", markdown)
        markdown = re.sub(r"\]\(\.\./README\.md", "](../index.md", markdown)
        return re.sub(r"\]\(\.\./CHANGELOG\.md", "](../changelog.md", markdown)
    if "/" not in uri:  # a docs/ page: ../reports, ../models, ../README.md sit beside it
        markdown = re.sub(r"\]\(\.\./(reports|models)/", r"](\1/", markdown)
        markdown = re.sub(r"\]\(\.\./README\.md", "](index.md", markdown)
        return re.sub(r"\]\(\.\./CHANGELOG\.md", "](changelog.md", markdown)
    return markdown
