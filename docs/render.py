"""Paste the tables that commands write under reports/ into the documents that include them.

A document includes a file between two markers:

    <!-- include reports/model/sensors.md -->
    … the file's text, as it is …
    <!-- end include reports/model/sensors.md -->

``python docs/render.py`` (``make docs``) replaces every such block with the file's current
text; ``--check`` changes nothing and exits 1 naming each block that differs (what
``tests/test_docs_figures.py`` asserts). The file names its own command in its first line.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = (ROOT / "README.md", ROOT / "models" / "README.md", ROOT / "docs" / "deploy.md")
BLOCK = re.compile(r"(<!-- include (\S+) -->\n)(.*?)(<!-- end include \2 -->\n)", re.S)


def render(text: str) -> str:
    def paste(m: re.Match[str]) -> str:
        return m[1] + (ROOT / m[2]).read_text() + m[4]

    return BLOCK.sub(paste, text)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--check", action="store_true", help="change nothing; exit 1 if stale")
    args = ap.parse_args()
    stale = []
    for doc in DOCS:
        text = doc.read_text()
        new = render(text)
        if new != text:
            stale.append(doc.relative_to(ROOT))
            if not args.check:
                doc.write_text(new)
    verb = "differs" if args.check else "rendered"
    for path in stale:
        print(f"{path}: {verb}")
    return 1 if args.check and stale else 0


if __name__ == "__main__":
    sys.exit(main())
