"""A real `overlapmamba serve` process keeps its memory flat while it encodes: the service
runs for weeks, so whatever one scan allocates must be given back (the selective-scan
kernel once kept ≈ 0.5 MB a ring scan per call, ≈ 4 GB an hour at a fleet's rate)."""

from __future__ import annotations

import os
from pathlib import Path

import httpx
import pytest
from service_kit import OCTET, scan, server

pytestmark = pytest.mark.slow


def _resident_mb(pid: int) -> float:
    pages = int(Path(f"/proc/{pid}/statm").read_text().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / 1e6


@pytest.mark.skipif(not Path("/proc/self/statm").exists(), reason="reads Linux's /proc")
def test_a_real_server_encoding_scan_after_scan_keeps_its_memory_flat(tmp_path):
    bodies = [scan(i).tobytes() for i in range(4)]
    with server(tmp_path / "data") as (url, proc), httpx.Client(base_url=url, timeout=60) as c:

        def describe(n: int) -> None:
            for i in range(n):
                r = c.post("/v1/descriptors", content=bodies[i % 4], headers=OCTET)
                assert r.status_code == 200, r.text

        describe(40)  # the allocators' and the runtime's first blocks
        before = _resident_mb(proc.pid)
        describe(160)
        grown = _resident_mb(proc.pid) - before
        scan_path = c.get("/readyz").json()["detail"]["scan"]
    assert grown < 30.0, f"the server grew {grown:.0f} MB over 160 scans (scan path {scan_path})"
