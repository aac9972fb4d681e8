"""A real `overlapmamba serve` process keeps its memory flat while it answers: the service
runs for weeks, so whatever one scan allocates must be given back (the selective-scan
kernel once kept ≈ 0.5 MB a ring scan per call, gigabytes an hour at a fleet's rate). Two
paths are run scan after scan: encoding alone, and a scan query whose candidates are
registered against their keyframes' geometry (small_gicp)."""

from __future__ import annotations

import httpx
import pytest
from conftest import PROC_STATM, resident_bytes
from service_kit import OCTET, scan, server

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not PROC_STATM, reason="reads Linux's /proc"),
]
GROWTH_MB = 30.0  # over a phase's requests, after its warm-up


def test_a_real_server_answering_scan_after_scan_keeps_its_memory_flat(tmp_path):
    bodies = [scan(i).tobytes() for i in range(4)]
    turned = [scan(i, yaw_deg=25.0 * (i + 1)).tobytes() for i in range(4)]
    with server(tmp_path / "data") as (url, proc), httpx.Client(base_url=url, timeout=60) as c:
        scan_path = c.get("/readyz").json()["detail"]["scan"]

        def grown(send, warm: int, n: int) -> float:
            for i in range(warm):  # the allocators' and the runtime's first blocks
                send(i)
            before = resident_bytes(proc.pid) / 1e6
            for i in range(n):
                send(i)
            return resident_bytes(proc.pid) / 1e6 - before

        def describe(i: int) -> None:
            r = c.post("/v1/descriptors", content=bodies[i % 4], headers=OCTET)
            assert r.status_code == 200, r.text

        encoding = grown(describe, 40, 160)
        assert encoding < GROWTH_MB, f"encoding grew {encoding:.0f} MB (scan path {scan_path})"

        assert c.put("/v1/maps/town").status_code == 201
        for i, body in enumerate(bodies):
            params = {"keyframe_id": f"k{i}", "timestamp": 100.0 + i, "robot_id": "r1"}
            r = c.post("/v1/maps/town/keyframes", params=params, content=body, headers=OCTET)
            assert r.status_code == 201, r.text
        checked: list[bool | None] = []

        def query(i: int) -> None:
            r = c.post("/v1/maps/town/query", params={"k": 3}, content=turned[i % 4], headers=OCTET)
            assert r.status_code == 200, r.text
            checked.append(r.json()["matches"][0]["verification"]["verified"])

        verifying = grown(query, 20, 120)
        assert all(checked), "each turned keyframe should verify against itself"
        assert verifying < GROWTH_MB, f"verified queries grew {verifying:.0f} MB"
