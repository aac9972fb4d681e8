"""Verified loop closures across sensors: a map made by one sensor, queries from another.

``benchmarks/verify_threshold.py`` scores the service's geometric verification on loops
within one drive, each sensor against itself. A mixed fleet also asks it to verify a VLP-16
robot's scan against the keyframe geometry an HDL-64E car left in the map. This runs the
service's path on the issue's five sensors' pairs (``across_pairs.SENSORS``; a second drive
by the query sensor against a first drive's map by the map sensor, 20 pairs across sensors
and the five same-sensor pairs): every scan encoded as the service encodes a scan that names
its sensor and kept as a keyframe's compact geometry (``overlapmamba.core.geometry``); each
query's top ``--candidates`` in the service's order (``overlapmamba.service.ranking``: the
descriptor shortlist re-ranked by the yaw features) registered against them
(``overlapmamba.service.verify``). A closure is **correct** when its relative pose is within
1 m and 2° of the true one (T = P_keyframe⁻¹ · P_query, the drives' poses in the town's
frame), as ``verify_threshold.py`` judges it; a query **has** a loop when a map scan lies
within 5 m (``overlapmamba.train.sessions``). Scored at the model file's thresholds (its
calibration, else the service's defaults), the first verified candidate in the answer's
order (``verify.stop_at_first``, the default): precision, and recall over the queries with
a loop, pair by pair.

With the model's covariance calibration (``benchmarks/pose_covariance.py``), each right
closure's covariance is scored as there (the share inside each level's ellipsoid, the mean
negative log-likelihood), pair by pair and pooled across sensors and on the same sensor;
``--fit-from`` (that calibration's JSON) scores its one ellipsoid for every closure beside it.

- ``val``: calibration town ``cal-x00`` (``--frames`` scans a drive);
- ``test``: the sensor test town (``test-SENSOR`` maps, ``test-s1-SENSOR`` queries).

    python benchmarks/verify_across.py [--model FILE] [--every 2] [--fit-from JSON] [--out …]

Writes JSON (default reports/service/verify-across.json).
"""

from __future__ import annotations

import argparse
import itertools
import math
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
from across_pairs import SENSORS, split_towns
from bench_kit import ROOT, model_record, served_input, served_rerank, served_settings
from closure_kit import candidate, closure, recorded_rival, score
from common_beams import drive_arguments
from pose_covariance import covariances, read_fit, scored_kinds
from reports_kit import REPORTS, write_report
from rich.console import Console
from tqdm import tqdm

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.poses import POSE_RIGHT
from overlapmamba.core.rerank import Rerank, by_score, score_d2
from overlapmamba.core.sensors.catalogue import CATALOGUE
from overlapmamba.core.yaw import estimate_yaw
from overlapmamba.service.encoder import Encoder
from overlapmamba.service.registration import keyframe_geometry, prepare
from overlapmamba.service.sensors import FieldOfView
from overlapmamba.service.settings import VerifySettings
from overlapmamba.service.verify import params_of, verify_candidates
from overlapmamba.synth.generate import read_manifest
from overlapmamba.train.sessions import check_sessions, ground_truth


class Drive:
    """One drive as the service holds it: descriptors, yaw features (float16, as a map keeps
    them), each scan's keyframe geometry (``keyframes``: a map drive's keep it), and
    world poses. A query's registration grid is prepared when it is asked (``prepared``):
    a drive's grids held at once take gigabytes."""

    def __init__(
        self, enc: Encoder, path: Path, v: VerifySettings, *, keyframes: bool, batch: int = 8
    ) -> None:
        seq = open_sequence(path)
        self.seq = seq
        sensor = served_input(enc, seq.sensor)
        self.params = params_of(v)
        descs, yaws, self.blobs = [], [], []
        for start in tqdm(range(0, len(seq), batch), desc=f"encode {path.name}", unit="batch"):
            pts = [seq.points(i) for i in range(start, min(len(seq), start + batch))]
            d, y = enc.describe(pts, sensor, batch=len(pts))
            descs.append(d)
            yaws.append(np.asarray(y, dtype=np.float16))
            if keyframes:
                self.blobs += [
                    keyframe_geometry(prepare(p.xyz, self.params), self.params) for p in pts
                ]
        self.desc, self.yaw = np.concatenate(descs), np.concatenate(yaws)
        m = read_manifest(path)
        world = np.asarray(m.get("world_from_sequence", np.eye(4)), dtype=np.float64)
        self.poses = world @ seq.poses  # (N, 4, 4) in the town's frame

    def prepared(self, i: int) -> Any:
        return prepare(self.seq.points(i).xyz, self.params)


def pair_queries(
    db: Drive,
    q: Drive,
    k: int,
    v: VerifySettings,
    rerank: Rerank,
    every: int,
    view: FieldOfView | None,
    rivals_from: float | None = None,
) -> list[dict[str, Any]]:
    """Each ``every``-th query's candidates in the service's order, registered: what
    ``verify_threshold.score`` reads (fitness, rmse, pose error, within the hit radius).
    ``rivals_from``: each candidate whose fitness reaches it is registered again from the
    other quarter turns too (``closure_kit.recorded_rival``), so that the ambiguity margin can be
    chosen on the pairs."""
    check_sessions(db.seq, q.seq)
    within = ground_truth(db.poses[:, :3, 3], q.poses[:, :3, 3])
    d2 = np.maximum(2.0 - 2.0 * q.desc @ db.desc.T, 0.0)
    s2 = score_d2(rerank, q.desc, db.desc, d2)
    v = v.model_copy(update={"stop_at_first": False})  # every candidate: score() decides
    out = []
    for i in range(0, len(q.desc), every):
        top = np.argsort(d2[i], kind="stable")[: max(k, rerank.shortlist)]
        deg, conf = estimate_yaw(q.yaw[i].astype(np.float32), db.yaw[top].astype(np.float32))
        if rerank.on:  # as overlapmamba.service.ranking orders the answer
            order, _ = by_score(s2[i, top], conf, rerank.weight)
            top, deg = top[order], deg[order]
        top, deg = top[:k], deg[:k]
        prepared = q.prepared(i)
        verdicts = verify_candidates(
            prepared,
            [
                (db.blobs[j], float(a), float(np.sqrt(d2[i, j])))
                for j, a in zip(top, deg, strict=True)
            ],
            v,
            [view] * len(top),
        )
        cands = [
            candidate(j, float(np.sqrt(d2[i, j])), within[i, j], verdict, db.poses[j], q.poses[i])
            | recorded_rival(prepared, db.blobs[j], float(a), verdict, q.params, rivals_from, view)
            for j, a, verdict in zip(top, deg, verdicts, strict=True)
        ]
        out.append(
            {
                "query": i,
                "has_loop": bool(within[i].any()),
                "candidates": cands,
                "group": f"{q.seq.name} against {db.seq.name}",
            }
        )
    return out


def view_of(map_sensor: str, query_sensor: str) -> FieldOfView | None:
    """The map sensor's field of view when the query's sensor is another, as the service
    registers such a pair (``overlapmamba.service.places``)."""
    if map_sensor == query_sensor:
        return None
    s = CATALOGUE[map_sensor]
    return FieldOfView.of(s.elevations_deg, s.max_range)


def val_pair_queries(
    enc: Encoder,
    v: VerifySettings,
    rerank: Rerank,
    every: int = 2,
    frames: int = 500,
    rivals_from: float | None = None,
) -> tuple[list[dict[str, Any]], list[str]]:
    """Every candidate of the calibration town's 25 pairs registered (no descriptor gate:
    ``verify_threshold.py --calibrate --across`` sweeps it; ``rivals_from``: as
    :func:`pair_queries`), and the drives' names."""
    towns = split_towns("val", ROOT / "data" / "synth", ROOT / "data" / "common-beams", frames)
    drives = {key: Drive(enc, path, v, keyframes=key[1] == 0) for key, path in towns.items()}
    v = v.model_copy(update={"gate_distance": None})
    queries = []
    for m, q in itertools.product(SENSORS, SENSORS):
        queries += pair_queries(
            drives[(m, 0)],
            drives[(q, 1)],
            v.candidates,
            v,
            rerank,
            every,
            view_of(m, q),
            rivals_from,
        )
    return queries, sorted(path.name for path in towns.values())


def right_closures(queries: list[dict[str, Any]], v: VerifySettings) -> list[dict[str, Any]]:
    """Each query's closure as :func:`closure_kit.score` calls it at the file's thresholds,
    where its pose is right and it has a Hessian: what ``pose_covariance.scored_kinds``
    reads (δ, the Hessian, the residual)."""
    out = []
    for q in queries:
        best, _ = closure(
            q, v.min_fitness, v.max_rmse_m, v.gate_distance, v.stop_at_first, v.ambiguity_margin
        )
        if best is None or best.get("hessian") is None:
            continue
        if best["t_err"] <= POSE_RIGHT[0] and best["yaw_err"] <= POSE_RIGHT[1]:
            out.append({k: best[k] for k in ("delta", "hessian", "residual")})
    return out


def _across(row: dict[str, Any]) -> bool:
    return bool(row["queries_sensor"] != row["map_sensor"])


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Across sensors (the 20 pairs) and the same sensor (the diagonal): mean and lowest
    recall, the lowest precision, and the closures accepted and correct over all."""
    out: dict[str, Any] = {}
    for name, keep in (("across", _across), ("same", lambda r: not _across(r))):
        sel = [r["verified"] for r in rows if keep(r)]
        accepted = sum(x["accepted"] for x in sel)
        out[name] = {
            "pairs": len(sel),
            "recall_mean": float(np.mean([x["recall"] for x in sel])),
            "recall_lowest": float(np.min([x["recall"] for x in sel])),
            "precision_lowest": float(np.min([x["precision"] for x in sel])),
            "accepted": accepted,
            "correct": sum(x["correct"] for x in sel),
            "precision": sum(x["correct"] for x in sel) / accepted if accepted else 1.0,
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    drive_arguments(ap, REPORTS / "service" / "verify-across.json")
    ap.add_argument("--every", type=int, default=2, help="query every n-th scan of a drive")
    ap.add_argument("--split", choices=("val", "test", "both"), default="both")
    ap.add_argument(
        "--no-view",
        action="store_true",
        help="score fitness over all the query's points, not only those inside the map "
        "sensor's field of view (the service before it knew the two sensors apart)",
    )
    ap.add_argument(
        "--fit-from",
        type=Path,
        help="score the one ellipsoid for every closure of this benchmarks/pose_covariance.py "
        "--calibrate JSON (the same model's) beside the served covariance",
    )
    args = ap.parse_args()
    console = Console(width=120)
    t0 = time.perf_counter()
    enc = Encoder(args.model)
    served = served_settings(enc.meta)
    v, rr = served.verify, served_rerank(enc.meta)
    fit = read_fit(args.fit_from, enc.model_id) if args.fit_from is not None else None
    if fit is not None and any(
        Path(t.strip()).name.startswith("test") for t in fit["town"].split(",")
    ):
        ap.error(f"{args.fit_from} was fitted on a test town: fit on validation towns")
    cov = served.covariance
    if fit is not None and cov.estimator is None:
        ap.error(
            f"{args.model} carries no covariance calibration: run benchmarks/"
            "pose_covariance.py --calibrate --write-calibration on it first, or leave out "
            "--fit-from"
        )
    if fit is not None and (
        cov.estimator != fit["chosen"]
        or not math.isclose(cov.scale or 0.0, fit["fits"][fit["chosen"]]["scale"], rel_tol=1e-9)
    ):
        ap.error(
            f"{args.fit_from} chose {fit['chosen']}, the file serves {cov.estimator} at scale "
            f"{cov.scale}: give the JSON of the calibration the file carries"
        )
    kinds = covariances(cov, fit)
    constant = np.asarray(fit["constant_covariance"]) if fit is not None else np.eye(6)
    record: dict[str, Any] = {
        **model_record(args.model, enc),
        "verify": v.model_dump(),
        "rerank": asdict(rr),
        "calibrated": sorted(enc.meta.calibration),
        "every": args.every,
        "field_of_view": not args.no_view,
        "pose_ok": {"translation_m": 1.0, "yaw_deg": 2.0},
        "covariance": {"scored": {k: {"estimator": e, "scale": x} for k, (e, x) in kinds.items()}}
        | ({"fit_from": fit["from"], "fit_towns": fit["town"]} if fit else {}),
    }
    splits = ("val", "test") if args.split == "both" else (args.split,)
    for split in splits:
        towns = split_towns(split, args.data, args.scratch, args.frames)
        drives = {key: Drive(enc, path, v, keyframes=key[1] == 0) for key, path in towns.items()}
        rows = []
        pooled: dict[str, list[dict[str, Any]]] = {"across": [], "same": []}
        for m, q in itertools.product(SENSORS, SENSORS):
            view = None if args.no_view else view_of(m, q)
            queries = pair_queries(
                drives[(m, 0)],
                drives[(q, 1)],
                v.candidates,
                v,
                rr,
                args.every,
                view,
            )
            gate = v.gate_distance
            # the service's call: a candidate refused as ambiguous carries its rival's fit
            got = score(
                queries,
                v.min_fitness,
                v.max_rmse_m,
                gate,
                stop_at_first=v.stop_at_first,
                margin=v.ambiguity_margin,
            )
            row = {
                "queries_sensor": q,
                "map_sensor": m,
                "queries": len(queries),
                "with_loop": sum(x["has_loop"] for x in queries),
                "verified": got,
            }
            if kinds:
                right = right_closures(queries, v)
                pooled["across" if m != q else "same"] += right
                row["covariance"] = scored_kinds(right, kinds, constant)
            rows.append(row)
            console.print(
                f"{split}: {q} queries against {m}'s map: precision {got['precision']:.3f}, "
                f"recall {got['recall']:.3f} ({got['accepted']} accepted)"
                + "".join(
                    f"; {label} covariance: inside 95 % {c['inside']['0.95']:.3f}"
                    f", NLL {c['nll']:.2f}"
                    for label, c in row.get("covariance", {}).items()
                    if c["closures"]
                ),
                highlight=False,
            )
        record[split] = {"pairs": rows, "summary": summary(rows)}
        for name, right in pooled.items() if kinds else ():
            record[split]["summary"][name]["covariance"] = scored_kinds(right, kinds, constant)
        del drives
    record["seconds"] = round(time.perf_counter() - t0, 1)
    write_report(args.out, record)
    console.print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
