"""End to end, load: a real server on loopback; a fleet of robots streaming ``observe``, a
map-building job inserting descriptors and a dashboard polling statistics, all at once.
Zero errors, and afterwards every acknowledged write is there.

Quick (``make test``): 2 robots for 8 s. Full (``make e2e``): 8 robots asked for 10 Hz, 250
scans each (``SCANS``), the run bounded at 300 s: every machine's robots cover the same
stretches of the drive, so the closures' recall compares across machines and files (in a
fixed 60 s, as before 2026-12-02, a slower server's robots got less far, where the loops
differ: the recall floor tested the machine's speed as well, benchmarks/fleet_reach.py).
``OVERLAPMAMBA_E2E_MODEL=FILE`` serves another model file (a twin of the shipped one); its
report is then ``reports/e2e/load-STEM.json`` beside the shipped file's ``load.json``.
"""

from __future__ import annotations

import asyncio
import os
import time
from pathlib import Path

import httpx
import pytest
from e2e_kit import (
    FULL,
    PRECISION_BAR,
    RECALL_BAR,
    CpuMeter,
    Mapper,
    Poller,
    drive_dir,
    missing_keyframes,
    percentiles,
    resident_mb,
    size,
    write_report,
)
from service_kit import MODEL, server

from overlapmamba.client import NO_RETRY
from overlapmamba.client._replay import open_drive
from overlapmamba.client.fleet import simulate
from overlapmamba.service.calibration import read_model_metadata

pytestmark = pytest.mark.e2e


# Each robot's scans in the full run: what 8 robots covered in 60 s at about 34 observations
# a second, the one-pass file's runs of 2026-12-02 (reports/e2e/load-*.json before this).
SCANS = 250


@pytest.mark.timeout(900)
def test_fleet_mapper_and_dashboard_together(tmp_path):
    robots, duration, scans = size(2, 8), size(8.0, 300.0), size(None, SCANS)
    drive = open_drive(drive_dir())
    env: dict[str, str] = {}  # the defaults: micro-batching on (docs/deploy.md, sizing)
    model = Path(os.environ.get("OVERLAPMAMBA_E2E_MODEL") or MODEL)
    if not model.is_file():
        pytest.fail(f"OVERLAPMAMBA_E2E_MODEL={model} is not a file")
    name = "load" if model.resolve() == MODEL.resolve() else f"load-{model.stem}"
    # the served check's cost, measured beside the file's own margin: e.g. "off"
    margin = os.environ.get("OVERLAPMAMBA_VERIFY__AMBIGUITY_MARGIN")
    if margin:
        name += f"-margin-{margin}"
    # registration in the server's threads (0) or in more children than the default's one
    processes = os.environ.get("OVERLAPMAMBA_VERIFY__PROCESSES")
    if processes:
        name += f"-processes-{processes}"
    with (
        server(tmp_path / "data", env, model) as (url, _),
        httpx.Client(base_url=url, timeout=60) as c,
    ):
        ready = c.get("/readyz").json()["detail"]
        model_id = ready["model_id"]
        served_margin = ready["thresholds"]["verify.ambiguity_margin"]
        assert c.put("/v1/maps/built").status_code == 201
        resident_ready, children_ready = resident_mb(c)
        dim = read_model_metadata(model).descriptor_dim  # e.g. 768 for a first stage's
        mapper = Mapper(url, model_id=model_id, dim=dim).start()
        poller = Poller(url).start()
        meter = CpuMeter(c).start()
        t0 = time.monotonic()
        # No retries: an overload (503) or a timeout counts as an error, not a slow success.
        report, samples = asyncio.run(
            simulate(
                url,
                "fleet",
                [drive],
                robots=robots,
                duration_s=duration,
                rate_hz=10.0,
                retry=NO_RETRY,
                scans=scans,
            )
        )
        elapsed = time.monotonic() - t0
        cpu = meter.cores()
        assert mapper.alive and poller.alive, (mapper.errors[-3:], poller.errors[-3:])
        mapper.stop()
        poller.stop()

        # every acknowledged write is there, and the index agrees with the store
        fleet_ids = [s.inserted for s in samples if s.inserted]
        missing = missing_keyframes(c, "fleet", fleet_ids)
        missing += missing_keyframes(c, "built", list(mapper.acked))
        maps = {m["map_id"]: m for m in c.get("/v1/maps").json()["maps"]}
        stats = c.get("/v1/stats").json()
        resident_after, children_after = resident_mb(c)

    errors = sum(report.errors.values()) + len(mapper.errors) + len(poller.errors)
    body = {
        "command": "make e2e (tests/test_e2e_load.py)"
        if name == "load"
        else (f"OVERLAPMAMBA_VERIFY__AMBIGUITY_MARGIN={margin} " if margin else "")
        + (f"OVERLAPMAMBA_VERIFY__PROCESSES={processes} " if processes else "")
        + f"OVERLAPMAMBA_E2E=full OVERLAPMAMBA_E2E_MODEL={model} "
        "python -m pytest -m e2e tests/test_e2e_load.py",
        "verify_ambiguity_margin": served_margin,  # value and source, as /readyz says
        "registration_processes": ready["registration_processes"],  # 0: the server's threads
        "model": report.server,  # the service's model id, views and scan path (its /readyz)
        "drive": drive.name,
        "robots": robots,
        "rate_hz_asked": 10.0,
        "scans_per_robot": scans,  # None: as many as the duration let (the quick run)
        "rate_hz_achieved_per_robot": report.throughput_per_s / robots,
        "retries": "none (NO_RETRY): every 429/503/timeout would count as an error",
        "duration_s": elapsed,
        "fleet": {
            "observations": report.observations,
            "throughput_per_s": report.throughput_per_s,
            "latency_ms": report.latency_ms,
            "errors": report.errors,
            "keyframes_inserted": len(fleet_ids),
            "loop_closures": report.loop_closures,
            "verified_closures": report.verified_closures,
            "closure_precision": report.precision,
            "closure_recall": report.recall,
            "bars": {"precision": PRECISION_BAR, "recall": RECALL_BAR, "asserted": FULL},
            "pose_error": report.pose_error,
            "covariance": report.covariance,
        },
        "mapper": {
            "batches": mapper.requests,
            "keyframes_acknowledged": len(mapper.acked),
            "latency_ms": percentiles(mapper.latencies_ms),
            "errors": mapper.errors[:5],
        },
        "dashboard": {
            "polls": poller.requests,
            "latency_ms": percentiles(poller.latencies_ms),
            "errors": poller.errors[:5],
        },
        "errors_total": errors,
        "acknowledged_missing": len(missing),
        "index_equals_store": {k: m["index"]["vectors"] == m["keyframes"] for k, m in maps.items()},
        "server_encode_ms": stats["latency_ms"].get("encode"),
        # every stage's time and the verify stage's work (registrations, ambiguous refusals),
        # as /v1/stats gives them: what a throughput difference between two runs came from
        "server_stages_ms": stats["latency_ms"],
        "server_verification": stats.get("verification"),
        # where the CPU went during the load, in cores: the server's, this process's (fleet,
        # mapper, dashboard) and the machine's; a server short of the idle cores is not CPU-bound
        "cpu": cpu,
        # the server's own /metrics (process_resident_memory_bytes): ready, and after the load
        "server_resident_mb": {"ready": resident_ready, "after": resident_after},
        # its registration processes' together (verify.processes), which that leaves out
        "registration_resident_mb": {"ready": children_ready, "after": children_after},
    }
    path = write_report(name, body)
    # every robot got through its scans before the bound: the stretches the recall compares
    done = {r: v["observations"] for r, v in report.per_robot.items()}
    assert scans is None or set(done.values()) == {scans}, f"robots' scans {done}, {scans} asked"
    assert errors == 0, (report.errors, mapper.errors[:3], poller.errors[:3], path)
    assert not missing, missing[:10]
    assert all(body["index_equals_store"].values()), maps
    assert report.observations > 0 and mapper.acked and poller.requests > 0
    if FULL:  # on a town the thresholds never saw (e2e_kit.HELD_OUT)
        assert report.precision is not None and report.recall is not None, (
            f"{drive.name} has no loop ground truth: the bars cannot be checked"
        )
        assert report.precision >= PRECISION_BAR, (report.precision, path)
        assert report.recall >= RECALL_BAR, (report.recall, path)
