"""The benchmarks' drives generated on first use (``benchmarks/common_beams.py:drive``):
runs that need the same drive at once generate it once and both read it whole."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"

# one run's side: the tiny preset cut to 40 scans, generated into the shared scratch folder
RUN = """
import sys, json
sys.path.insert(0, {benchmarks!r})
from pathlib import Path
from common_beams import drive
from overlapmamba.synth.presets import PRESETS
cfg = PRESETS["tiny"].model_copy(update={{"frames": 40}})
asked = []  # drive() asks for the configuration only to generate
out = drive(Path({scratch!r}), Path({data!r}), "race", lambda: asked.append(1) or cfg)
print(json.dumps({{"out": str(out), "generated": bool(asked)}}))
"""


def test_two_runs_needing_one_drive_generate_it_once_and_both_read_it_whole(tmp_path):
    pytest.importorskip("embreex")
    scratch, data = tmp_path / "scratch", tmp_path / "data"
    code = RUN.format(benchmarks=str(BENCHMARKS), scratch=str(scratch), data=str(data))
    runs = [
        subprocess.Popen(
            [sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE
        )
        for _ in range(2)
    ]
    outs = [run.communicate(timeout=240) for run in runs]
    answers = []
    for run, (out, err) in zip(runs, outs, strict=True):
        assert run.returncode == 0, err.decode()[-2000:]
        answers.append(json.loads(out.decode().strip().splitlines()[-1]))
    assert [a["out"] for a in answers] == [str(scratch / "race")] * 2
    assert sorted(a["generated"] for a in answers) == [False, True]  # one made it, one waited
    assert (scratch / "race" / "manifest.json").is_file()
    scans = sorted((scratch / "race").rglob("*.bin"))
    assert len(scans) == 40, len(scans)
