"""A first stage reduced to fewer floats, measured on a drive its directions never saw.

``overlapmamba export FILE --reduce K --fit-on data/synth/val`` writes a file's first stage
times its K leading principal directions, fitted on ``val``'s vectors, at unit length
(:mod:`overlapmamba.train.reduce_head`). This scores, on ``val-s1`` (a second drive through
the validation town, not in the fit) within its own drive and queried against ``val``
(AR@1, a hit within 5 m), the first stage as it is, reduced as the export reduces it
(projected uncentred), and reduced after centring on the fit's mean (the textbook way),
for each ``--dims``: what the reduction costs and why the export projects uncentred.
Validation data only: the choice is made here, the test towns report it.

    python benchmarks/reduce_stage.py [--model runs/one-view-net/encoder.onnx]
        [--stage mixed:0.75:32:sqrt] [--dims 128,256] [--splits 96+160,128+128,160+96]

``--splits`` reduces the network's descriptor and the spectrum each on its own (``--reduce
K1+K2``), so that a second stage can still score by the network's distance (the leading K1
floats); every row is also scored with a second stage on top (``--rerank``, the service's
default shortlist and weight, by the network's distance where the vector holds it), and the
split of the best mean of its two stages' F1max and Recall@1 and its AR@1 is chosen.

The file must carry the network's own descriptor (the first stage is computed here from its
descriptor and yaw features). Writes JSON (default reports/model/reduce-stage.json).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np
from bench_kit import model_record
from first_stage import Towns
from reports_kit import REPORTS, ROOT, shown_path, write_report

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.rerank import OFF, Rerank
from overlapmamba.core.yaw_spectrum import FirstStage, unit
from overlapmamba.service.encoder import Encoder
from overlapmamba.train.evaluate import SUBSETS, loop_closure
from overlapmamba.train.reduce_head import (
    fit_directions,
    parse_reduction,
    reduce_vectors,
    split_directions,
)
from overlapmamba.train.sessions import check_sessions, descriptor_recall

SYNTH = ROOT / "data" / "synth"


def scores(towns: Towns, fit: Path, held: Path, vectors: Any, second: Rerank) -> dict[str, Any]:
    """The held-out drive's loop closure by ``vectors(town)`` (its own revisits), alone and
    with the ``second`` stage on top, and its AR@1 against the fit town (alone)."""
    gt, stored = towns._drive_truth(held)
    held_vectors = vectors(held)
    out: dict[str, Any] = {}
    for name, p in (("drive", OFF), ("two_stages", second)):
        res = loop_closure(held_vectors, gt, stored, p)
        out[name] = {s: {"f1max": res[s].f1max, "recall@1": res[s].recall_at_1} for s in SUBSETS}
    r = descriptor_recall(vectors(fit), towns.positions(fit), held_vectors, towns.positions(held))
    return {**out, "second_stage": asdict(second), "sessions_ar@1": float(r["ar@1"])}


def split_score(row: dict[str, Any]) -> float:
    """A split's figure: its two stages' F1max and Recall@1 over all revisits of the
    held-out drive and its AR@1, weighed alike."""
    two = row["two_stages"]["all"]
    return float(np.mean([two["f1max"], two["recall@1"], row["sessions_ar@1"]]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, default=ROOT / "runs" / "one-view-net" / "encoder.onnx")
    ap.add_argument("--stage", default="mixed:0.75:32:sqrt", help="the first stage reduced")
    ap.add_argument("--dims", default="128,256", help="floats kept, comma-separated")
    ap.add_argument(
        "--splits",
        default="96+160,128+128,160+96",
        help="K1+K2 reductions (the descriptor's K1 directions, the spectrum's K2), "
        "comma-separated; the best is chosen",
    )
    ap.add_argument("--rerank", default="20,0.2", help="the second stage: K,WEIGHT")
    ap.add_argument("--fit", type=Path, default=SYNTH / "val", help="the town fitted on")
    ap.add_argument("--held", type=Path, default=SYNTH / "val-s1", help="its second drive")
    ap.add_argument("--out", type=Path, default=REPORTS / "model" / "reduce-stage.json")
    args = ap.parse_args()
    try:
        stage = FirstStage.parse(args.stage)
        dims = [int(d) for d in args.dims.split(",")]
        splits = [x for x in args.splits.split(",") if x]
        for split in splits:
            if parse_reduction(split)[1] is None:
                raise ValueError(f"--splits {split!r} is not K1+K2")
        Rerank.parse(args.rerank)
    except ValueError as err:
        ap.error(str(err))
    if not args.model.is_file():
        ap.error(
            f"--model {args.model} does not exist: `overlapmamba export "
            "models/overlapmamba-hdl64.onnx --views 1 --column-phase aligned --out "
            "runs/one-view-net/encoder.onnx` writes the one-view network"
        )
    enc = Encoder(args.model)
    if enc.meta.first_stage != "descriptor":
        ap.error(f"{args.model} carries first stage {enc.meta.first_stage!r}: give the network's")
    for town in (args.fit, args.held):
        if not (town / "manifest.json").is_file():
            ap.error(f"{town} is not a generated town (make data; gen-data --preset val-s1)")
        if town.name.startswith("test"):
            ap.error(f"{town}: a reduction is chosen on validation towns, never a test town")
    check_sessions(open_sequence(args.fit), open_sequence(args.held))
    t0 = time.perf_counter()
    towns = Towns(args.model)

    def staged(town: Path) -> np.ndarray:
        return stage.vectors(*towns.features(town))

    fitted = staged(args.fit)
    mean = fitted.mean(axis=0)
    own = enc.dim  # the network's descriptor leads a mixed stage's vector
    rerank = Rerank.parse(args.rerank)
    network = replace(rerank, part=own)
    rows = [
        {"vector": "the network's descriptor", "floats": own, "centred": None,
         **scores(towns, args.fit, args.held, lambda t: unit(towns.features(t)[0]), rerank)},
        {"vector": stage.name, "floats": fitted.shape[1], "centred": None,
         **scores(towns, args.fit, args.held, staged, network)},
    ]  # fmt: skip
    for dim in dims:
        directions, kept = fit_directions(fitted, dim)
        for centred in (False, True):
            shift = mean if centred else 0.0
            rows.append(
                {
                    "vector": f"{stage.name}, {dim} principal directions",
                    "floats": dim,
                    "centred": centred,
                    "variance_kept": kept,
                    **scores(
                        towns,
                        args.fit,
                        args.held,
                        lambda t, d=directions, s=shift: reduce_vectors(staged(t) - s, d),
                        rerank,
                    ),
                }
            )
    for split in splits:
        dim, lead = parse_reduction(split)
        directions, kept = split_directions(fitted, own, lead, dim - lead)
        rows.append(
            {
                "vector": f"{stage.name}, the descriptor's {lead} and the spectrum's "
                f"{dim - lead} principal directions",
                "floats": dim,
                "split": split,
                "centred": False,
                "variance_kept": kept,
                **scores(
                    towns,
                    args.fit,
                    args.held,
                    lambda t, d=directions: reduce_vectors(staged(t), d),
                    replace(rerank, part=lead),
                ),
            }
        )
        rows[-1]["score"] = split_score(rows[-1])
    chosen = max((r for r in rows if "split" in r), key=lambda r: r["score"], default=None)
    for r in rows:
        a, b = r["drive"]["all"], r["two_stages"]["all"]
        print(
            f"{r['vector'][:60]:>60s} {r['floats']:>4d} centred={r['centred']!s:5s}: "
            f"{a['f1max']:.3f} / {a['recall@1']:.3f} · two stages {b['f1max']:.3f} / "
            f"{b['recall@1']:.3f} · AR@1 {r['sessions_ar@1']:.3f}"
        )
    print(f"chosen split: {chosen['split'] if chosen else None}")
    record = {
        **model_record(args.model, enc),
        "stage": stage.name,
        "second_stage": "the network's distance (the leading floats) where the vector holds "
        "it, else the vector's own; shortlist and weight as --rerank",
        "split_chosen_by": "the mean of the held-out drive's two-stage F1max and Recall@1 "
        "(all revisits) and its AR@1, among the splits",
        "split_chosen": chosen["split"] if chosen else None,
        "fit": shown_path(args.fit),
        "held_out": shown_path(args.held),
        "rows": rows,
        "seconds": round(time.perf_counter() - t0, 1),
    }
    write_report(args.out, record)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
