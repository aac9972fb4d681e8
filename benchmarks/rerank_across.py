"""The second stage across sensors: how long a shortlist, and how much the yaw features weigh.

A scan query's answer is its ``shortlist`` nearest descriptors re-ranked by d² − ``weight`` · c,
c the aligned correlation of the two scans' yaw features (:mod:`overlapmamba.core.rerank`).
Across sensors (``benchmarks/across_pairs.py``) the descriptor alone often misses where the
re-ranked answer finds the place, and it misses by rank: the right scan is in a longer
shortlist. This measures, for one model file and every ordered pair among the issue's five
sensors (``across_pairs.SENSORS``: queries of a second drive against a first drive's map),
AR@1 at each (shortlist, weight) of a grid, and what the re-ranking costs a query (the yaw
correlations of that many candidates, one thread, median).

The setting is chosen on ``val`` (calibration town ``cal-x00``, ``--frames`` scans a drive):
the best mean AR@1 over all 25 pairs (the five same-sensor pairs among them, so that a
setting cannot buy the pairs across sensors with one sensor's own answers); ties go to the
shorter shortlist, then the lighter weight. It is reported on ``test`` (the sensor test
town), never chosen there, beside the descriptor alone and the file's own setting (its
calibration, or the service's defaults where it has none). ``--write-calibration`` records
the chosen setting in the file as its ``rerank`` calibration (the service reads it from
there): the calibration of a file meant for a fleet of mixed sensors. ``--score network``
scores a mixed first stage's shortlist by the network's own descriptors inside it
(``benchmarks/rerank.py`` says more); the calibration records the score.

    python benchmarks/rerank_across.py --model runs/NAME/encoder.onnx \\
        --out reports/model/rerank-across-NAME.json

≈ 27 min on 2 cores with a one-view file (the correlations of 200 candidates for every
query are most of it).
"""

from __future__ import annotations

import argparse
import itertools
import time
from pathlib import Path
from typing import Any

import numpy as np
from across_pairs import BAR_AR1, SENSORS, Drives, split_towns
from bench_kit import check_section, model_record, served_settings, write_calibration
from common_beams import drive_arguments
from reports_kit import REPORTS, write_report
from rich.console import Console

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.metrics import nearest
from overlapmamba.core.rerank import Rerank, aligned_correlation, scored_by, with_score
from overlapmamba.core.yaw_spectrum import SCORES
from overlapmamba.service.encoder import Encoder
from overlapmamba.train.sessions import HIT_RADIUS, check_sessions, ground_truth, town_positions

SHORTLISTS = (1, 20, 50, 100, 200)  # 1: the descriptor alone
WEIGHTS = (0.2, 0.5, 1.0, 2.0, 8.0)


class Pair:
    """One map and one query drive: each query's ``k`` nearest descriptors, their squared
    distances, their yaw features' aligned correlations, and which lie within the hit
    radius, computed once for every setting of the grid."""

    def __init__(
        self, drives: Drives, db_town: Path, q_town: Path, k: int, part: int | None = None
    ) -> None:
        db_seq, q_seq = open_sequence(db_town), open_sequence(q_town)
        check_sessions(db_seq, q_seq)
        pos_db, pos_q = town_positions(db_seq), town_positions(q_seq)
        (d_db, y_db), (d_q, y_q) = drives.model(db_town), drives.model(q_town)
        k = min(k, len(d_db))
        self.ranked, self.dist = nearest(d_q, d_db, k)
        # the score's d² by what it is measured between (core.rerank.Rerank.part): the first
        # stage's vectors, and with a part the network's descriptors inside them
        self.d2 = {"stage": self.dist}
        if part is not None:
            rows = Rerank(part=part).rows(np.concatenate([d_db, d_q]))
            queries = len(d_db) + np.arange(len(d_q))
            self.d2["network"] = scored_by(rows, queries, self.ranked, self.dist, k)
        self.corr = np.stack(
            [aligned_correlation(y_q[i], y_db[self.ranked[i]]) for i in range(len(d_q))]
        )
        within = ground_truth(pos_db, pos_q)
        self.evaluated = within.any(1)  # queries with a place of the map within the radius
        self.near = np.take_along_axis(within, self.ranked, 1)

    def ar1(self, shortlist: int, weight: float, scored: str = "stage") -> float:
        """AR@1 with the first ``shortlist`` re-ranked at ``weight`` (1: the descriptor), the
        score's d² as ``scored`` says (stage, network)."""
        k = min(shortlist, self.dist.shape[1])
        score = self.d2[scored][:, :k] - weight * self.corr[:, :k]
        top = np.argmin(score, axis=1)
        hit = self.near[np.arange(len(top)), top]
        return float(hit[self.evaluated].mean())


def settings(shortlists: tuple[int, ...], weights: tuple[float, ...]) -> list[tuple[int, float]]:
    """The grid: the descriptor alone once (shortlist 1), then every shortlist × weight."""
    return [(1, 0.0)] * (1 in shortlists) + [(k, w) for k in shortlists if k > 1 for w in weights]


def score(
    pairs: dict[tuple[str, str], Pair], setting: tuple[int, float], scored: str = "stage"
) -> dict[str, Any]:
    ar = {key: p.ar1(*setting, scored) for key, p in pairs.items()}
    cross = [v for (q, m), v in ar.items() if q != m]
    same = [v for (q, m), v in ar.items() if q == m]
    return {
        "shortlist": setting[0],
        "weight": setting[1],
        "score": scored,
        "mean_ar@1": float(np.mean(list(ar.values()))),
        "cross_mean_ar@1": float(np.mean(cross)) if cross else None,
        "cross_min_ar@1": float(np.min(cross)) if cross else None,
        "same_mean_ar@1": float(np.mean(same)) if same else None,
        "pairs_at_bar": int(sum(v >= BAR_AR1 for v in cross)),
        "pairs": [{"queries": q, "map": m, "ar@1": v} for (q, m), v in ar.items()],
    }


def choose(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The best mean AR@1 over all pairs; ties to the shorter shortlist, the lighter weight."""
    return max(rows, key=lambda r: (round(r["mean_ar@1"], 9), -r["shortlist"], -r["weight"]))


def cost_ms(drives: Drives, town: Path, shortlists: tuple[int, ...], reps: int = 30) -> dict:
    """Median ms a query spends on the yaw correlations of ``k`` candidates (this process's
    numpy, as the service runs them), for each shortlist of the grid."""
    _, yaw = drives.model(town)
    rng = np.random.default_rng(0)
    out = {}
    for k in (k for k in shortlists if k > 1 and k <= len(yaw)):
        times = []
        for _ in range(reps):
            q, cand = rng.integers(len(yaw)), rng.choice(len(yaw), size=k, replace=False)
            t0 = time.perf_counter()
            aligned_correlation(yaw[q], yaw[cand])
            times.append(time.perf_counter() - t0)
        out[str(k)] = float(np.median(times) * 1e3)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    drive_arguments(ap, REPORTS / "model" / "rerank-across.json")
    ap.add_argument(
        "--shortlists",
        type=lambda t: tuple(int(k) for k in t.split(",")),
        default=SHORTLISTS,
        help=f"comma-separated (default {','.join(map(str, SHORTLISTS))}; 1: the first stage)",
    )
    ap.add_argument(
        "--write-calibration",
        action="store_true",
        help="record the setting chosen on val as the model's rerank.shortlist / rerank.weight",
    )
    ap.add_argument(
        "--score",
        choices=SCORES,
        default="stage",
        help="the score's d²: between the first stage's vectors (stage) or the network's own "
        "descriptors inside a mixed first stage (network); recorded with the calibration",
    )
    args = ap.parse_args()
    if args.write_calibration:  # choose only among what the service can answer with
        for k in args.shortlists:
            try:
                check_section("rerank", {"shortlist": k})
            except ValueError as err:
                ap.error(
                    f"--write-calibration with shortlist {k}: {err}; give --shortlists "
                    "the service accepts (e.g. 1,20,50)"
                )
    console = Console(width=120)
    t0 = time.perf_counter()
    enc = Encoder(args.model)
    served = served_settings(enc.meta)
    own = (served.rerank.shortlist, served.rerank.weight)
    try:
        part = with_score(Rerank(), args.score, enc.meta).part
        own_part = with_score(Rerank(), served.rerank.score, enc.meta).part
    except ValueError as err:
        ap.error(str(err))
    if args.score == "network" and part is None:
        ap.error(f"{args.model}'s first stage is the network's descriptor: score it by stage")
    grid = settings(args.shortlists, WEIGHTS)
    drives = Drives(enc, args.scratch)
    record: dict[str, Any] = {
        **model_record(args.model, enc),
        "own": {
            "shortlist": own[0],
            "weight": own[1],
            "score": served.rerank.score,
            "calibrated": "rerank" in (enc.meta.calibration or {}),
        },
        "sensors": list(SENSORS),
        "grid": {
            "shortlists": list(args.shortlists),
            "weights": list(WEIGHTS),
            "score": args.score,
        },
        "bar_ar@1": BAR_AR1,
        "radius_m": HIT_RADIUS,
    }
    kmax = max(args.shortlists)
    for split in ("val", "test"):
        towns = split_towns(split, args.data, args.scratch, args.frames)
        pairs = {
            (q, m): Pair(drives, towns[(m, 0)], towns[(q, 1)], kmax, part or own_part)
            for m, q in itertools.product(SENSORS, SENSORS)
        }
        console.print(f"{split}: {len(pairs)} pairs ready at {time.perf_counter() - t0:.0f} s")
        if split == "val":
            rows = [score(pairs, s, args.score) for s in grid]
            for r in rows:
                console.print(
                    f"shortlist {r['shortlist']:4d} weight {r['weight']:4.1f}: mean "
                    f"{r['mean_ar@1']:.3f}, across {r['cross_mean_ar@1']:.3f} (min "
                    f"{r['cross_min_ar@1']:.3f}), same {r['same_mean_ar@1']:.3f}",
                    highlight=False,
                )
            chosen = choose(rows)
            record["val"] = {"settings": rows, "chosen": chosen}
            record["cost_ms"] = cost_ms(drives, towns[(SENSORS[0], 0)], args.shortlists)
            calibration_towns = ", ".join(sorted({t.name for t in towns.values()}))
        else:
            best = (chosen["shortlist"], chosen["weight"])
            record["test"] = {
                "descriptor": score(pairs, (1, 0.0)),
                "own": score(pairs, own, served.rerank.score),
                "chosen": score(pairs, best, args.score),
            }
            for name, r in record["test"].items():
                console.print(
                    f"test {name}: mean {r['mean_ar@1']:.3f}, across "
                    f"{r['cross_mean_ar@1']:.3f} (min {r['cross_min_ar@1']:.3f}, "
                    f"{r['pairs_at_bar']} of 20 at the bar), same {r['same_mean_ar@1']:.3f}",
                    highlight=False,
                )
    record["seconds"] = round(time.perf_counter() - t0, 1)
    write_report(args.out, record)
    console.print(f"wrote {args.out}")
    if args.write_calibration:  # once the report that says why is written
        values = {"shortlist": chosen["shortlist"], "weight": chosen["weight"], "score": args.score}
        write_calibration(args.model, "rerank", values, calibration_towns)


if __name__ == "__main__":
    main()
