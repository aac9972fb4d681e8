"""Figures a reader sees come from the command that measured them: a table a command writes
under reports/ is included in the documents as it is, or rendered from a report's JSON,
between markers naming its source (docs/render.py, `make docs`), and this test fails when a
copy differs from what its source gives (or a marked block lost its source)."""

from __future__ import annotations

import importlib.util
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("docs_render", ROOT / "docs" / "render.py")
assert _spec and _spec.loader
render = importlib.util.module_from_spec(_spec)
sys.modules["docs_render"] = render
_spec.loader.exec_module(render)


def _rel(doc: Path) -> str:
    return str(doc.relative_to(ROOT))


def _includes() -> list[tuple[Path, str, str]]:
    blocks = render.INCLUDE.finditer
    return [(doc, m[2], m[3]) for doc in render.DOCS for m in blocks(doc.read_text())]


def _rendered() -> list[tuple[Path, str, str]]:
    blocks = render.RENDER.finditer
    return [(doc, m[2], m[3]) for doc in render.DOCS for m in blocks(doc.read_text())]


def test_the_measured_tables_are_in_their_documents():
    included = {(_rel(doc), name) for doc, name, _ in _includes()}
    assert {
        ("docs/results.md", "reports/model/sensors.md"),
        ("models/README.md", "reports/model/sensors.md"),
        ("docs/deploy.md", "reports/deploy/image.md"),
    } <= included
    rendered = {(_rel(doc), name) for doc, name, _ in _rendered()}
    assert {
        ("README.md", "headline"),
        ("models/README.md", "model-tables"),
        ("models/README.md", "encoder"),
        ("docs/results.md", "encoder"),
        ("docs/results.md", "service"),
        ("docs/results.md", "verify"),
        ("docs/results.md", "e2e"),
        ("docs/deploy.md", "sizing"),
        ("docs/service.md", "calibration"),
        ("docs/service.md", "covariance"),
        ("docs/client.md", "fleet"),
        ("docs/client.md", "tf-memory"),
    } <= rendered
    assert set(render.RENDERERS) == {name for _, name in rendered}, "a renderer nobody uses"


@pytest.mark.parametrize("doc", render.FIGURE_FREE, ids=_rel)
def test_no_measured_figure_is_typed_by_hand(doc):
    found = render.hand_typed(doc.read_text())
    assert not found, (
        f"{_rel(doc)} types measured figures outside rendered blocks (render them from the "
        "JSON their command wrote, or move the history to CHANGELOG.md's lab notebook):\n"
        + "\n".join(f"  line {i}: {line}" for i, line in found)
    )


def test_the_figure_detector_knows_a_measurement_from_a_setting():
    measured = [
        "F1max 0.929 against 0.747",
        "a query takes 27.0 ms",
        "the run took ≈ 2.5 h",
        "about 34 observations/s with 8 robots",
        "the yaw features are 92 % of it",
        "three views cost 2.35× one view",
    ]
    for text in measured:
        assert render.hand_typed(text), text
    settings = [
        "mounted 1.73 m up, pitched 5° down",
        "a cosine ≥ 0.999 under any turn",
        "`loop_closure.accept_distance = 0.1794`",
        "Recall@1% over 2,500 scans of 64 × 900",
        "<!-- render headline -->\n| 0.929 | 27.0 ms |\n<!-- end render headline -->\n",
        "```\ntook 12.5 ms\n```\n",
    ]
    for text in settings:
        assert not render.hand_typed(text), text


@pytest.mark.parametrize("doc,name,text", _includes(), ids=lambda x: str(x)[-40:])
def test_an_included_table_is_its_file(doc, name, text):
    path = ROOT / name
    assert path.is_file(), f"{doc.name} includes {name}, which does not exist"
    assert text == path.read_text(), (
        f"{_rel(doc)}'s copy of {name} differs from the file: `make docs` pastes it again "
        "(it is written by the command its first line names)"
    )


@pytest.mark.parametrize("doc,name,text", _rendered(), ids=lambda x: str(x)[-40:])
def test_a_rendered_table_is_its_json(doc, name, text):
    assert name in render.RENDERERS, f"{_rel(doc)} asks for an unknown table {name!r}"
    made = render.RENDERERS[name]()
    assert text == made, f"{_rel(doc)}'s table {name} differs from its JSON: run `make docs`"
    assert re.match(
        r"<!-- from reports/\S+\.(json|jsonl|md)( \([\d-]+\))?, written by `[^`]+`", made
    ), "a rendered table names its JSON and the command that wrote it"


def test_a_stale_block_is_found_and_rendered_again():
    doc = "x\n<!-- render headline -->\n| stale |\n<!-- end render headline -->\ny\n"
    fresh = render.render(doc)
    assert "| stale |" not in fresh and fresh.startswith("x\n") and fresh.endswith("y\n")
    assert render.render(fresh) == fresh
    with pytest.raises(KeyError, match="no renderer 'nope'"):
        render.render("<!-- render nope -->\n<!-- end render nope -->\n")
    with pytest.raises(FileNotFoundError, match="missing"):
        render.render("<!-- include reports/nope.md -->\n<!-- end include reports/nope.md -->\n")


def test_the_readme_fits_a_newcomer():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 300, f"README.md has {len(lines)} lines; its details belong in docs/"


def test_the_covariance_reading_says_what_its_numbers_say():
    """The sentence under the covariance table is read off the numbers (a recalibration
    cannot leave it stale): the share inside the 95% ellipsoid is "about" 0.95 within two
    binomial standard errors; heavy tails are fewer inside the 95% ellipsoid than a Gaussian
    fitted to the 50% share would hold, which a Gaussian only too wide is not."""
    from scipy.stats import chi2

    figures = sys.modules["figures_covariance"]  # imported by docs/render.py, beside it

    def town(name: str, n: int, half: float, most: float, nll: float) -> dict:
        served = {"closures": n, "inside": {"0.5": half, "0.95": most}, "nll": nll}
        return {
            "town": f"data/{name}",
            "served": served,
            "constant": {"closures": n, "nll": -20.0},
        }

    # c: a Gaussian 1.5 times too wide in variance: its 50% and 95% shares, no heavier tail
    wide = [float(chi2.cdf(chi2.ppf(q, 6) * 1.5, 6)) for q in (0.5, 0.95)]
    towns = [
        town("a", 400, 0.50, 0.95, -25.0),
        town("b", 400, 0.70, 0.90, -15.0),
        town("c", 400, *wide, -22.0),
    ]
    said = figures._covariance_reading(towns)
    assert "lower NLL on 2 of 3 test towns (`a`, `c`)" in said
    assert "about their share on `a`; fewer on `b`; more on `c`" in said
    assert "heavier tails than a Gaussian's on `b`:" in said
    assert figures._heavy_tailed({"0.5": 0.70, "0.95": 0.90}, 400)
    assert not figures._heavy_tailed({"0.5": wide[0], "0.95": wide[1]}, 400)
    assert not figures._heavy_tailed({"0.5": 1.0, "0.95": 1.0}, 50)  # every one inside
    assert "On no town do the errors show heavier tails" in figures._covariance_reading(towns[2:])
    assert figures._share(0.97, 0.95, 100) == "about"  # 2σ is 0.044 for 100 closures
    assert figures._share(0.97, 0.95, 10_000) == "more"


def test_the_covariance_across_sensors_reading_says_what_its_numbers_say():
    """Under the covariance across sensors: the pooled shares across sensors and on the same
    sensor, each pair's (queries → map) against one ellipsoid, and the calibration town's,
    each read off its numbers."""
    figures = sys.modules["figures_covariance"]

    def cov(n: int, most: float, nll: float, k_nll: float) -> dict:
        served = {"closures": n, "inside": {"0.95": most}, "nll": nll}
        return {"served": served, "constant": {"closures": n, "nll": k_nll}}

    summary = {"across": {"covariance": cov(4000, 0.88, -27, -17)}}
    summary["same"] = {"covariance": cov(100, 0.94, -29, -23)}
    across = [("A → B", cov(400, 0.95, -30, -20)), ("B → A", cov(400, 0.80, -10, -20))]
    said = figures._across_reading(across, summary)
    assert "hold fewer across sensors, pooled, and about their share on the same" in said
    assert "on the 2 pairs with a right closure: its NLL is lower than one ellipsoid's on 1" in said
    assert "about their share on 1; fewer on 1 (fewer: B → A)" in said
    assert "hold more.\n" in figures._val_reading(cov(3000, 0.97, -28, -23))
    assert figures._share(0.5, 0.95, 2) == "about"  # 1 of 2: the exact test cannot tell
    assert figures._share(0.5, 0.95, 4) == "fewer"  # 2 of 4: it can
    none = {"served": {"closures": 0, "estimator": "residual"}, "constant": {"closures": 0}}
    empty = {"across": {"covariance": none}, "same": {"covariance": none}}
    assert "hold nothing (no right closure) across sensors" in figures._across_reading([], empty)


def test_the_covariance_across_sensors_figure_reads_its_grid_queries_down_maps_across(tmp_path):
    """covariance_across: a cell is the queries' sensor's row and the map's column, with its
    closures counted; a pair without a right closure says so; the pooled rows name their
    pairs' count from the JSON."""
    import json

    figures = sys.modules["figures_covariance"]

    def scores(n: int, most: float) -> dict:
        s = {"closures": n, "estimator": "residual", "scale": 6.0, "nll": -28.0}
        if n:
            s |= {"inside": {"0.5": 0.7, "0.9": 0.9, "0.95": most, "0.99": 0.99}}
            s |= {"sigma_median": {"x_m": 0.01, "yaw_deg": 0.01}}
            s |= {"error_rms": {"x_m": 0.02, "yaw_deg": 0.01}}
        return {"served": s}

    pairs = [
        {"queries_sensor": "vlp16", "map_sensor": "kitti-hdl64", "covariance": scores(7, 0.8)},
        {"queries_sensor": "kitti-hdl64", "map_sensor": "vlp16", "covariance": scores(0, 0)},
        {"queries_sensor": "vlp16", "map_sensor": "vlp16", "covariance": scores(50, 0.96)},
        {"queries_sensor": "kitti-hdl64", "map_sensor": "kitti-hdl64",
         "covariance": scores(60, 0.95)},
    ]  # fmt: skip
    summary = {
        "across": {"pairs": 2, "covariance": scores(7, 0.8)},
        "same": {"pairs": 2, "covariance": scores(110, 0.95)},
    }
    report = {
        "command": "python benchmarks/verify_across.py",
        "date": "2026-12-05T00:00:00+00:00",
        "model_id": "om-x",
        "covariance": {"scored": {"served": {"estimator": "residual", "scale": 6.0}}},
        "test": {"pairs": pairs, "summary": summary},
    }
    path = tmp_path / "across.json"
    path.write_text(json.dumps(report))
    made = figures.covariance_across(str(path))
    assert "| across sensors (2 pairs) | served (residual) | 7 |" in made
    rows = [[c.strip() for c in x.strip("|").split("|")] for x in made.splitlines()]
    head = next(r for r in rows if r[0] == "queries ↓ map →")
    grid = {r[0]: dict(zip(head[1:], r[1:], strict=True)) for r in rows if len(r) == len(head)}
    assert grid["HDL-64E"]["VLP-16"] == "no right closure"  # queries HDL-64E, map VLP-16
    assert grid["VLP-16"]["HDL-64E"].startswith("0.800 of 7,")  # queries VLP-16, map HDL-64E
    assert "on the 1 pairs with a right closure" in made
