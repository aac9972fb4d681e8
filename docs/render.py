"""Paste the tables that commands write under reports/ into the documents that include them.

A document includes a file between two markers:

    <!-- include reports/model/sensors.md -->
    … the file's text, as it is …
    <!-- end include reports/model/sensors.md -->

or a table rendered here from a report's JSON:

    <!-- render headline -->
    … the table ``RENDERERS["headline"]`` makes, naming its JSON and command …
    <!-- end render headline -->

``python docs/render.py`` (``make docs``) replaces every such block with the file's current
text or the table; ``--check`` changes nothing and exits 1 naming each document that differs
(what ``tests/test_docs_figures.py`` asserts). An included file names its own command in its
first line; a rendered table names its JSON and the command that wrote it.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
import figures_bev  # docs/figures_*.py, beside this file
import figures_covariance
import figures_cpu
import figures_cut
import figures_fill
import figures_firing
import figures_fleet
import figures_input
import figures_lerp
import figures_memory
import figures_model
import figures_onepass
import figures_pairs
import figures_phase
import figures_runs
import figures_scan
import figures_sensors
import figures_spectrum
import figures_verify

ROOT = Path(__file__).resolve().parents[1]
DOCS = (
    ROOT / "README.md",
    ROOT / "CHANGELOG.md",
    ROOT / "models" / "README.md",
    *sorted((ROOT / "docs").glob("*.md")),
)
INCLUDE = re.compile(r"(<!-- include (\S+) -->\n)(.*?)(<!-- end include \2 -->\n)", re.S)
RENDER = re.compile(r"(<!-- render (\S+) -->\n)(.*?)(<!-- end render \2 -->\n)", re.S)

TWO_STAGE = "reports/model/two-stage/report.json"
SHIPPED = "OverlapMamba narrow, mined hard negatives (shipped)"


def headline() -> str:
    """The shipped model against Scan Context (README): loop closure on the three test towns
    (mean), across sessions and on real KITTI 00, from the two-stage report."""
    r: dict[str, Any] = json.loads((ROOT / TWO_STAGE).read_text())
    t1, xs = r["table1"], r["cross_session"]
    real = r["real"]["kitti00"]["retrieval_odd_to_even"]
    rows = [
        ("Scan Context", "Scan Context", real["scan_context"]["recall@1"]),
        ("OverlapMamba, the descriptor alone", SHIPPED, real["recall@1"]),
        (
            "**OverlapMamba as the service answers** (two stages)",
            f"{SHIPPED} + yaw re-rank",
            real["reranked"]["recall@1"],
        ),
    ]
    f = lambda x: f"{x['f1max']:.3f} / {x['recall@1']:.3f}"  # noqa: E731
    lines = [
        f"<!-- from {TWO_STAGE}, written by `overlapmamba report --runs EMPTY --out "
        "reports/model/two-stage`; rendered by `make docs` -->",
        "",
        f"| method | all revisits | same direction | reverse | across sessions AR@1 "
        f"| real KITTI 00 Recall@1 ({real['hit_radius_m']:g} m) |",
        "|---|---|---|---|---|---|",
    ]
    for label, key, kitti in rows:
        m = t1[key]
        lines.append(
            f"| {label} | {f(m['all'])} | {f(m['same'])} | {f(m['reverse'])} | "
            f"{xs[key]['ar@1']:.3f} | {kitti:.3f} |"
        )
    n = t1["Scan Context"]["all"]
    lines += [
        "",
        f"{n['queries']:,} queries ({n['queries_with_loop']:,} with a loop) on "
        f"{', '.join(Path(p).name for p in r['test'])}; across sessions: "
        f"{Path(xs['queries']).name} queried against {Path(xs['database']).name} "
        f"({xs['Scan Context']['queries']:,} queries, a hit within "
        f"{xs['Scan Context']['radius_m']:g} m).",
    ]
    return "\n".join(lines) + "\n"


RENDERERS: dict[str, Callable[[], str]] = {
    "headline": headline,
    **figures_model.RENDERERS,
    **figures_onepass.RENDERERS,
    **figures_input.RENDERERS,
    **figures_bev.RENDERERS,
    **figures_lerp.RENDERERS,
    **figures_cpu.RENDERERS,
    **figures_cut.RENDERERS,
    **figures_fill.RENDERERS,
    **figures_firing.RENDERERS,
    **figures_fleet.RENDERERS,
    **figures_memory.RENDERERS,
    **figures_pairs.RENDERERS,
    **figures_runs.RENDERERS,
    **figures_phase.RENDERERS,
    **figures_scan.RENDERERS,
    **figures_sensors.RENDERERS,
    **figures_spectrum.RENDERERS,
    **figures_verify.RENDERERS,
    **figures_covariance.RENDERERS,
}


def render(text: str) -> str:
    def paste(m: re.Match[str]) -> str:
        if not (ROOT / m[2]).is_file():
            raise FileNotFoundError(
                f"{m[2]} is included but missing: run the command that writes it"
            )
        return m[1] + (ROOT / m[2]).read_text() + m[4]

    def table(m: re.Match[str]) -> str:
        if m[2] not in RENDERERS:
            raise KeyError(f"no renderer {m[2]!r}; known: {', '.join(RENDERERS)}")
        return m[1] + RENDERERS[m[2]]() + m[4]

    return RENDER.sub(table, INCLUDE.sub(paste, text))


# What a measured figure looks like in prose: a number with three or more decimals (0.929,
# 0.99955; not a bound such as "≥ 0.999"), a time in ms, an approximate duration (≈ 2 h),
# a rate (scans/s, observations/s), a percentage or a decimal ratio (2.29×). Settings,
# specifications and counts are written without them (or in `code`, where a setting's value
# belongs).
MEASURED = re.compile(
    r"(?<![\w.])(?<![≥≤<>] )(?<![≥≤<>])\d+\.\d{3,}"
    r"|\d+(?:\.\d+)?\s?(?:ms|µs)\b"
    r"|≈\s?\d+(?:[.,]\d+)?\s?(?:s|min|minutes|h|hours)\b"
    r"|\d+(?:\.\d+)?\s?(?:scans|obs|observations|queries)/s\b"
    r"|(?<![@\d.])\d+(?:\.\d+)?\s?%"  # not the metric Recall@1%
    r"|\d+\.\d+\s?×"
)
# the pages a user reads, where every measured figure must be rendered (the changelog keeps
# the lab notebook's history as it was measured)
FIGURE_FREE = tuple(d for d in DOCS if d.name != "CHANGELOG.md")


def hand_typed(text: str) -> list[tuple[int, str]]:
    """(line number, line) of every line with a measured-looking figure outside the rendered
    and included blocks, code blocks and `code` spans."""
    blanked = INCLUDE.sub(lambda m: "\n" * m[0].count("\n"), text)
    blanked = RENDER.sub(lambda m: "\n" * m[0].count("\n"), blanked)
    blanked = re.sub(r"```.*?```", lambda m: "\n" * m[0].count("\n"), blanked, flags=re.S)
    blanked = re.sub(r"<!--.*?-->", lambda m: "\n" * m[0].count("\n"), blanked, flags=re.S)
    out = []
    for i, line in enumerate(blanked.splitlines(), 1):
        if MEASURED.search(re.sub(r"`[^`]*`", "", line)):
            out.append((i, line.strip()))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--check", action="store_true", help="change nothing; exit 1 if stale")
    args = ap.parse_args()
    stale, broken = [], []
    for doc in DOCS:
        text = doc.read_text()
        try:
            new = render(text)
        except (FileNotFoundError, KeyError) as e:
            broken.append(f"{doc.relative_to(ROOT)}: {e}")
            continue
        if new != text:
            stale.append(doc.relative_to(ROOT))
            if not args.check:
                doc.write_text(new)
    verb = "differs" if args.check else "rendered"
    for path in stale:
        print(f"{path}: {verb}")
    for line in broken:
        print(line, file=sys.stderr)
    return 1 if broken or (args.check and stale) else 0


if __name__ == "__main__":
    sys.exit(main())
