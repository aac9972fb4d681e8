"""An experiment across sensors, with the shipped weights and no training: every sensor's
scan, the model sensor's too, thinned to the beams nearest a common set of elevations before
it enters the network, against each sensor's scan projected as the service projects it today.

    elevation   the service today (``overlapmamba.core.sensors.input``, ``elevation`` mode;
                the model sensor's scans native)
    common      the ``common`` mode (``overlapmamba.core.sensors.input``): of each sensor,
                only the beam nearest each of the VLP-16's 16 elevations (−15° … +15°, 2°
                apart: the sparsest spinning sensor of the catalogue), when that beam lies
                within 0.5° of it; a point's beam is the nearest elevation of its sensor's
                table; the points kept are projected as a VLP-16's scan would be. Every
                sensor's image then shows the same rings at the same rows

Why it might pay: the network reads rows 0–26 of its 64 (``benchmarks/receptive_rows.py``),
+2.8° … −8.6°, where a VLP-16 has 7 beams, an XT32 13 and an HDL-64E 26. What differs
between two sensors' images of one place is mostly that vertical sampling.

AR@1/5/20 (a hit within 5 m, ``overlapmamba.train.sessions.descriptor_recall``, the
descriptor alone) of a second drive by one sensor queried against the first drive's map by
another, on

- ``val``: calibration town ``cal-x00`` (``overlapmamba.synth.presets.calibration_town``,
  split val), 500 scans a drive, sessions 0 and 1. The common set and its tolerance were
  chosen here (against a window of elevations, which lost);
- ``test``: the sensor test town's presets (``test-kitti-hdl64``, ``test-os1-128`` and the
  ``test-s1-…`` second drives), as ``benchmarks/sensors.py`` pairs them.

Drives are generated into ``--scratch`` without overlap tables (or read from ``--data``
where a preset's folder exists there) and kept for a rerun.

    python benchmarks/common_beams.py [--model models/overlapmamba-hdl64.onnx] [--out …]

A file that takes every scan its own way (``sensor_input`` ``common``, ``structure``,
``bev`` or ``bev-soft``: trained on them, e.g. the ``common-towns``, ``structure-towns``,
``bev-towns`` and ``bev-soft-pilot`` presets) is measured its own way
only (``--out`` names its report). Writes reports/model/common-beams.json. ≈ 30 min on 2
cores with the three-view file, most of it describing.
"""

from __future__ import annotations

import argparse
import fcntl
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
from reports_kit import REPORTS, ROOT, write_report
from rich.console import Console

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.sensors.catalogue import CATALOGUE
from overlapmamba.core.sensors.input import (
    ALL_SCANS_MODES,
    COMMON_SENSOR,
    COMMON_TOLERANCE_DEG,
    SensorInput,
    common_beams,
)
from overlapmamba.service.encoder import Encoder
from overlapmamba.train.sessions import check_sessions, descriptor_recall, town_positions

QUERIES = ("kitti-hdl64", "vlp16", "os0-128", "xt32", "os1-128")
MAPS = ("kitti-hdl64", "os1-128")
WAYS = ("elevation", "common")


def describe(enc: Encoder, town: Path, way: str) -> tuple[np.ndarray, np.ndarray]:
    """The town's descriptors (the network's own: the shipped file carries no sensor maps)
    and positions, the town's sensor's scans taken by ``way`` (``elevation``: as the service
    projects them today, the model sensor's natively)."""
    seq = open_sequence(town)
    sensor = CATALOGUE[seq.sensor or enc.meta.profile.name]
    clouds = (seq.points(i) for i in range(len(seq)))
    sensor_input = SensorInput(enc.meta.profile, sensor, way)  # type: ignore[arg-type]
    desc, _ = enc.describe(clouds, sensor_input, mapped=False)
    return desc, town_positions(seq)


def drive(scratch: Path, data: Path, name: str, cfg_of: Any) -> Path:
    """The drive ``name``: ``data/name`` when it is there, else generated into scratch.

    Runs that need the same drive at once (``verify_across.py``, ``verify_threshold.py
    --across``, ``across_pairs.py`` …) generate it once: each takes a lock beside it
    (``scratch/.name.lock``) before looking again, so a second run waits and reads what the
    first wrote instead of removing its half-written folder as an interrupted one."""
    from overlapmamba.synth.generate import generate

    for root in (data, scratch):
        if (root / name / "manifest.json").is_file():
            return root / name
    out = scratch / name
    scratch.mkdir(parents=True, exist_ok=True)
    with open(scratch / f".{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes, or its process dies
        if (out / "manifest.json").is_file():  # made by a run that held the lock before
            return out
        if out.exists():  # an interrupted generation: nobody else holds the lock
            shutil.rmtree(out)
        generate(out, cfg_of(), workers=2, progress=False, ground_truth=False)
    return out


def drive_arguments(ap: argparse.ArgumentParser, out: Path) -> None:
    """The arguments of a benchmark over these drives: the model file, where presets are
    read (``--data``) and generated (``--scratch``), a val drive's length, the report."""
    ap.add_argument("--model", type=Path, default=ROOT / "models" / "overlapmamba-hdl64.onnx")
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "synth")
    ap.add_argument("--scratch", type=Path, default=ROOT / "data" / "common-beams")
    ap.add_argument("--frames", type=int, default=500, help="scans a val drive")
    ap.add_argument("--out", type=Path, default=out)


def pairs(
    enc: Encoder, towns: dict[tuple[str, int], Path], ways: tuple[str, ...], console: Console
) -> list[dict[str, Any]]:
    rows = []
    cache: dict[tuple[Path, str], tuple[np.ndarray, np.ndarray]] = {}

    def get(town: Path, way: str) -> tuple[np.ndarray, np.ndarray]:
        if (town, way) not in cache:
            cache[(town, way)] = describe(enc, town, way)
        return cache[(town, way)]

    for m in MAPS:
        for q in QUERIES:
            db_town, q_town = towns[(m, 0)], towns[(q, 1)]
            check_sessions(open_sequence(db_town), open_sequence(q_town))
            row: dict[str, Any] = {"queries": q, "map": m}
            for way in ways:
                db, pdb = get(db_town, way)
                qd, pq = get(q_town, way)
                r = descriptor_recall(db, pdb, qd, pq)
                row[way] = {k: r[k] for k in ("ar@1", "ar@5", "ar@20")}
            console.print(row)
            rows.append(row)
    return rows


def main() -> None:
    from overlapmamba.synth.presets import calibration_town, preset

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    drive_arguments(ap, REPORTS / "model" / "common-beams.json")
    args = ap.parse_args()
    console = Console(width=120)
    t0 = time.perf_counter()
    enc = Encoder(args.model)
    # a file trained on common beams takes nothing else (its elevation images mean nothing)
    own = enc.meta.sensor_input
    ways = (own,) if own in ALL_SCANS_MODES else WAYS
    sensors = sorted(set(QUERIES) | set(MAPS))
    val: dict[tuple[str, int], Path] = {}
    test: dict[tuple[str, int], Path] = {}
    for s in sensors:
        for session in (0, 1):
            cfg = calibration_town(0, s, args.frames).model_copy(update={"session": session})
            val[(s, session)] = drive(
                args.scratch, args.data, f"cal-x00-s{session}-{s}", lambda c=cfg: c
            )
    for s in MAPS:
        test[(s, 0)] = drive(args.scratch, args.data, f"test-{s}", lambda s=s: preset(f"test-{s}"))
    for s in QUERIES:
        test[(s, 1)] = drive(
            args.scratch, args.data, f"test-s1-{s}", lambda s=s: preset(f"test-s1-{s}")
        )
    console.print(f"drives ready in {time.perf_counter() - t0:.0f} s")
    record = {
        "model_id": enc.model_id,
        "views": enc.meta.views,
        "sensor_input": enc.meta.sensor_input,
        # what the file says of its own training and selection (its metadata, from the run)
        "file_metrics": enc.meta.metrics,
        "training_data": enc.meta.training_data,
        "common": {
            "elevations_of": COMMON_SENSOR,
            "tolerance_deg": COMMON_TOLERANCE_DEG,
            "beams_kept": {s: int(common_beams(CATALOGUE[s]).size) for s in sensors},
        },
        "val": pairs(enc, val, ways, console),
        "test": pairs(enc, test, ways, console),
    }
    record["seconds"] = time.perf_counter() - t0
    write_report(args.out, record)
    console.print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
