"""The output files of the command lines (overlapmamba.core.outfiles): checked before the
work, written whole."""

from __future__ import annotations

import os

import pytest

from overlapmamba.core.outfiles import check_outputs, write_whole


def test_an_output_is_checked_and_its_folder_made_before_the_work(tmp_path):
    check_outputs(("--json", tmp_path / "a" / "b" / "r.json", None), ("--plot", None, None))
    assert (tmp_path / "a" / "b").is_dir()  # made now, not after the work
    with pytest.raises(ValueError, match=r"--json .* is a folder; give a file name"):
        check_outputs(("--json", tmp_path / "a", None))
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match=r"--out .*r.json: .*file is a file, not a folder"):
        check_outputs(("--out", tmp_path / "file" / "deeper" / "r.json", None))
    with pytest.raises(ValueError, match="--plot .*p.txt: allowed formats are pdf, png"):
        check_outputs(("--plot", tmp_path / "p.txt", {"png", "pdf"}))
    check_outputs(("--plot", tmp_path / "p.PNG", {"png", "pdf"}))  # the suffix in any case
    # two outputs at one file (found in review: observe --record and --g2o), however named
    same = tmp_path / "a" / "b" / ".." / "b" / "r.json"
    with pytest.raises(ValueError, match="--json and --plot are the same file"):
        check_outputs(("--json", tmp_path / "a" / "b" / "r.json", None), ("--plot", same, None))


def test_a_refused_output_leaves_no_folder_made_for_another(tmp_path):
    """Every output is checked before any folder is made: a refused plot leaves no new
    folder behind for the JSON beside it."""
    with pytest.raises(ValueError, match="allowed formats"):
        check_outputs(
            ("--json", tmp_path / "new" / "r.json", None),
            ("--plot", tmp_path / "p.txt", {"png"}),
        )
    assert not (tmp_path / "new").exists()


def test_a_write_cut_off_leaves_the_old_file_and_no_temporary_one(tmp_path, monkeypatch):
    path = tmp_path / "r.json"
    write_whole(path, "old\n")

    def cut(*args: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", cut)
    with pytest.raises(OSError, match="No space"):
        write_whole(path, "new\n")
    assert path.read_text() == "old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.json"]
    monkeypatch.undo()
    write_whole(path, "new\n")
    assert path.read_text() == "new\n"
