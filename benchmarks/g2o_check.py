"""Does g2o itself read the client's pose graph as the covariance's convention means it?

``overlapmamba-client observe --g2o`` writes a verified closure's covariance as the
information of g2o's ``EDGE_SE3:QUAT`` (``overlapmamba.core.posecov.g2o_information``: g2o's
error is the quaternion's vector part, half the rotation vector, so the rotation rows and
columns are scaled). This writes a drifting drive's graph with the client's own
``PoseGraph`` and optimises it twice:

- with g2o (``benchmarks/g2o_solve.py``, run by ``--python``: a Python with g2o's bindings,
  which are no dependency of this project), from the file;
- with ``benchmarks/graph_kit.py`` in posecov's convention (the error Log(Z⁻¹ · T_a⁻¹ ·
  T_b), each loop edge weighted by the inverse of the covariance the server would answer,
  each odometry edge by its σ's), from the same poses and measurements.

When the file says what the convention says, the two optima agree to the order the two
errors differ by (g2o takes the relative pose's translation as it is, posecov the SE(3)
logarithm's: second order in the residuals; the half angle is scaled away). A control file
shows that the comparison can fail: the same graph with its rotation information read as
GTSAM's ``readG2o`` reads it (over the rotation vector, four times g2o's weight), optimised
by g2o.

The drive: ``--scans`` poses on nearly two laps of a 40 m circle rising and falling, the
odometry a step drawn with ``--odometry-sigma-m`` and ``--odometry-sigma-deg`` per axis (the
drive's poses dead-reckoned from it, as a robot's odometry gives them), and a loop closure
from every third scan of the second lap onto the nearest scan of the first, its relative
pose the truth perturbed by a draw of its own covariance (correlated, different per
closure). Scored: each optimum's positions against the other's (largest and RMS gap), the
largest rotation gap, each one's position RMS against the truth, and the χ² each reports.

    python benchmarks/g2o_check.py --python /path/to/python-with-g2o [--out …]

Writes JSON (default reports/client/g2o-check.json).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import graph_kit as gk
import numpy as np
from bench_kit import provenance
from reports_kit import REPORTS, write_report
from rich.console import Console

from overlapmamba.client.posegraph import PoseGraph, odometry_information

HALF = np.diag([1.0, 1.0, 1.0, 2.0, 2.0, 2.0])  # g2o's error → posecov's δ (D⁻¹)


def circle_drive(scans: int, laps: float = 1.9, radius: float = 40.0) -> np.ndarray:
    """(scans, 4, 4) true poses: ``laps`` laps of a circle, heading along it, rising and
    falling 0.3 m three times a lap."""
    t = np.linspace(0.0, 2 * np.pi * laps, scans)
    xi = np.zeros((scans, 6))
    xi[:, 5] = t + np.pi / 2
    poses = gk.exp_se3(xi)
    poses[:, 0, 3], poses[:, 1, 3] = radius * np.cos(t), radius * np.sin(t)
    poses[:, 2, 3] = 0.3 * np.sin(3 * t)
    return poses


def closures(truth: np.ndarray, rng: np.random.Generator) -> list[tuple[int, int, Any, Any]]:
    """(keyframe, query, relative pose, covariance): every third scan past the first lap
    onto the nearest scan before it, the truth perturbed on the right by a draw of a
    covariance of its own (σ of centimetres and tenths of a degree, correlated)."""
    n = len(truth)
    first = n // 2
    out = []
    for q in range(first + 10, n, 3):
        k = int(np.argmin(np.linalg.norm(truth[:first, :3, 3] - truth[q, :3, 3], axis=1)))
        a = rng.normal(size=(6, 6)) * 0.004
        cov = a @ a.T + np.diag([4e-4, 2e-4, 9e-4, 1e-6, 2e-6, 8e-6])
        noise = gk.exp_se3(rng.multivariate_normal(np.zeros(6), cov)[None])[0]
        out.append((k, q, np.linalg.inv(truth[k]) @ truth[q] @ noise, cov))
    return out


def client_graph(
    poses: np.ndarray, loops: list, odometry: np.ndarray, gtsam_reading: bool = False
) -> PoseGraph:
    """The graph as ``observe --g2o`` makes it: a vertex a scan at the drive's pose, the
    odometry's information on each consecutive pair, a loop edge a closure with its
    covariance. ``gtsam_reading``: the control, every rotation block as GTSAM reads g2o's
    (the information a covariance of D Σ D gives, D = diag(1, 1, 1, ½, ½, ½): four times the
    rotation's weight)."""
    g = PoseGraph(odometry=HALF @ odometry @ HALF if gtsam_reading else odometry,
                  others_from=len(poses))  # fmt: skip
    for i, p in enumerate(poses):
        g.scan(i, p, f"scan-{i}")
    for k, q, rel, cov in loops:
        c = np.linalg.inv(HALF) @ cov @ np.linalg.inv(HALF) if gtsam_reading else cov
        if not g.closure(q, f"scan-{k}", rel, c):
            raise AssertionError(f"closure {q} → {k} left out: {g.left_out}")
    return g


def gaps(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    """Two sets of poses' largest and RMS position gap (m) and largest rotation gap (°)."""
    d = np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=1)
    rot = gk.rotation_errors_deg(a, b)
    return {
        "position_max_m": float(d.max()),
        "position_rms_m": float(np.sqrt((d**2).mean())),
        "rotation_max_deg": float(rot.max()),
    }


def position_rms(poses: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt((np.linalg.norm(poses[:, :3, 3] - truth[:, :3, 3], axis=1) ** 2).mean()))


def g2o_solve(python: str, graph: Path, iterations: int) -> tuple[np.ndarray, dict[str, Any]]:
    """g2o's optimum of ``graph`` (``g2o_solve.py`` under ``python``) and what it said."""
    out = graph.with_suffix(".npy")
    script = Path(__file__).with_name("g2o_solve.py")
    cmd = [python, str(script), str(graph), str(out), "--iterations", str(iterations)]
    run = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if run.returncode != 0:
        raise SystemExit(
            f"{' '.join(cmd)} failed ({run.returncode}): {run.stderr.strip()[-600:]}\n"
            f'--python needs g2o\'s bindings: pip install g2o-python "numpy<2"'
        )
    return np.load(out), json.loads(run.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--python", required=True, help="a Python with g2o-python and numpy<2")
    ap.add_argument("--scans", type=int, default=400)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--odometry-sigma-m", type=float, default=0.03)
    ap.add_argument("--odometry-sigma-deg", type=float, default=0.15)
    ap.add_argument("--iterations", type=int, default=200)
    ap.add_argument("--out", type=Path, default=REPORTS / "client" / "g2o-check.json")
    args = ap.parse_args()
    if args.scans < 60:
        ap.error(f"--scans {args.scans}: at least 60, for a second lap to close loops")
    rng = np.random.default_rng(args.seed)
    truth = circle_drive(args.scans)
    sigma = np.r_[[args.odometry_sigma_m] * 3, [np.radians(args.odometry_sigma_deg)] * 3]
    steps = gk.inverse(truth[:-1]) @ truth[1:]
    measured = steps @ gk.exp_se3(rng.normal(size=(len(steps), 6)) * sigma)
    odometry = gk.Edges(
        np.arange(len(steps)), np.arange(1, args.scans), measured,
        np.tile(np.diag(1.0 / sigma**2), (len(steps), 1, 1)),
    )  # fmt: skip
    poses = [truth[0]]
    for z in measured:
        poses.append(poses[-1] @ z)
    drift = np.array(poses)
    loops = closures(truth, rng)
    info = odometry_information(args.odometry_sigma_m, args.odometry_sigma_deg)
    edges = gk.Edges.join(
        odometry,
        gk.Edges(
            np.array([k for k, *_ in loops]), np.array([q for _, q, *_ in loops]),
            np.array([r for *_, r, _ in loops]), np.array([np.linalg.inv(c) for *_, c in loops]),
        ),
    )  # fmt: skip
    ours = gk.optimise(drift, edges, fixed=0, iterations=args.iterations)
    if not ours.converged:
        raise SystemExit("graph_kit did not converge: more --iterations")
    report: dict[str, Any] = {
        **provenance(),
        "python": args.python,
        "graph": {
            "scans": args.scans,
            "loop_edges": len(loops),
            "seed": args.seed,
            "odometry_sigma": {"m": args.odometry_sigma_m, "deg": args.odometry_sigma_deg},
        },
        "graph_kit": {
            "chi2_start": 2 * ours.cost_start,
            "chi2": 2 * ours.cost,
            "iterations": ours.iterations,
        },
        "position_rms_m": {
            "dead_reckoning": position_rms(drift, truth),
            "graph_kit": position_rms(ours.poses, truth),
        },
    }
    with tempfile.TemporaryDirectory() as tmp:
        for name, gtsam_reading in (("client", False), ("control", True)):
            path = Path(tmp) / f"{name}.g2o"
            client_graph(drift, loops, info, gtsam_reading).write(path)
            solved, said = g2o_solve(args.python, path, args.iterations)
            report[name] = {"g2o": said, "gap_to_graph_kit": gaps(solved, ours.poses)}
            report["position_rms_m"][f"g2o_{name}"] = position_rms(solved, truth)
    write_report(args.out, report)
    c, k = report["client"], report["control"]
    Console().print(
        f"g2o {c['g2o']['g2o_python']} on the client's file against graph_kit: positions "
        f"within {c['gap_to_graph_kit']['position_max_m']:.2e} m, rotations "
        f"{c['gap_to_graph_kit']['rotation_max_deg']:.2e}°; χ² {c['g2o']['chi2']:.4f} against "
        f"{report['graph_kit']['chi2']:.4f}. The control (rotation read as GTSAM reads it): "
        f"{k['gap_to_graph_kit']['position_max_m']:.3f} m. Wrote {args.out}"
    )


if __name__ == "__main__":
    main()
