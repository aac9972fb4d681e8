"""Worker pools: safe after onnxruntime and torch ran in the parent, and never an endless wait."""

from __future__ import annotations

import gc
import math
import operator
import os
import re
import time
from pathlib import Path

import numpy as np
import pytest

from overlapmamba.synth.config import GenConfig
from overlapmamba.synth.generate import generate, read_manifest
from overlapmamba.synth.workers import WorkerError, run_jobs, start_method

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("overlapmamba", "benchmarks")


def test_generate_with_workers_after_onnxruntime_and_torch_ran_in_this_process(tmp_path):
    """The hang of a forked pool: a parent that ran onnxruntime and torch thread pools, then
    left an onnxruntime session as garbage for the collector to free — in a forked child, that
    free waits forever on a lock whose owner thread does not exist there."""
    ort = pytest.importorskip("onnxruntime")
    torch = pytest.importorskip("torch")

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 2
    sess = ort.InferenceSession(
        str(ROOT / "models" / "overlapmamba-hdl64.onnx"), opts, providers=["CPUExecutionProvider"]
    )
    inp = sess.get_inputs()[0]
    shape = [1 if not isinstance(d, int) else d for d in inp.shape]
    out = sess.run(None, {inp.name: np.random.default_rng(0).random(shape, np.float32)})
    assert np.isfinite(out[0]).all()
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        a = torch.randn(512, 512)
        assert torch.isfinite(a @ a).all()
    finally:
        torch.set_num_threads(before)  # the process's later tests compute as they would have
    garbage: list = [sess]
    garbage.append(garbage)  # a cycle: only the garbage collector frees this session
    del sess, garbage  # pending for the collector, as in the reported hang

    cfg = GenConfig(seed=9, frames=12, sensor="hdl32", world={"nx": 2, "ny": 2}, gt_radius=10.0)
    t0 = time.monotonic()
    generate(tmp_path / "town", cfg, workers=2, progress=False, stall_timeout_s=60)
    gc.collect()
    man = read_manifest(tmp_path / "town")
    assert man["counts"]["frames"] == 12
    assert len(list((tmp_path / "town" / "velodyne").glob("*.bin"))) == 12
    assert (tmp_path / "town" / "ground_truth" / "loops.npz").exists()
    assert time.monotonic() - t0 < 60


def test_no_pool_in_the_packages_forks():
    assert start_method() in ("forkserver", "spawn")
    # Deterministic where the hang is not: workers are not children of this (threaded) process
    # but of the fork server, which holds no thread pools.
    parents = {ppid for _, ppid in run_jobs(operator.call, [os.getppid] * 4, workers=2)}
    if start_method() == "forkserver":
        assert os.getpid() not in parents
    forks = [
        f"{p.relative_to(ROOT)}:{n}"
        for pkg in PACKAGES
        for p in (ROOT / pkg).rglob("*.py")
        for n, line in enumerate(p.read_text().splitlines(), 1)
        if re.search(r"""get_context\(\s*["']fork["']|set_start_method\(\s*["']fork["']""", line)
    ]
    assert not forks, f"worker pools must not fork: {forks}"


def test_results_come_back_for_every_job():
    got = dict(run_jobs(abs, range(-20, 20), workers=2, stall_timeout_s=60))
    assert got == {i: abs(i - 20) for i in range(40)}


def test_a_dead_worker_is_an_error_naming_the_job():
    t0 = time.monotonic()
    with pytest.raises(WorkerError, match=r"worker process died while running chunk \d"):
        list(run_jobs(os._exit, [3, 3, 3], workers=2, stall_timeout_s=60, what="chunk"))
    assert time.monotonic() - t0 < 30  # reported when it happens, not after the stall limit


def test_a_stuck_worker_is_killed_and_named():
    t0 = time.monotonic()
    jobs = [0.0, 0.0, 0.0, 120.0]  # job 3 never finishes in time
    with pytest.raises(WorkerError, match=r"no scan finished in 1\.5 s.*in flight: \[3\]"):
        for _ in run_jobs(time.sleep, jobs, workers=2, stall_timeout_s=1.5, what="scan"):
            pass
    assert time.monotonic() - t0 < 30  # the sleeping worker was killed, not waited for


def test_an_error_in_a_job_keeps_its_type_and_names_the_job():
    with pytest.raises(ValueError, match="math domain error") as info:
        list(run_jobs(math.sqrt, [4.0, 9.0, -1.0], workers=2, stall_timeout_s=60))
    assert "raised by job 2 in a worker process" in info.value.__notes__


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [({"workers": 0}, "workers must be ≥ 1"), ({"stall_timeout_s": 0}, "stall_timeout_s")],
)
def test_bad_pool_arguments_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        list(run_jobs(abs, [1], **{"workers": 2, "stall_timeout_s": 5.0, **kwargs}))
