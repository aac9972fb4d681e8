"""Choose how a model takes scans of other sensors, on the validation towns (never on test).

A scan of a sensor other than the model's own enters the model's input in one of two ways
(:mod:`overlapmamba.core.sensors.input`): ``elevation`` (each row shows the beam nearest its own
elevation; rows the sensor has no beam for stay empty) or ``rows`` (the sensor's beams
stretched over the rows). This scores both with the model on the ``val-SENSOR`` towns
(``make data-sensors``) of four sensors that span the catalogue's differences from the
HDL-64E: the fewest beams (VLP-16), a non-uniform table (VLP-32C), the widest field of view
(OS0-128) and a uniform 1° table (XT32); ``--sensor`` picks others. The score: loop closure
F1max and Recall@1 over all revisits, the descriptor alone and in two stages (the service's
re-rank); the mode with the higher mean of those four numbers over the towns wins.
``--write`` records the pick in the model file (``EncoderMetadata.sensor_input``; the graph
stays byte for byte, the model id changes when the pick is not the default, ``elevation``:
other descriptors of other sensors' scans must not share a map).

    python benchmarks/sensor_input.py [--model models/overlapmamba-hdl64.onnx] [--write]

Writes JSON (default reports/model/sensor-input.json).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from bench_kit import ROOT, provenance, refuse_aligned
from rich.console import Console
from rich.table import Table

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.datasets.base import Sequence
from overlapmamba.core.rerank import Rerank
from overlapmamba.core.sensors import CATALOGUE, get_sensor
from overlapmamba.core.sensors.input import MODES, SensorInput
from overlapmamba.service.encoder import Encoder
from overlapmamba.train.evaluate import loop_closure, sequence_loops

KEYS = ("f1max", "recall@1")
PICKED = ("vlp16", "vlp32c", "os0-128", "xt32")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", type=Path, default=ROOT / "models" / "overlapmamba-hdl64.onnx")
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "synth", help="val-SENSOR towns")
    ap.add_argument("--write", action="store_true", help="record the pick in the model file")
    ap.add_argument(
        "--sensor",
        action="append",
        help="val-SENSOR towns to score (default: " + ", ".join(PICKED) + ")",
    )
    ap.add_argument("--out", type=Path, default=ROOT / "reports" / "model" / "sensor-input.json")
    args = ap.parse_args()
    console = Console(width=120)
    t0 = time.perf_counter()
    refuse_aligned(args.model, "it compares inputs with the sensor's columns, bird's-eye ones too")
    enc = Encoder(args.model)  # as the service runs it (the C-kernel path when it builds)
    profile, own = enc.meta.profile, enc.meta.sensor_input
    for name in args.sensor or ():
        get_sensor(name)  # an unknown name is refused with the allowed ones
    towns = [
        args.data / f"val-{name}"
        for name in args.sensor or PICKED
        if (args.data / f"val-{name}" / "manifest.json").is_file()
        and CATALOGUE[name].profile() != profile
    ]
    if not towns:
        raise SystemExit(f"no val-SENSOR towns under {args.data}: run `make data-sensors`")
    rows: dict[str, dict[str, dict[str, float]]] = {}
    rerank = Rerank()
    for mode in MODES:
        for town in towns:
            seq = open_sequence(town)
            gt = sequence_loops(seq)
            inp = SensorInput(profile, get_sensor(seq.sensor or town.name), mode)
            desc, yaw = describe(enc, seq, inp)
            alone = loop_closure(desc, gt)["all"].summary()
            staged = loop_closure(desc, gt, yaw, rerank)["all"].summary()
            rows.setdefault(seq.sensor or town.name, {})[mode] = {
                **{f"alone_{k}": float(alone[k]) for k in KEYS},
                **{f"two_stage_{k}": float(staged[k]) for k in KEYS},
            }
    means = {m: float(np.mean([list(r[m].values()) for r in rows.values()])) for m in MODES}
    pick = max(MODES, key=lambda m: means[m])
    table = Table(title=f"{args.model.name} on the validation towns: F1max / Recall@1 (all)")
    table.add_column("sensor")
    for mode in MODES:
        table.add_column(f"{mode}: alone", justify="right")
        table.add_column(f"{mode}: two stages", justify="right")
    for sensor, r in rows.items():
        cells = []
        for mode in MODES:
            x = r[mode]
            cells += [
                f"{x['alone_f1max']:.3f} / {x['alone_recall@1']:.3f}",
                f"{x['two_stage_f1max']:.3f} / {x['two_stage_recall@1']:.3f}",
            ]
        table.add_row(sensor, *cells)
    table.add_row("mean of the four", *[f"{means[m]:.3f}" for m in MODES for _ in (0, 1)])
    console.print(table)
    console.print(f"pick: {pick} (the model file says {own})")
    report = {
        **provenance(),
        "model_id": enc.model_id,
        "towns": [str(t) for t in towns],
        "rerank": {"shortlist": rerank.shortlist, "weight": rerank.weight},
        "by_sensor": rows,
        "mean": means,
        "pick": pick,
        "seconds": time.perf_counter() - t0,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    console.print(f"wrote {args.out}")
    if args.write:
        from overlapmamba.train.modelfile import with_sensor_input

        meta = with_sensor_input(args.model, pick)  # type: ignore[arg-type]
        console.print(f"{args.model}: sensor_input = {pick}, model id {meta.model_id}")


def describe(enc: Encoder, seq: Sequence, inp: SensorInput) -> tuple[np.ndarray, np.ndarray]:
    """Every scan of ``seq`` as the service describes it with ``inp``: (N, D), (N, C, W)."""
    from tqdm import tqdm

    descs, yaws = [], []
    for start in tqdm(range(0, len(seq), 8), desc=f"{seq.name} {inp.mode}", unit="batch"):
        pts = [seq.points(i) for i in range(start, min(len(seq), start + 8))]
        d, y = enc.encode(np.stack([enc.project(p, inp) for p in pts]))
        descs.append(d)
        yaws.append(y)
    return np.concatenate(descs), np.concatenate(yaws)


if __name__ == "__main__":
    main()
