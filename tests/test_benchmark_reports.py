"""Benchmarks write their figures under reports/, each JSON with the command, commit, machine
and date inside (benchmarks/reports_kit.py), so the documents can render them from files in
the repository rather than from an ignored folder."""

from __future__ import annotations

import ast
import json
import sys
from pathlib import Path

from conftest import benchmark_module

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"


def _argument_defaults(tree: ast.AST) -> list[tuple[str, str]]:
    """(option, the default's source) for every add_argument(..., default=...) call."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "add_argument":
            for kw in node.keywords:
                if kw.arg == "default" and node.args and isinstance(node.args[0], ast.Constant):
                    out.append((str(node.args[0].value), ast.unparse(kw.value)))
    return out


def test_every_benchmark_writes_its_json_under_reports_with_its_provenance():
    scripts = sorted(BENCH.glob("*.py"))
    assert len(scripts) > 10
    for script in scripts:
        text = script.read_text()
        tree = ast.parse(text)
        for option, default in _argument_defaults(tree):
            if default.endswith(('.json"', '.jsonl"')):
                assert "REPORTS" in default or "reports" in default, (
                    f"{script.name} {option} defaults to {default}: figures go under reports/"
                )
            assert "bench-results" not in default or not default.endswith('.json"'), (
                f"{script.name} {option}: {default} is an ignored folder"
            )
        if "json.dumps" in text and ".write_text(" in text and script.name != "reports_kit.py":
            assert "write_report(" in text or "**provenance()" in text, (
                f"{script.name} writes JSON without its provenance: use "
                "reports_kit.write_report, which records the command, commit, machine and date"
            )


def test_a_written_report_names_its_command_commit_machine_and_date(tmp_path, monkeypatch):
    reports_kit = benchmark_module("reports_kit")
    monkeypatch.setattr(sys, "argv", [str(BENCH / "views.py"), "--scans", "3"])
    out = tmp_path / "deep" / "x.json"
    reports_kit.write_report(out, {"figure": 1.5, "date": "kept"})
    got = json.loads(out.read_text())
    assert got["command"] == "python benchmarks/views.py --scans 3"
    assert len(got["commit"].removesuffix("-dirty")) in (40, len("unknown"))
    assert got["machine"]["cores"] >= 1 and got["machine"]["cpu"]
    assert got["figure"] == 1.5 and got["date"] == "kept"  # the record's own keys win
    assert list(got)[:4] == ["command", "commit", "machine", "date"]


def test_a_report_names_a_file_inside_the_checkout_as_a_clone_has_it_and_others_as_given(
    tmp_path, monkeypatch
):
    reports_kit = benchmark_module("reports_kit")
    monkeypatch.chdir(reports_kit.ROOT)
    inside = Path("models") / ".." / "models" / "overlapmamba-hdl64.onnx"
    assert reports_kit.shown_path(inside) == "models/overlapmamba-hdl64.onnx"
    assert reports_kit.shown_path(reports_kit.ROOT / "reports") == "reports"
    outside = tmp_path / "candidate.onnx"  # never created: a report names it all the same
    assert reports_kit.shown_path(outside) == str(outside)


def test_the_encoder_benchmarks_tables_print_from_its_committed_record():
    """benchmarks/encoder.py prints its tables from the record it writes (encoder_tables),
    so a committed JSON prints them again; every variant and ratio is in them."""
    from rich.console import Console

    tables = benchmark_module("encoder_tables")
    record = json.loads((ROOT / "reports" / "service" / "encoder-narrow.json").read_text())
    console = Console(record=True, width=200)
    tables.print_tables(console, record)
    text = console.export_text()
    for name in [*record["variants"], *record["ratios"]]:
        assert name in text, name
    assert "OT-style" in text and "GFLOP per scan" in text


def test_the_server_profile_counts_each_sample_in_the_first_part_its_stack_holds():
    """benchmarks/server_profile.py groups py-spy's raw stacks: a stack holding two parts'
    code counts in the first listed (the registrar's call waiting on its pipe is
    registration), a stack of no part is the rest, and the shares sum to one."""
    import pytest

    prof = benchmark_module("server_profile")
    raw = "\n".join(
        [
            "process 1:x;run (overlapmamba/service/pipeline.py:10);"
            "Session.run (onnxruntime/capi/onnxruntime_inference_collection.py:406) 6",
            "process 2:x;_verify (overlapmamba/service/registrar.py:430);"
            "register (overlapmamba/service/registration.py:253) 3",
            "process 1:x;pixel_coordinates (overlapmamba/core/projection.py:71) 1",
            "process 1:x;Runner.run (asyncio/runners.py:118) 2",
            "garbage",
        ]
    )
    got, samples = prof.shares(raw)
    assert samples == 12 and sum(got.values()) == pytest.approx(1.0)
    assert got["encoder"] == pytest.approx(0.5) and got["registration"] == pytest.approx(0.25)
    assert got["projection"] == pytest.approx(1 / 12) and got[prof.REST] == pytest.approx(2 / 12)
    assert prof.part_of("a;scan_forward (overlapmamba/core/scan_kernel.py:282)") == "encoder"
    waiting = (
        "a;_call (overlapmamba/service/registrar.py:300);_send (multiprocessing/connection.py:384)"
    )
    assert prof.part_of(waiting) == "registration"
    assert prof.part_of("a;_send (multiprocessing/connection.py:384)").startswith("pipe")
    with pytest.raises(SystemExit, match="no samples"):
        prof.shares("")


def _towns(report: dict) -> list[str]:
    """The towns a fleet or load report ran on, by their folder's name."""
    named = [report.get("sequence"), report.get("drive"), *(report.get("drives") or [])]
    return [Path(t).name for t in named if t]


def test_fleet_and_load_figures_are_measured_on_a_held_out_town():
    """Every fleet and end-to-end load report ran on a test town: each file's thresholds were
    chosen on `val` (and `val-s1`), so precision and recall there are no held-out figures.
    fleet_views.py runs on `test` unless told otherwise."""
    reports = sorted((ROOT / "reports" / "client").glob("fleet*.json"))
    reports += sorted((ROOT / "reports" / "e2e").glob("load*.json"))
    reports.append(ROOT / "reports" / "service" / "server-profile.json")
    seen = {}
    for path in reports:
        towns = _towns(json.loads(path.read_text()))
        assert towns, f"{path.relative_to(ROOT)} names no town it ran on"
        seen[path.relative_to(ROOT).as_posix()] = towns
    off = {p: t for p, t in seen.items() if not all(x.startswith("test") for x in t)}
    assert not off, f"fleet figures measured off the test towns: {off}"
    tree = ast.parse((BENCH / "fleet_views.py").read_text())
    assert ("--sequence", "ROOT / 'data' / 'synth' / 'test'") in _argument_defaults(tree)
