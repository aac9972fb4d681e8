"""Descriptors of other sensors moved into the model sensor's: how far a per-sensor
calibration, fitted on validation renderings, carries recognition across sensors.

The validation drive of the sensor towns is rendered by every sensor scan for scan
(``val-kitti-hdl64``, ``val-vlp16``, …: frame i is the same pose in each), so each sensor's
descriptors can be paired with the model sensor's of the same place. Per sensor, three ways
to bring a scan's descriptor d into the model sensor's space, leaving the model sensor's own
descriptors (and so every map it made) as they are:

    raw     d as the network gives it (what the service answers today)
    shift   d − m_sensor + m_model: the two sensors' mean descriptors over the validation
            drive (one 256-vector a sensor)
    linear  (d − m_sensor) W + m_model, W the ridge regression of the model sensor's centred
            descriptors on the sensor's (one 256 × 256 matrix a sensor); the ridge weight,
            per frame fitted on, is chosen on validation

each renormalised. **Chosen on validation**: the maps are fitted on the first half of the
drive, and the second half's odd frames of the sensor, queried against its even frames of
the model sensor (AR@1, a hit within 5 m), pick the ridge weight: frames the map was not
fitted on. **Reported on test**: refitted on every
validation frame, the second test drive of each sensor (``test-s1-SENSOR``) queried against
the first drive's map by the model sensor (``test-kitti-hdl64``), AR@1 / AR@5 as
``benchmarks/sensors.py`` counts them. Every scan enters the model as the service projects
its sensor's.

    python benchmarks/sensor_align.py [--model models/overlapmamba-hdl64.onnx]

Writes reports/model/sensor-align.json. ≈ 2 min a sensor on 2 cores with a one-view model
(each view a pass: a three-view file takes about three times as long).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from reports_kit import REPORTS, ROOT, write_report
from rich.console import Console

from overlapmamba.core.datasets import open_sequence
from overlapmamba.service.encoder import Encoder
from overlapmamba.service.sensors import Sensors
from overlapmamba.train.sessions import check_sessions, descriptor_recall, town_positions

SENSORS = ("vlp16", "os0-128", "xt32", "os1-128")  # those with a second test drive
RIDGE = (1e-6, 1e-5, 1e-4, 1e-3, 1e-2)  # per frame fitted on


def describe(enc: Encoder, town: Path) -> tuple[np.ndarray, np.ndarray]:
    """(N, D) float64 descriptors as the service makes them for the town's sensor, and the
    scans' (N, 3) positions in the town's frame."""
    seq = open_sequence(town)
    sensors = Sensors(enc.meta)
    inp = sensors.input(sensors.resolve(seq.sensor))
    out = []
    for start in range(0, len(seq), 8):
        pts = [seq.points(i) for i in range(start, min(len(seq), start + 8))]
        d, _ = enc.encode(np.stack([enc.project(p, inp) for p in pts]))
        out.append(d)
    return np.concatenate(out).astype(np.float64), town_positions(seq)


HOWS = ("raw", "shift", "linear")


def fit(q: np.ndarray, m: np.ndarray, how: str, ridge: float = 0.0) -> Callable:
    """The map d → the model sensor's space, fitted on paired descriptors q (the sensor's)
    and m (the model sensor's, same frames); ``ridge`` per frame."""
    if how not in HOWS:
        raise ValueError(f"unknown calibration {how!r}; allowed: {', '.join(HOWS)}")
    mq, mm = q.mean(0), m.mean(0)
    if how == "raw":
        return lambda d: d
    if how == "shift":
        return lambda d: d - mq + mm
    a, b = q - mq, m - mm
    w = np.linalg.solve(a.T @ a + ridge * len(a) * np.eye(a.shape[1]), a.T @ b)
    return lambda d: (d - mq) @ w + mm


def recall(db: np.ndarray, pos_db: np.ndarray, q: np.ndarray, pos_q: np.ndarray) -> dict:
    def unit(x: np.ndarray) -> np.ndarray:
        return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)

    r = descriptor_recall(unit(db), pos_db, unit(q), pos_q)
    return {"queries": r["queries"], "ar@1": r["ar@1"], "ar@5": r["ar@5"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, default=ROOT / "models" / "overlapmamba-hdl64.onnx")
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "synth")
    ap.add_argument("--sensors", nargs="+", default=list(SENSORS))
    ap.add_argument("--out", type=Path, default=REPORTS / "model" / "sensor-align.json")
    args = ap.parse_args()
    console = Console(width=120)
    t0 = time.perf_counter()
    enc = Encoder(args.model)
    own = enc.meta.profile.name
    need = [f"val-{own}", f"test-{own}"]
    need += [f"{p}-{s}" for s in args.sensors for p in ("val", "test-s1")]
    missing = [n for n in need if not (args.data / n / "manifest.json").is_file()]
    if missing:
        raise SystemExit(f"missing: {', '.join(missing)} (make data-sensors)")
    val_m, pos_val = describe(enc, args.data / f"val-{own}")
    db, pos_db = describe(enc, args.data / f"test-{own}")
    n = len(val_m)
    first = np.arange(n // 2)  # fitted on
    even, odd = np.arange(n // 2, n, 2), np.arange(n // 2 + 1, n, 2)  # chosen on
    rows = []
    for name in args.sensors:
        val_q, pos = describe(enc, args.data / f"val-{name}")
        if pos.shape != pos_val.shape or np.abs(pos - pos_val).max() > 0.01:
            raise SystemExit(f"val-{name} is not val-{own}'s drive scan for scan")
        check_sessions(
            open_sequence(args.data / f"test-{own}"), open_sequence(args.data / f"test-s1-{name}")
        )
        q, pos_q = describe(enc, args.data / f"test-s1-{name}")
        chosen: dict[str, Any] = {}

        def on_val(how: str, ridge: float, val_q: np.ndarray = val_q) -> float:
            """Fitted on the first half; the second half's odd frames against its even."""
            f = fit(val_q[first], val_m[first], how, ridge)
            return recall(val_m[even], pos_val[even], f(val_q[odd]), pos_val[odd])["ar@1"]

        for ridge in RIDGE:
            chosen[f"{ridge:g}"] = on_val("linear", ridge)
        best = max(RIDGE, key=lambda x: (chosen[f"{x:g}"], x))  # ties: the stronger ridge
        row: dict[str, Any] = {"sensor": name, "val_ar@1_by_ridge": chosen, "ridge": best}
        for how in HOWS:
            row[how] = {
                "val_ar@1": on_val(how, best),
                "test": recall(db, pos_db, fit(val_q, val_m, how, best)(q), pos_q),
            }
        rows.append(row)
        console.print(
            f"{name}: ridge {best:g}; test AR@1 raw {row['raw']['test']['ar@1']:.3f}, shift "
            f"{row['shift']['test']['ar@1']:.3f}, linear {row['linear']['test']['ar@1']:.3f}"
        )
    model = args.model.resolve()
    report = {
        "model": str(model.relative_to(ROOT) if model.is_relative_to(ROOT) else args.model),
        "model_id": enc.model_id,
        "views": enc.views,
        "map": f"test-{own}",
        "hit_radius_m": 5.0,
        "rows": rows,
        "seconds": time.perf_counter() - t0,
    }
    write_report(args.out, report)
    console.print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
