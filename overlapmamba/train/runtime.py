"""Process set-up for training-sized work on CPU.

**Huge pages for big tensors.** A training step allocates and frees tensors of 30–90 MB
(e.g. the scan's (48, 512, 900) inputs). glibc serves every request above 32 MB with a
fresh ``mmap``, so each step touched ≈2 GB of new 4 KB pages: 0.4–1.2 M page faults and
1.5–3 s of kernel time per 5 s step (measured, reference config, batch 16, 2 cores).
glibc ≥ 2.35's tunable ``glibc.malloc.hugetlb=1`` makes malloc ask for transparent huge
pages instead, 50× fewer faults: the same step took 4.2 s instead of 5.0–5.6 s. A tunable is
read only at process start, so :func:`reexec_with_hugepages` restarts the process once with
it set. Set ``OVERLAPMAMBA_NO_REEXEC=1`` to opt out.
"""

from __future__ import annotations

import os
import sys

TUNABLE = "glibc.malloc.hugetlb=1"


def reexec_with_hugepages() -> None:
    """Re-run this process (same interpreter and arguments) with the huge-page tunable, unless
    it is set already, opted out of, or not on Linux. Returns only when nothing is done."""
    tunables = os.environ.get("GLIBC_TUNABLES", "")
    if (
        not sys.platform.startswith("linux")
        or "glibc.malloc.hugetlb" in tunables
        or os.environ.get("OVERLAPMAMBA_NO_REEXEC")
    ):
        return
    env = dict(os.environ, GLIBC_TUNABLES=":".join(t for t in (tunables, TUNABLE) if t))
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, [sys.executable, *sys.orig_argv[1:]], env)
