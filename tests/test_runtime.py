"""Process set-up for heavy commands: the one-time restart with glibc's huge-page tunable."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

SCRIPT = (
    "import os; from overlapmamba.train.runtime import reexec_with_hugepages; "
    "reexec_with_hugepages(); print(os.environ.get('GLIBC_TUNABLES', ''))"
)


def run(env: dict) -> str:
    result = subprocess.run(
        [sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, check=True
    )
    return result.stdout.strip()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc tunables are Linux-only")
def test_restarts_once_with_the_tunable_and_keeps_other_tunables():
    env = {
        k: v for k, v in os.environ.items() if k not in ("GLIBC_TUNABLES", "OVERLAPMAMBA_NO_REEXEC")
    }
    assert run(env) == "glibc.malloc.hugetlb=1"
    assert run({**env, "GLIBC_TUNABLES": "glibc.malloc.arena_max=2"}) == (
        "glibc.malloc.arena_max=2:glibc.malloc.hugetlb=1"
    )
    # Already set (the restarted process itself): no second restart, nothing changed.
    assert run({**env, "GLIBC_TUNABLES": "glibc.malloc.hugetlb=0"}) == "glibc.malloc.hugetlb=0"


def test_opt_out_leaves_the_process_alone():
    env = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
    assert run({**env, "OVERLAPMAMBA_NO_REEXEC": "1"}) == ""
