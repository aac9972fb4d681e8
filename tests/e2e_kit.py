"""Shared by the end-to-end tests (``tests/test_e2e_*.py``): the size switch, the report
writer, and the background clients that make the load "mixed".

Sizes. ``make test`` runs each end-to-end test small (seconds). ``make e2e`` sets
``OVERLAPMAMBA_E2E=full``, which runs the sizes the issue asks for (8 robots for 60 s, 10
crashes, every fuzz case at full strength) and writes the figures to ``reports/e2e/``.
Small runs write to ``bench-results/e2e/``, so a quick run never overwrites the published
numbers.
"""

from __future__ import annotations

import json
import os
import platform
import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
FULL = os.environ.get("OVERLAPMAMBA_E2E") == "full"
OUT = ROOT / ("reports" if FULL else "bench-results") / "e2e"
KITTI = ROOT.parent / "shared" / "data" / "kitti00_0000-0100"
SYNTH_VAL = ROOT / "data" / "synth" / "val"
# The full run's drive: a town no threshold was calibrated on (the thresholds were chosen on
# val), so its closure precision and recall are evidence; OVERLAPMAMBA_E2E_DRIVE names another.
HELD_OUT = Path(os.environ.get("OVERLAPMAMBA_E2E_DRIVE") or ROOT / "data" / "synth" / "test")
# The full run's bars on that town: verified closures precision ≥ 0.95, recall ≥ 0.5 (a floor
# under load: a query has a loop once its keyframe was acknowledged, before the map settles)
PRECISION_BAR, RECALL_BAR = 0.95, 0.5


def size(small: Any, full: Any) -> Any:
    return full if FULL else small


def cpu_name() -> str:
    """The processor's name with its family and model numbers, which a cloud machine's
    generic name leaves out: the scan kernel's cost depends on them."""
    from overlapmamba.core.scan_kernel import processor

    p = processor()
    family = f" (family {p['cpu family']} model {p['model']})" if "model" in p else ""
    return f"{p['name']}{family}"


def write_report(name: str, body: dict[str, Any]) -> Path:
    OUT.mkdir(parents=True, exist_ok=True)
    body = {
        "mode": "full" if FULL else "quick",
        "machine": {"platform": platform.platform(), "cores": os.cpu_count(), "cpu": cpu_name()},
        "when": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        **body,
    }
    path = OUT / f"{name}.json"
    path.write_text(json.dumps(body, indent=2, default=float))
    return path


def drive_dir() -> Path:
    """A recorded drive for the robots. Full: the held-out test town (`make data`), whose
    loops the thresholds never saw. Small: the real KITTI 00 frames from ../shared/data, else
    the synthetic validation town."""
    if FULL:  # the evidence run must not pass by skipping, nor on the calibration town
        if (HELD_OUT / "manifest.json").is_file():
            return HELD_OUT
        pytest.fail(f"no drive: {HELD_OUT} is not made (make e2e makes it; make data too)")
    if KITTI.is_dir():
        return KITTI
    if (SYNTH_VAL / "manifest.json").is_file():
        return SYNTH_VAL
    pytest.skip("no drive: ../shared/data (KITTI 00) is absent and data/synth/val not made")


def unit(rng: np.random.Generator, dim: int = 256) -> list[float]:
    v = rng.normal(size=dim)
    return (v / np.linalg.norm(v)).tolist()


@dataclass
class Worker:
    """A background client loop; counts requests and errors, keeps what was acknowledged."""

    url: str
    headers: dict[str, str] = field(default_factory=dict)
    requests: int = 0
    errors: list[str] = field(default_factory=list)
    acked: dict[str, list[float]] = field(default_factory=dict)
    latencies_ms: list[float] = field(default_factory=list)
    _stop: threading.Event = field(default_factory=threading.Event)
    _thread: threading.Thread | None = None

    def start(self) -> Worker:
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(60)

    def _run(self) -> None:
        with httpx.Client(base_url=self.url, headers=self.headers, timeout=60) as c:
            while not self._stop.is_set():
                t0 = time.perf_counter()
                try:
                    self.step(c)
                except Exception as err:  # anything, recorded: a dead worker must show
                    if isinstance(err, httpx.TransportError):
                        if self._stop.is_set():
                            return
                        self.errors.append(f"transport: {type(err).__name__}: {err}")
                    else:
                        self.errors.append(f"{type(err).__name__}: {err}")
                self.requests += 1
                self.latencies_ms.append((time.perf_counter() - t0) * 1e3)
                self._stop.wait(self.pause_s)

    pause_s: float = 0.2

    def step(self, c: httpx.Client) -> None:
        raise NotImplementedError


@dataclass
class Mapper(Worker):
    """A map-building job: batches of descriptors into ``map_id``, each batch acknowledged
    before the next (the acknowledged ids are what must survive anything)."""

    map_id: str = "built"
    model_id: str = ""
    dim: int = 256  # the served model's descriptor length
    batch: int = 5
    seed: int = 0
    _n: int = 0

    def step(self, c: httpx.Client) -> None:
        rng = np.random.default_rng(self.seed + self._n)
        rows = []
        for _ in range(self.batch):
            rows.append(
                {
                    "keyframe_id": f"m{self.seed}-{self._n}",
                    "timestamp": float(self._n),
                    "robot_id": "mapper",
                    "session_id": "build",
                    "descriptor": unit(rng, self.dim),
                }
            )
            self._n += 1
        r = c.post(
            f"/v1/maps/{self.map_id}/keyframes:batch",
            json={"model_id": self.model_id, "keyframes": rows},
        )
        if r.status_code == 200:
            for row in rows:
                self.acked[row["keyframe_id"]] = row["descriptor"]
        else:
            self.errors.append(f"{r.status_code}: {r.text[:200]}")


@dataclass
class Poller(Worker):
    """An ops dashboard: statistics and metrics once a second."""

    pause_s: float = 1.0

    def step(self, c: httpx.Client) -> None:
        for path in ("/v1/stats", "/metrics"):
            r = c.get(path)
            if r.status_code != 200:
                self.errors.append(f"{path} {r.status_code}: {r.text[:200]}")


def missing_keyframes(c: httpx.Client, map_id: str, ids: list[str]) -> list[str]:
    return [k for k in ids if c.get(f"/v1/maps/{map_id}/keyframes/{k}").status_code != 200]


def metrics(c: httpx.Client) -> dict[str, float]:
    """The server's own ``/metrics``: each unlabelled series' value by name."""
    r = c.get("/metrics")
    r.raise_for_status()
    return {m[1]: float(m[2]) for m in re.finditer(r"^([a-z_]+) (\S+)$", r.text, re.M)}


def resident_mb(c: httpx.Client) -> tuple[float | None, float | None]:
    """The server's resident memory (MB) as its ``/metrics`` says, in one scrape: its own
    process's (``process_resident_memory_bytes``) and its registration processes' together
    (``overlapmamba_registration_resident_bytes``), which the first leaves out; None where
    the platform has no such series."""
    got = metrics(c)
    own = got.get("process_resident_memory_bytes")
    children = got.get("overlapmamba_registration_resident_bytes")
    return (
        own / 1e6 if own is not None else None,
        children / 1e6 if children is not None else None,
    )


@dataclass
class CpuMeter:
    """Where the CPU went during a run, in cores (CPU seconds a second): the server's own
    process, its registration processes, this process's (the fleet, the mapper and the
    dashboard), the whole machine's busy time, and the rest of it (anything else).
    A server using well under the cores the machine has left idle is bound by something else
    than CPU, e.g. Python's lock held by a native call; a machine busy on every core is
    bound by CPU."""

    c: httpx.Client
    t0: float = 0.0
    server0: dict[str, float] = field(default_factory=dict)
    own0: float = 0.0
    busy0: tuple[float, float] | None = None

    def start(self) -> CpuMeter:
        self.t0, self.server0 = time.monotonic(), metrics(self.c)
        self.own0, self.busy0 = time.process_time(), machine_busy()
        return self

    def cores(self) -> dict[str, Any]:
        wall = time.monotonic() - self.t0
        server, own, busy = metrics(self.c), time.process_time(), machine_busy()

        def rate(series: str) -> float | None:
            if series not in server or series not in self.server0:
                return None
            return (server[series] - self.server0[series]) / wall

        out: dict[str, Any] = {"machine_cores": os.cpu_count(), "wall_s": wall}
        out["server_cores"] = rate("process_cpu_seconds_total")
        out["registration_cores"] = rate("overlapmamba_registration_cpu_seconds_total")
        out["load_cores"] = (own - self.own0) / wall  # the fleet, mapper and dashboard
        out["machine_busy_cores"] = None
        if busy is not None and self.busy0 is not None:
            (t0, b0), (t1, b1) = self.busy0, busy
            out["machine_busy_cores"] = (b1 - b0) / (t1 - t0) * (os.cpu_count() or 1)
        parts = [out[k] for k in ("machine_busy_cores", "server_cores", "load_cores")]
        out["other_cores"] = (
            parts[0] - sum(parts[1:]) - (out["registration_cores"] or 0.0)
            if None not in parts
            else None
        )
        return out


def machine_busy() -> tuple[float, float] | None:
    """(total, busy) clock ticks of every core together, as the benchmarks read them
    (``bench_kit._machine_jiffies``, ``/proc/stat``; None elsewhere)."""
    from conftest import benchmark_module

    try:
        return benchmark_module("bench_kit")._machine_jiffies()
    except (OSError, ValueError, IndexError):
        return None


def percentiles(values: list[float]) -> dict[str, float]:
    if not values:
        return {"p50": 0.0, "p95": 0.0, "p99": 0.0}
    a = np.asarray(values)
    return {f"p{q}": float(np.percentile(a, q)) for q in (50, 95, 99)}
