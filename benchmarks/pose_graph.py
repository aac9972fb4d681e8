"""What a verified closure's covariance buys a pose graph.

Per test town, the closures as the service answers them (``benchmarks/pose_covariance.py``'s:
each scan queried against the earlier ones, its verified closure of highest fitness, right
or wrong), and the graph a SLAM back end builds from a drifting drive: a vertex a scan,
an odometry edge between consecutive scans (the true motion with noise drawn per step of
the σ given, weighted by that σ's true information), a loop edge a verified closure (its
relative pose, from the keyframe's vertex to the query's). Optimised
(``benchmarks/graph_kit.py``: Levenberg–Marquardt, scan 0 held at its true pose) with the
loop edges weighted three ways:

- ``served``: the covariance the service answers (the model file's calibration);
- ``constant``: one ellipsoid for every closure, the one fitted on the validation closures
  (``reports/service/pose_covariance.json``, the yardstick of that benchmark);

and, beside them, the odometry alone (dead reckoning: the drift the loops must undo).

Scored against the truth over ``--seeds`` noise draws: each scan's position error (RMS, the
largest, the share of scans within 0.1 m) and rotation error (RMS, degrees), and the map
where the drive comes back: the relative pose of every revisit pair of the town's ground
truth (the error a map shows as a doubled wall). Prints a table, writes
``reports/service/pose-graph-test.json``.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import graph_kit as gk
import numpy as np
from bench_kit import ROOT, provenance, served_rerank, served_settings
from pose_covariance import read_fit, town_closures
from reports_kit import REPORTS, write_report
from rich.console import Console
from rich.table import Table

from overlapmamba.core import posecov
from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.overlap import LoopGroundTruth
from overlapmamba.service.encoder import Encoder

WAYS = ("served", "constant")
NEAR_M = 0.1  # a scan "within" when its position is this close to the truth


def odometry(truth: np.ndarray, sigma: np.ndarray, rng: np.random.Generator) -> gk.Edges:
    """Consecutive scans' true motion, each with noise of ``sigma`` (6: x, y, z in metres,
    then roll, pitch, yaw in radians) drawn on the right, weighted by its information."""
    n = len(truth)
    steps = gk.inverse(truth[:-1]) @ truth[1:]
    noisy = steps @ gk.exp_se3(rng.normal(size=(n - 1, 6)) * sigma)
    info = np.tile(np.diag(1.0 / sigma**2), (n - 1, 1, 1))
    return gk.Edges(np.arange(n - 1), np.arange(1, n), noisy, info)


def dead_reckoning(start: np.ndarray, edges: gk.Edges) -> np.ndarray:
    """The poses the odometry edges chain from ``start``."""
    poses = [start]
    for z in edges.z:
        poses.append(poses[-1] @ z)
    return np.array(poses)


def loop_edges(closures: list[dict[str, Any]], covariances: list[np.ndarray]) -> gk.Edges:
    """Each closure as an edge from its keyframe's vertex to its query's, weighted by the
    inverse of its covariance."""
    return gk.Edges(
        np.array([c["keyframe"] for c in closures], dtype=int),
        np.array([c["query"] for c in closures], dtype=int),
        np.array([c["pose"] for c in closures]).reshape(-1, 4, 4),
        np.array([np.linalg.inv(c) for c in covariances]).reshape(-1, 6, 6),
    )


def scores(estimate: np.ndarray, truth: np.ndarray, revisits: np.ndarray) -> dict[str, float]:
    """Against the truth: each scan's position and rotation (vertex 0 held at its true pose,
    no alignment), and the map where the drive comes back: each revisit pair's (``revisits``,
    (k, 2): query, earlier scan) relative pose."""
    if len(revisits) == 0:
        raise ValueError("the town's ground truth has no revisit pair: nothing to score there")
    d = gk.position_errors(estimate, truth)
    rot = gk.rotation_errors_deg(estimate, truth)
    q, r = revisits[:, 0], revisits[:, 1]
    est = gk.inverse(estimate[r]) @ estimate[q]
    true = gk.inverse(truth[r]) @ truth[q]
    rel_d = gk.position_errors(est, true)
    rel_rot = gk.rotation_errors_deg(est, true)
    return {
        "position_rms_m": float(np.sqrt((d**2).mean())),
        "position_max_m": float(d.max()),
        "within_0.1m": float((d <= NEAR_M).mean()),
        "rotation_rms_deg": float(np.sqrt((rot**2).mean())),
        "revisit_rms_m": float(np.sqrt((rel_d**2).mean())),
        "revisit_rotation_rms_deg": float(np.sqrt((rel_rot**2).mean())),
    }


def mean_of(runs: list[dict[str, float]]) -> dict[str, float]:
    return {k: float(np.mean([r[k] for r in runs])) for k in runs[0]}


def town_graph(
    town: dict[str, Any],
    truth: np.ndarray,
    revisits: np.ndarray,
    served: tuple[str, float],
    constant: np.ndarray,
    sigma: np.ndarray,
    seeds: int,
) -> dict[str, Any]:
    """One town's closures optimised each way over ``seeds`` odometry draws, scored on
    ``truth`` and its ``revisits`` (:func:`scores`)."""
    closures = town["right"] + town["wrong_closures"]
    wrong = {c["query"] for c in town["wrong_closures"]}  # a query has one closure
    covs = [posecov.covariance(c["hessian"], c["residual"], *served) for c in closures]
    kept = [(c, v) for c, v in zip(closures, covs, strict=True) if v is not None]
    edges = {
        "served": loop_edges([c for c, _ in kept], [v for _, v in kept]),
        "constant": loop_edges([c for c, _ in kept], [constant] * len(kept)),
    }
    out: dict[str, Any] = {
        "town": town["town"],
        "scans": len(truth),
        "revisit_pairs": len(revisits),
        "loop_edges": len(kept),
        "wrong_loop_edges": sum(c["query"] in wrong for c, _ in kept),
        "without_covariance": len(closures) - len(kept),
        "runs": {w: [] for w in ("dead_reckoning", *WAYS)},
    }
    for seed in range(seeds):
        odo = odometry(truth, sigma, np.random.default_rng(seed))
        start = dead_reckoning(truth[0], odo)
        out["runs"]["dead_reckoning"].append(scores(start, truth, revisits))
        for way in WAYS:
            solved = gk.optimise(start, gk.Edges.join(odo, edges[way]))
            if not (solved.converged and np.isfinite(solved.poses).all()):
                raise RuntimeError(f"{town['town']} seed {seed} {way}: did not converge")
            out["runs"][way].append(
                {**scores(solved.poses, truth, revisits), "iterations": solved.iterations}
            )
    out["mean"] = {w: mean_of(r) for w, r in out["runs"].items()}
    return out


def true_poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The town's true scan poses (n, 4, 4), in the frame its closures' poses are in, and
    its revisit pairs (query, earlier scan; its ground truth's loops)."""
    loops = LoopGroundTruth.load(path / "ground_truth" / "loops.npz")
    pairs = np.stack([loops.query, loops.reference], 1)[loops.is_loop]
    return np.asarray(open_sequence(path).poses, dtype=np.float64), pairs.astype(int)


def read_constant(path: Path, model_id: str) -> tuple[np.ndarray, dict[str, Any]]:
    """The validation closures' one ellipsoid (its covariance times its scale) from
    ``pose_covariance.py --calibrate``'s JSON, which must be of this model."""
    val = read_fit(path, model_id)
    scale = float(val["fits"]["constant"]["scale"])
    source = {"file": val["from"], "town": val["town"], "scale": scale}
    return scale * np.asarray(val["constant_covariance"]), source


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, default=ROOT / "models" / "overlapmamba-hdl64.onnx")
    ap.add_argument("--town", type=Path, action="append", help="default: data/synth/test")
    ap.add_argument(
        "--constant-from",
        type=Path,
        default=REPORTS / "service" / "pose_covariance.json",
        help="pose_covariance.py --calibrate's JSON for this model (the one ellipsoid)",
    )
    ap.add_argument("--seeds", type=int, default=3, help="odometry noise draws a town")
    for flag, default, names, unit in (
        ("--sigma-m", (0.02, 0.02, 0.02), ("X", "Y", "Z"), "metres"),
        ("--sigma-deg", (0.05, 0.05, 0.1), ("ROLL", "PITCH", "YAW"), "degrees"),
    ):
        ap.add_argument(
            flag,
            type=float,
            nargs=3,
            default=default,
            metavar=names,
            help=f"odometry noise a step, {unit}",
        )
    ap.add_argument("--json", type=Path, default=REPORTS / "service" / "pose-graph-test.json")
    args = ap.parse_args()
    if args.seeds < 1:
        ap.error("--seeds must be ≥ 1")
    if min(*args.sigma_m, *args.sigma_deg) <= 0:
        ap.error("--sigma-m and --sigma-deg must be > 0")
    towns = args.town or [ROOT / "data" / "synth" / "test"]
    if any(t.name.startswith("val") for t in towns):
        ap.error("score on test towns; the constant ellipsoid was fitted on val")
    enc = Encoder(args.model)
    served = served_settings(enc.meta)
    cov = served.covariance
    if cov.estimator is None or cov.scale is None:
        raise SystemExit(f"{args.model} carries no covariance calibration: nothing to score")
    constant, source = read_constant(args.constant_from, enc.model_id)
    sigma = np.array([*args.sigma_m, *np.radians(args.sigma_deg)])
    report: dict[str, Any] = {
        **provenance(),
        "model_id": enc.model_id,
        "served": {"estimator": cov.estimator, "scale": cov.scale},
        "constant": source,
        "odometry_sigma": {"m": list(args.sigma_m), "deg": list(args.sigma_deg)},
        "seeds": args.seeds,
        "towns": [],
    }
    rerank = served_rerank(enc.meta)
    for path in towns:
        town = town_closures(enc, path, served, rerank)
        truth, revisits = true_poses(path)
        served_cov = (cov.estimator, cov.scale)
        report["towns"].append(
            town_graph(town, truth, revisits, served_cov, constant, sigma, args.seeds)
        )
    table = Table(title=f"pose graph after optimisation ({enc.model_id}, {args.seeds} seeds)")
    for col in ("town", "loop edges", "loop weights", "position RMS / max (m)", "within 0.1 m"):
        table.add_column(col, justify="right")
    for col in ("rotation RMS (°)", "revisits RMS (m / °)"):
        table.add_column(col, justify="right")
    for t in report["towns"]:
        for way in ("dead_reckoning", *WAYS):
            m = t["mean"][way]
            table.add_row(
                Path(t["town"]).name,
                str(t["loop_edges"]),
                way,
                f"{m['position_rms_m']:.3f} / {m['position_max_m']:.3f}",
                f"{m['within_0.1m']:.3f}",
                f"{m['rotation_rms_deg']:.3f}",
                f"{m['revisit_rms_m']:.3f} / {m['revisit_rotation_rms_deg']:.3f}",
            )
    Console().print(table)
    write_report(args.json, report)
    Console().print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
