"""Do g2o and GTSAM themselves read the client's pose graph as the covariance means it?

``overlapmamba-client observe --g2o`` writes a verified closure's covariance as the
information of ``EDGE_SE3:QUAT``, for the back end named by ``--g2o-for``
(``overlapmamba.client.posegraph.file_information``): g2o's error takes the quaternion's
vector part, half the rotation vector, so a file for g2o has the rotation's rows and
columns doubled; GTSAM's ``readG2o`` reads the same block as over the rotation vector, so a
file for GTSAM holds the inverse covariance as it is. This writes a drifting drive's graph
with the client's own ``PoseGraph`` both ways and optimises each file with g2o
(``benchmarks/g2o_solve.py`` under ``--python``, a Python with g2o's bindings) and, with
``--gtsam-python``, GTSAM (``benchmarks/gtsam_solve.py``); neither is a dependency here. The
yardstick is ``benchmarks/graph_kit.py``'s optimum in posecov's convention (the error
Log(Z⁻¹ · T_a⁻¹ · T_b), each loop edge weighted by the inverse of the covariance the server
would answer, each odometry edge by its σ's), from the same poses and measurements.

A file read by the back end it was written for should land on that optimum, to the order
the errors differ by (g2o takes the relative pose's translation as it is, posecov the SE(3)
logarithm's: second order in the residuals); one written for the other back end weighs
every rotation four times too much or too little and should not: the check can fail.

The drive: ``--scans`` poses on nearly two laps of a 40 m circle rising and falling, the
odometry a step drawn with ``--odometry-sigma-m`` and ``--odometry-sigma-deg`` per axis (the
drive's poses dead-reckoned from it, as a robot's odometry gives them), and a loop closure
from every third scan of the second lap onto the nearest scan of the first, its relative
pose the truth perturbed by a draw of its own covariance (correlated, different per
closure). Scored: each optimum's positions against graph_kit's (largest and RMS gap), the
largest rotation gap, each one's position RMS against the truth, and the χ² each reports.

    python benchmarks/g2o_check.py --python PY [--gtsam-python PY] [--out …]

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
import pose_graph
from bench_kit import provenance
from reports_kit import REPORTS, write_report
from rich.console import Console

from overlapmamba.client.posegraph import READERS, PoseGraph


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
    poses: np.ndarray, loops: list, sigma: tuple[float, float], reader: str
) -> PoseGraph:
    """The graph as ``observe --g2o --g2o-for READER`` makes it: a vertex a scan at the
    drive's pose, the odometry's σ (metres, degrees) on each consecutive pair, a loop edge a
    closure with its covariance."""
    g = PoseGraph.for_reader(*sigma, len(poses), reader)
    for i, p in enumerate(poses):
        g.scan(i, p, f"scan-{i}")
    for k, q, rel, cov in loops:
        if not g.closure(q, f"scan-{k}", rel, cov):
            raise AssertionError(f"closure {q} → {k} left out: {g.left_out}")
    return g


def gaps(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    """Two sets of poses' largest and RMS position gap (m) and largest rotation gap (°)."""
    d = gk.position_errors(a, b)
    return {
        "position_max_m": float(d.max()),
        "position_rms_m": float(np.sqrt((d**2).mean())),
        "rotation_max_deg": float(gk.rotation_errors_deg(a, b).max()),
    }


def position_rms(poses: np.ndarray, truth: np.ndarray) -> float:
    return gaps(poses, truth)["position_rms_m"]


SOLVERS = {  # back end → its script, and what the Python that runs it needs
    "g2o": ("g2o_solve.py", 'g2o\'s bindings: pip install g2o-python "numpy<2"'),
    "gtsam": ("gtsam_solve.py", "GTSAM's bindings: pip install gtsam"),
}


def solve(
    backend: str, python: str, graph: Path, iterations: int
) -> tuple[np.ndarray, dict[str, Any]]:
    """``backend``'s optimum of ``graph`` (its script under ``python``) and what it said."""
    script, needs = SOLVERS[backend]
    out = graph.with_name(f"{graph.stem}-{backend}.npy")
    cmd = [python, str(Path(__file__).with_name(script)), str(graph), str(out)]
    run = subprocess.run([*cmd, "--iterations", str(iterations)], capture_output=True, text=True)
    if run.returncode != 0:
        raise SystemExit(
            f"{' '.join(cmd)} failed ({run.returncode}): {run.stderr.strip()[-600:]}\n"
            f"{python} needs {needs}"
        )
    return np.load(out), json.loads(run.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--python", required=True, help="a Python with g2o-python and numpy<2")
    ap.add_argument("--gtsam-python", help="a Python with gtsam: GTSAM reads both files too")
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
    odometry = pose_graph.odometry(truth, sigma, rng)  # as the covariance benchmark draws it
    drift = pose_graph.dead_reckoning(truth[0], odometry)
    loops = closures(truth, rng)
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
        "gtsam_python": args.gtsam_python,
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
    pythons = {"g2o": args.python} | ({"gtsam": args.gtsam_python} if args.gtsam_python else {})
    odo_sigma = (args.odometry_sigma_m, args.odometry_sigma_deg)
    report["solvers"] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for reader in READERS:
            path = Path(tmp) / f"for-{reader}.g2o"
            client_graph(drift, loops, odo_sigma, reader).write(path)
            for backend, python in pythons.items():
                solved, said = solve(backend, python, path, args.iterations)
                report["solvers"].setdefault(backend, {})[reader] = {
                    "said": said,
                    "gap_to_graph_kit": gaps(solved, ours.poses),
                    "position_rms_m": position_rms(solved, truth),
                }
    write_report(args.out, report)
    for backend, files in report["solvers"].items():
        for reader, x in files.items():
            d = x["gap_to_graph_kit"]
            Console().print(
                f"{backend} reading the file for {reader}: positions within "
                f"{d['position_max_m']:.2e} m of graph_kit's, rotations "
                f"{d['rotation_max_deg']:.2e}°; "
                f"χ² {x['said']['chi2']:.4f} against {report['graph_kit']['chi2']:.4f}",
                highlight=False,
            )
    Console().print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
