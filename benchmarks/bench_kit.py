"""What the benchmarks share: paths, scans (KITTI 00 when present, else synthetic), a real
server in a temporary data folder (:mod:`overlapmamba.service.process`), and a watch on the CPU use
of other processes, so a noisy run says so."""

from __future__ import annotations

import contextlib
import os
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from reports_kit import CORES, REPORTS, ROOT, provenance, write_report  # noqa: F401 (re-exported)
from rich.console import Console

from overlapmamba.service.process import serve_process

REAL = ROOT.parent / "shared" / "data" / "kitti00_0000-0100"
MODEL = ROOT / "models" / "overlapmamba-hdl64.onnx"

# ---- scans ----------------------------------------------------------------------------------


def synthetic_scan(seed: int, n: int = 120_000) -> np.ndarray:
    """(n, 4) float32 xyzi: a ground plane and a wavy ring of walls around the sensor."""
    rng = np.random.default_rng(seed)
    ng = n // 3
    r = 40 * np.sqrt(rng.uniform(0.01, 1, ng))
    a = rng.uniform(-np.pi, np.pi, ng)
    ground = np.column_stack([r * np.cos(a), r * np.sin(a), rng.normal(-1.73, 0.02, ng)])
    nw = n - ng
    a = rng.uniform(-np.pi, np.pi, nw)
    radius = 15 + 5 * np.sin(3 * a + seed) + rng.normal(0, 0.05, nw)
    walls = np.column_stack([radius * np.cos(a), radius * np.sin(a), rng.uniform(-1.7, 3, nw)])
    xyz = np.concatenate([ground, walls])
    return np.column_stack([xyz, rng.uniform(0, 1, n)]).astype(np.float32)


def scan_bodies(n: int) -> tuple[list[bytes], str]:
    paths = sorted((REAL / "velodyne").glob("*.bin"))[:n]
    if paths:
        pts = len(paths[0].read_bytes()) // 16
        return [p.read_bytes() for p in paths], (
            f"KITTI 00 frames 0–{len(paths) - 1} (frame 0: {pts} points)"
        )
    return [synthetic_scan(i).tobytes() for i in range(n)], "synthetic scans (120k points)"


def _machine_jiffies() -> tuple[int, int]:
    """(total, busy) CPU time of the whole machine from /proc/stat, in clock ticks."""
    values = [int(v) for v in Path("/proc/stat").read_text().split("\n")[0].split()[1:8]]
    return sum(values), sum(values) - values[3] - values[4]  # minus idle and iowait


def _pid_cpu_s(pid: int) -> float:
    """CPU seconds of process ``pid`` and its descendants: its own, its children's that it
    waited for, and those still running (a server's registration processes,
    ``verify.processes``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    ticks = sum(int(f) for f in fields[11:15])  # utime, stime, cutime, cstime
    return ticks / os.sysconf("SC_CLK_TCK") + sum(_pid_cpu_s(c) for c in _children(pid))


def _children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            ppid = int(stat.read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):  # gone meanwhile
            continue
        if ppid == pid:
            out.append(int(stat.parent.name))
    return out


SERVER_CPU_S = [0.0]  # CPU seconds used by the benchmark's servers, added as each one stops


class OtherLoad:
    """The share of the machine's CPU used by *other* processes over a stretch of time:
    machine busy time (/proc/stat) minus this process's and its servers' CPU time. Anything
    above a few percent means the measurements competed with someone else's work. Linux
    only; elsewhere ``fraction()`` is None."""

    def __init__(self) -> None:
        try:
            self.start: tuple[int, int] | None = _machine_jiffies()
        except (OSError, ValueError, IndexError):
            self.start = None
        self.t0 = time.perf_counter()
        self.own0 = time.process_time() + SERVER_CPU_S[0]

    def fraction(self) -> float | None:
        if self.start is None:
            return None
        total, busy = _machine_jiffies()
        hz = os.sysconf("SC_CLK_TCK")
        own = time.process_time() + SERVER_CPU_S[0] - self.own0
        other = (busy - self.start[1]) / hz - own
        return max(0.0, other / max((total - self.start[0]) / hz, 1e-9))


def other_load(console: Console, part: str, watch: OtherLoad, when: str) -> float | None:
    busy = watch.fraction()
    if busy is not None and busy > 0.1:
        console.print(
            f"[yellow]warning:[/] {when} the {part} part, other processes used {100 * busy:.0f}% "
            "of the machine's CPU: these numbers are noisy; rerun when the machine is quiet"
        )
    return busy


# ---- servers --------------------------------------------------------------------------------


@contextlib.contextmanager
def server(
    env_extra: dict[str, str], startup_s: float = 180.0, model: Path = MODEL
) -> Iterator[str]:
    """A real ``overlapmamba serve`` of ``model`` on a free port with a temporary data folder,
    configured by ``env_extra`` only (not by this process's OVERLAPMAMBA_* variables); its
    base URL once /readyz answers 200. Its CPU time is added to SERVER_CPU_S as it stops."""
    with tempfile.TemporaryDirectory(prefix="om-bench-") as tmp:
        data = Path(tmp) / "data"
        with serve_process(
            data,
            model=model,
            env=env_extra,
            inherit_settings=False,
            log_path=Path(tmp) / "server.log",
            startup_s=startup_s,
            cwd=ROOT,
        ) as srv:
            try:
                yield srv.url
            finally:
                with contextlib.suppress(OSError, ValueError, IndexError):
                    SERVER_CPU_S[0] += _pid_cpu_s(srv.proc.pid)


def fleet_command(
    url: str,
    out: Path,
    *,
    robots: int,
    sequence: Path,
    rate: float,
    duration: float,
    scans: int | None = None,
) -> list[str]:
    """``overlapmamba-client simulate-fleet`` against ``url`` into map ``fleet``: its report
    to ``out`` and its latency plot beside it (``out`` as .png)."""
    import sys

    cmd = [str(Path(sys.executable).parent / "overlapmamba-client"), "simulate-fleet"]
    cmd += ["--robots", str(robots), "--sequence", str(sequence)]
    cmd += ["--duration", str(duration), "--rate", str(rate)]
    if scans is not None:
        cmd += ["--scans", str(scans)]
    cmd += ["--map", "fleet", "--url", url, "--out", str(out)]
    return [*cmd, "--plot", str(out.with_suffix(".png"))]


# ---- a model's calibration ------------------------------------------------------------------


class AlignCounter:
    """``small_gicp.align`` as ``overlapmamba.service.registration`` calls it, counted
    while the context is open (each call is one GICP run)."""

    def __init__(self) -> None:
        from overlapmamba.service import registration

        self._module = registration.small_gicp
        self._align = self._module.align
        self.calls = 0

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        self.calls += 1
        return self._align(*args, **kwargs)

    def __enter__(self) -> AlignCounter:
        self._module.align = self
        return self

    def __exit__(self, *exc: object) -> None:
        self._module.align = self._align


def served_settings(meta: Any) -> Any:
    """The settings the service answers with for a model of metadata ``meta``: its file's
    calibration where it has one, else the defaults (or OVERLAPMAMBA_* variables), as
    ``overlapmamba.service.calibration.resolve`` decides at start-up."""
    from overlapmamba.service.calibration import resolve
    from overlapmamba.service.settings import Settings

    return resolve(Settings(), meta)[0]


def served_rerank(meta: Any, text: str | None = None) -> Any:
    """The second stage the service runs for a model of metadata ``meta``
    (``overlapmamba.service.ranking.rerank_params`` of :func:`served_settings`); ``text``
    (``K,WEIGHT`` or ``off``) in place of its shortlist and weight, its score as served."""
    from dataclasses import replace

    from overlapmamba.core.rerank import Rerank
    from overlapmamba.service.ranking import rerank_params

    served = rerank_params(served_settings(meta).rerank, meta)
    if text is None:
        return served
    asked = Rerank.parse(text)
    return replace(asked, part=served.part) if asked.on else asked


def model_record(path: Path, enc: Any) -> dict[str, Any]:
    """What a report says of the model file it measured (an ``Encoder``): where it lies,
    its model id, the views, column phase and sensor input it is served with, and its first
    stage (``overlapmamba.core.yaw_spectrum``; ``descriptor`` for the network's own)."""
    from reports_kit import shown_path

    return {
        "model": shown_path(path),
        "model_id": enc.model_id,
        "views": enc.meta.views,
        "column_phase": enc.meta.column_phase,
        "sensor_input": enc.meta.sensor_input,
        "first_stage": enc.meta.first_stage,
    }


def served_input(enc: Any, sensor: str | None) -> Any:
    """The ``SensorInput`` the service gives a scan that names ``sensor`` (``None``: the
    file's own sensor), for the model ``enc`` serves: the file's own input mode, its sensor
    map applied where it carries one (``overlapmamba.service.sensors.Sensors``)."""
    from overlapmamba.service.sensors import Sensors

    sensors = Sensors(enc.meta)
    return sensors.input(sensors.resolve(sensor))


def write_calibration(model: Path, section: str, values: dict[str, Any], data: str) -> None:
    """Record thresholds this benchmark chose in the model file itself
    (``overlapmamba.core.calibration``): the service takes them from there."""
    from overlapmamba.core.calibration import calibrated
    from overlapmamba.train.modelfile import read_metadata, with_calibration

    data = data.replace(f"{ROOT}/", "")  # paths inside the checkout, as a clone has them
    entry = calibrated(section, values, chosen_by=str(provenance()["command"]), data=data)
    check_section(section, values)
    meta = read_metadata(model)
    # as the service will read it, before the file changes: a value it refuses is not written
    served_settings(meta.model_copy(update={"calibration": {**meta.calibration, section: entry}}))
    with_calibration(model, section, entry)
    print(f"{model}: calibration {section} = {values}")


def check_section(section: str, values: dict[str, Any]) -> None:
    """``values`` as the service's settings section ``section`` takes them, whatever this
    process's OVERLAPMAMBA_* variables set (a variable's value would hide the file's from
    ``served_settings``): ValueError naming the first value refused."""
    from pydantic import ValidationError

    from overlapmamba.service.settings import Settings

    kind = Settings.model_fields[section].annotation
    try:
        kind.model_validate(values)  # type: ignore[union-attr]
    except ValidationError as err:
        first = err.errors()[0]
        raise ValueError(
            f"the calibration of {section} is not valid ({first['loc']}: {first['msg']})"
        ) from None


def pct(ms: list[float] | np.ndarray, q: float) -> float:
    return float(np.percentile(np.asarray(ms, dtype=np.float64), q)) if len(ms) else float("nan")


def refuse_aligned(model: Path, why: str) -> None:
    """Stop with the reason when ``model`` aligns its columns (``column_phase`` aligned,
    ``overlapmamba.core.views``) and the benchmark would project its scans another way."""
    from overlapmamba.train.modelfile import read_metadata

    if read_metadata(model).aligned:
        raise SystemExit(
            f"{model} aligns each scan's columns (column_phase aligned); {why}: give the file "
            "with the sensor's columns (overlapmamba export FILE --column-phase sensor)"
        )


@dataclass(frozen=True)
class CarRendering:
    """A model as one view and the model sensor's car rendering of one split: its loop table
    (``gt``, labelling every rendering of the drive: frame i is the same place in each) and
    its descriptors (``d_car``)."""

    model: Any
    profile: Any
    car: Any
    gt: Any
    d_car: np.ndarray


@contextlib.contextmanager
def car_rendering(model_path: Path, data: Path, split: str) -> Iterator[CarRendering]:
    """:class:`CarRendering` of ``split`` (``make data-sensors``), the model a temporary
    one-view copy of ``model_path`` (a scan as one view, before any views). Refuses an
    aligned file: the renderings' benchmarks project with the sensor's columns."""
    from overlapmamba.core.datasets import open_sequence
    from overlapmamba.train.checkpoint import load_model
    from overlapmamba.train.evaluate import describe, sequence_loops
    from overlapmamba.train.modelfile import with_views
    from overlapmamba.train.rangecache import range_images

    car_path = data / f"{split}-kitti-hdl64"
    if not car_path.is_dir():
        raise SystemExit(f"{car_path} is missing: run `make data-sensors`")
    refuse_aligned(model_path, "this benchmark projects scans with the sensor's columns")
    with tempfile.TemporaryDirectory() as tmp:
        one = Path(tmp) / "one-view.onnx"
        with_views(model_path, one, 1)
        model, profile, _ = load_model(one)
        car = open_sequence(car_path)
        d_car, _ = describe(model, range_images(car, profile, progress=False))
        yield CarRendering(model, profile, car, sequence_loops(car), d_car)
