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

each renormalised (:mod:`overlapmamba.core.sensormaps`). What they are fitted on
(``--fit``):

    val     the validation drive: fitted on its first half; the second half's odd frames
            of the sensor, queried against its even frames of the model sensor (AR@1, a hit
            within 5 m), pick the ridge weight (frames the map was not fitted on); refitted
            on every validation frame
    towns   ``--towns`` calibration towns (``overlapmamba.synth.presets.calibration_town``:
            small towns of their own, each driven once and rendered by the model sensor and
            every other sensor, generated into ``--scratch``, described, then their scans
            deleted); the whole validation drive's odd frames against its even ones pick the
            ridge weight: a town none of the maps was fitted on

**Reported on test**: the second test drive of each sensor (``test-s1-SENSOR``) queried
against the first drive's map by the model sensor (``test-kitti-hdl64``), AR@1 / AR@5 as
``benchmarks/sensors.py`` counts them; and against the sensor's own first drive
(``test-SENSOR``), raw and with both sides mapped (what the maps cost a fleet of that sensor
alone). Every scan enters the model as the service projects
its sensor's. ``--write-maps OUT.onnx`` writes the model again carrying the linear maps as
reported (``overlapmamba.train.modelfile.with_sensor_maps``): the service then maps those
sensors' descriptors (``/readyz`` lists them).

    python benchmarks/sensor_align.py [--model models/overlapmamba-hdl64.onnx] [--fit towns]

Writes reports/model/sensor-align.json. ≈ 2 min a sensor on 2 cores with a one-view model
(each view a pass: a three-view file takes about three times as long); ``--fit towns`` adds
≈ 1 min a rendering of 400 scans (generated and described).
"""

from __future__ import annotations

import argparse
import hashlib
import shutil
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from bench_kit import served_input
from reports_kit import REPORTS, ROOT, shown_path, write_report
from rich.console import Console

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.sensormaps import SensorMap, fit_map
from overlapmamba.service.encoder import Encoder
from overlapmamba.train.modelfile import with_sensor_maps
from overlapmamba.train.sessions import check_sessions, descriptor_recall, town_positions

SENSORS = ("vlp16", "os0-128", "xt32", "os1-128")  # those with a second test drive
RIDGE = (1e-6, 1e-5, 1e-4, 1e-3, 1e-2, 1e-1)  # per frame fitted on


def describe(enc: Encoder, town: Path, cache: Path | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(N, D) float64 descriptors the network gives the town's scans as its sensor's (never
    mapped: what maps are fitted on and applied to), and the scans' (N, 3) positions in the
    town's frame. ``cache``: a folder keeping them under the model id and the town's manifest,
    so a rerun describes only what changed."""
    seq = open_sequence(town)
    f = None
    if cache is not None:
        stamp = hashlib.sha256((town / "manifest.json").read_bytes()).hexdigest()[:12]
        f = cache / enc.model_id / f"{town.name}-{stamp}.npy"
        if f.is_file():
            return np.load(f), town_positions(seq)
    inp = served_input(enc, seq.sensor)
    desc, _ = enc.describe((seq.points(i) for i in range(len(seq))), inp, mapped=False)
    if f is not None:
        f.parent.mkdir(parents=True, exist_ok=True)
        np.save(f, desc.astype(np.float64))
    return desc.astype(np.float64), town_positions(seq)


HOWS = ("raw", "shift", "linear")


def fit(q: np.ndarray, m: np.ndarray, how: str, ridge: float = 0.0) -> Callable:
    """The map d → the model sensor's space, fitted on paired descriptors q (the sensor's)
    and m (the model sensor's, same frames); ``ridge`` per frame."""
    if how not in HOWS:
        raise ValueError(f"unknown calibration {how!r}; allowed: {', '.join(HOWS)}")
    if how == "raw":
        return lambda d: d
    return fitted(q, m, how, ridge).apply


def fitted(q: np.ndarray, m: np.ndarray, how: str, ridge: float, data: str = "-") -> SensorMap:
    return fit_map(
        q,
        m,
        how,
        ridge=ridge,
        chosen_by="python benchmarks/sensor_align.py",
        data=data,
        at=datetime.now(UTC).isoformat(),
    )


def calibration_towns(
    enc: Encoder, sensors: list[str], towns: int, frames: int, scratch: Path, console: Console
) -> dict[str, np.ndarray]:
    """Per sensor (the model's own first), its descriptors of every calibration town's
    drive, towns in order: frame i of one sensor's is frame i of every other's. Each
    rendering is generated into ``scratch``, described and deleted; its descriptors are kept
    there under the model id, so a rerun describes only what is missing."""
    from overlapmamba.synth.generate import generate
    from overlapmamba.synth.presets import calibration_town

    out: dict[str, list[np.ndarray]] = {s: [] for s in sensors}
    cache = scratch / "descriptors" / enc.model_id
    cache.mkdir(parents=True, exist_ok=True)
    for k in range(towns):
        for s in sensors:
            cfg = calibration_town(k, s, frames)
            name = f"{cfg.preset}-{s}-{frames}"
            f = cache / f"{name}.npy"
            if not f.is_file():
                t = time.perf_counter()
                town = scratch / name
                shutil.rmtree(town, ignore_errors=True)
                generate(town, cfg, workers=2, progress=False, ground_truth=False)
                np.save(f, describe(enc, town)[0])
                shutil.rmtree(town)
                console.print(f"{name}: generated and described in {time.perf_counter() - t:.0f} s")
            out[s].append(np.load(f))
    return {s: np.concatenate(x) for s, x in out.items()}


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
    ap.add_argument("--fit", choices=("val", "towns"), default="val")
    ap.add_argument("--towns", type=int, default=6, help="--fit towns: how many")
    ap.add_argument("--frames", type=int, default=400, help="--fit towns: scans a town")
    ap.add_argument(
        "--scratch",
        type=Path,
        default=ROOT / "data" / "synth" / "calibration",
        help="where calibration renderings are made (and deleted) and descriptors kept",
    )
    ap.add_argument("--write-maps", type=Path, help="the model again, carrying the linear maps")
    ap.add_argument("--out", type=Path, default=REPORTS / "model" / "sensor-align.json")
    args = ap.parse_args()
    if args.towns < 1 or args.frames < 2:
        ap.error("--towns must be ≥ 1 and --frames ≥ 2")
    console = Console(width=120)
    t0 = time.perf_counter()
    enc = Encoder(args.model)
    own = enc.meta.profile.name
    if own in args.sensors:
        ap.error(f"{own} is the model's own sensor: its descriptors are never mapped")
    need = [f"val-{own}", f"test-{own}"]
    need += [f"{p}-{s}" for s in args.sensors for p in ("val", "test", "test-s1")]
    missing = [n for n in need if not (args.data / n / "manifest.json").is_file()]
    if missing:
        raise SystemExit(f"missing: {', '.join(missing)} (make data-sensors)")
    cache = args.scratch / "descriptors"  # val and test drives' too: reruns are cheap
    towns = None
    if args.fit == "towns":
        towns = calibration_towns(
            enc, [own, *args.sensors], args.towns, args.frames, args.scratch, console
        )
    val_m, pos_val = describe(enc, args.data / f"val-{own}", cache)
    db, pos_db = describe(enc, args.data / f"test-{own}", cache)
    n = len(val_m)
    if towns is None:  # fitted on the first half, chosen on the second
        first = np.arange(n // 2)
        even, odd = np.arange(n // 2, n, 2), np.arange(n // 2 + 1, n, 2)
        fitted_on = f"val-{own} and val-SENSOR (frames {n // 2} and on chose the ridge)"
    else:  # fitted on the towns, chosen on the whole validation drive
        even, odd = np.arange(0, n, 2), np.arange(1, n, 2)
        fitted_on = (
            f"{args.towns} calibration towns × {args.frames} scans (cal-x00 …), ridge chosen "
            f"on val-{own} and val-SENSOR"
        )
    rows, maps = [], {}
    for name in args.sensors:
        val_q, pos = describe(enc, args.data / f"val-{name}", cache)
        if pos.shape != pos_val.shape or np.abs(pos - pos_val).max() > 0.01:
            raise SystemExit(f"val-{name} is not val-{own}'s drive scan for scan")
        check_sessions(
            open_sequence(args.data / f"test-{own}"), open_sequence(args.data / f"test-s1-{name}")
        )
        q, pos_q = describe(enc, args.data / f"test-s1-{name}", cache)
        if towns is None:  # chosen fitted on the first half, then refitted on all
            sel_q, sel_m, fit_q, fit_m = val_q[first], val_m[first], val_q, val_m
        else:
            sel_q = fit_q = towns[name]
            sel_m = fit_m = towns[own]

        def on_val(how: str, ridge: float, val_q: np.ndarray = val_q, q0=sel_q, m0=sel_m) -> float:
            """The map's AR@1 on validation frames it was not fitted on."""
            f = fit(q0, m0, how, ridge)
            return recall(val_m[even], pos_val[even], f(val_q[odd]), pos_val[odd])["ar@1"]

        chosen: dict[str, Any] = {f"{r:g}": on_val("linear", r) for r in RIDGE}
        best = max(RIDGE, key=lambda x: (chosen[f"{x:g}"], x))  # ties: the stronger ridge
        row: dict[str, Any] = {"sensor": name, "val_ar@1_by_ridge": chosen, "ridge": best}
        for how in HOWS:
            row[how] = {
                "val_ar@1": on_val(how, best),
                "test": recall(db, pos_db, fit(fit_q, fit_m, how, best)(q), pos_q),
            }
        row["pairs"] = len(fit_q)
        maps[name] = fitted(fit_q, fit_m, "linear", best, fitted_on.replace("SENSOR", name))
        # the sensor's own map (its first test drive) queried by its second: both mapped, as
        # a service with the maps keeps them; does the map cost the sensor's own fleet?
        own_db, own_pos = describe(enc, args.data / f"test-{name}", cache)
        apply = maps[name].apply
        row["own"] = {
            "raw": recall(own_db, own_pos, q, pos_q),
            "linear": recall(apply(own_db), own_pos, apply(q), pos_q),
        }
        rows.append(row)
        console.print(
            f"{name}: ridge {best:g}; test AR@1 raw {row['raw']['test']['ar@1']:.3f}, shift "
            f"{row['shift']['test']['ar@1']:.3f}, linear {row['linear']['test']['ar@1']:.3f}; "
            f"own map {row['own']['raw']['ar@1']:.3f} → {row['own']['linear']['ar@1']:.3f}"
        )
    report = {
        "model": shown_path(args.model),
        "model_id": enc.model_id,
        "views": enc.views,
        "fit": args.fit,
        "fitted_on": fitted_on,
        "map": f"test-{own}",
        "hit_radius_m": 5.0,
        "rows": rows,
        "seconds": time.perf_counter() - t0,
    }
    if args.write_maps:
        meta = with_sensor_maps(args.model, args.write_maps, maps)
        report["wrote_maps"] = {"path": str(args.write_maps), "model_id": meta.model_id}
        console.print(
            f"wrote {args.write_maps} (model {meta.model_id}): maps for {', '.join(maps)}"
        )
    write_report(args.out, report)
    console.print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
