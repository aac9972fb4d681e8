"""Range-projection speed: median and p90 over repeated runs on a ~125k-point scan.

Uses a real KITTI scan when ../shared/data is present (padded to 125k points), else a seeded
synthetic one. Prints a table and writes JSON (default reports/service/projection.json).
Goal: median ≤ 3 ms for 125k points with the kitti-hdl64 profile. Also the model's input as
the service makes it for a scan (``service_input``): the shipped model's sub-column views,
for its own sensor (native) and for other sensors' (by the shipped file's input and by
``elevation-lerp``), on the same points. And decoding before any of it: a raw xyzi body →
PointCloud, and its copy of xyz and intensity out of the rows made two ways.
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np
from reports_kit import REPORTS, write_report

from overlapmamba.core.io import decode_raw, read_points
from overlapmamba.core.modelmeta import EncoderMetadata
from overlapmamba.core.points import split_xyzi
from overlapmamba.core.projection import project, project_with_index
from overlapmamba.core.sensors import CATALOGUE, get_profile
from overlapmamba.core.sensors.input import SensorInput

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "kitti00_overlapnet_reference" / "000000.bin"


def scan(n: int) -> tuple[np.ndarray, str]:
    if REAL.is_file():
        xyz = read_points(REAL).xyz
        reps = int(np.ceil(n / len(xyz)))
        jitter = np.random.default_rng(0).normal(0, 0.01, (reps * len(xyz), 3))
        return (np.tile(xyz, (reps, 1)) + jitter.astype(np.float32))[:n], f"KITTI {REAL.name}"
    rng = np.random.default_rng(0)
    az, el = rng.uniform(-np.pi, np.pi, n), np.radians(rng.uniform(-25, 3, n))
    r = rng.uniform(2, 70, n)
    xyz = np.column_stack(
        [r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)]
    )
    return xyz.astype(np.float32), "synthetic"


def time_it(fn, repeats: int) -> np.ndarray:
    for _ in range(5):
        fn()
    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return np.array(out) * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--points", type=int, default=125_000)
    ap.add_argument("--repeats", type=int, default=200)
    ap.add_argument("--json", type=Path, default=REPORTS / "service" / "projection.json")
    args = ap.parse_args()
    xyz, source = scan(args.points)
    rows = []
    for name, profile in [
        ("kitti-hdl64", get_profile("kitti-hdl64")),
        ("hdl32", get_profile("hdl32")),
    ]:
        for label, fn in [
            ("project", lambda p=profile: project(xyz, p)),
            ("project_with_index", lambda p=profile: project_with_index(xyz, p)),
        ]:
            ms = time_it(fn, args.repeats)
            rows.append(
                {
                    "profile": name,
                    "function": label,
                    "points": len(xyz),
                    "median_ms": float(np.median(ms)),
                    "p90_ms": float(np.percentile(ms, 90)),
                    "goal_ms": 3.0 if label == "project" else None,
                }
            )
    # Decoding a scan before any projection: a raw xyzi body (KITTI .bin layout) → PointCloud,
    # and the copy it spends most of its time on, made both ways
    xyzi = np.column_stack([xyz, np.linspace(0, 1, len(xyz), dtype=np.float32)])
    body = xyzi.astype("<f4").tobytes()
    for label, fn in [
        ("decode_raw (xyzi body)", lambda: decode_raw(body, "xyzi")),
        (
            "xyzi split by [:, :3] slices (before)",
            lambda: (np.ascontiguousarray(xyzi[:, :3]), np.ascontiguousarray(xyzi[:, 3])),
        ),
        ("xyzi split as two fields (split_xyzi)", lambda: split_xyzi(xyzi)),
    ]:
        ms = time_it(fn, args.repeats)
        rows.append(
            {
                "profile": "-",
                "function": label,
                "points": len(xyz),
                "median_ms": float(np.median(ms)),
                "p90_ms": float(np.percentile(ms, 90)),
                "goal_ms": None,
            }
        )
    meta = _shipped_metadata()
    inputs = [("kitti-hdl64", meta.sensor_input)]
    for sensor in ("vlp16", "os1-128"):  # the shipped file's input and elevation-lerp's
        inputs += [(sensor, mode) for mode in dict.fromkeys((meta.sensor_input, "elevation-lerp"))]
    for sensor, mode in inputs:
        inp = SensorInput(meta.profile, CATALOGUE[sensor], mode)  # type: ignore[arg-type]
        ms = time_it(lambda i=inp: i.project(xyz, meta.views), args.repeats)
        rows.append(
            {
                "profile": sensor,
                "input": inp.kind,
                "function": f"service_input ({inp.kind}, {meta.views} views)",
                "points": len(xyz),
                "median_ms": float(np.median(ms)),
                "p90_ms": float(np.percentile(ms, 90)),
                "goal_ms": None,
            }
        )
    print(
        f"range projection, {len(xyz)} points ({source}), {args.repeats} runs, "
        f"{platform.processor() or platform.machine()}"
    )
    print(f"{'profile':<12} {'function':<40} {'median ms':>10} {'p90 ms':>8}  goal")
    for r in rows:
        goal = (
            ""
            if r["goal_ms"] is None
            else (f"≤ {r['goal_ms']:g} ms {'met' if r['median_ms'] <= r['goal_ms'] else 'MISSED'}")
        )
        print(
            f"{r['profile']:<12} {r['function']:<40} {r['median_ms']:>10.2f} "
            f"{r['p90_ms']:>8.2f}  {goal}"
        )
    write_report(args.json, {"source": source, "results": rows})
    print(f"wrote {args.json}")


def _shipped_metadata() -> EncoderMetadata:
    from overlapmamba.service.calibration import read_model_metadata

    return read_model_metadata(ROOT / "models" / "overlapmamba-hdl64.onnx")


if __name__ == "__main__":
    main()
