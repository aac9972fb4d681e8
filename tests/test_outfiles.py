"""The output files of the command lines (overlapmamba.core.outfiles): checked before the
work, written whole."""

from __future__ import annotations

import os

import pytest

from overlapmamba.core.outfiles import check_output, write_whole


def test_an_output_is_checked_and_its_folder_made_before_the_work(tmp_path):
    check_output(tmp_path / "a" / "b" / "r.json", "--json")
    assert (tmp_path / "a" / "b").is_dir()  # made now, not after the work
    with pytest.raises(ValueError, match=r"--json .* is a folder; give a file name"):
        check_output(tmp_path / "a", "--json")
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="--out .*: cannot make its folder"):
        check_output(tmp_path / "file" / "r.json", "--out")
    with pytest.raises(ValueError, match="--plot .*p.txt: allowed formats are pdf, png"):
        check_output(tmp_path / "p.txt", "--plot", {"png", "pdf"})
    check_output(tmp_path / "p.PNG", "--plot", {"png", "pdf"})  # the suffix in any case


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
