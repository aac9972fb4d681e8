"""Optimise a ``.g2o`` pose graph with GTSAM: the half of ``benchmarks/g2o_check.py`` that
runs under another Python, one with GTSAM's bindings (``pip install gtsam``). It imports
neither this project nor scipy.

The file is read by GTSAM's own ``readG2o`` (3-D), which makes each ``EDGE_SE3:QUAT`` a
``BetweenFactorPose3`` and ignores ``FIX`` lines: each fixed vertex is held by a prior of
σ 1e-6 at its written pose. Levenberg–Marquardt from the written poses.

    python benchmarks/gtsam_solve.py GRAPH.g2o POSES.npy [--iterations 200]

Writes the optimised poses (n, 4, 4), in the order of the vertex ids, and prints one JSON
line (``solve_kit.hand_back``): the χ² (twice GTSAM's error) of the file's factors before
and after, and the versions.
"""

from __future__ import annotations

import numpy as np
from solve_kit import arguments, hand_back


def main() -> None:
    import gtsam  # type: ignore[import-not-found]  # only in the Python that runs this

    args = arguments(__doc__)
    graph, initial = gtsam.readG2o(args.graph, True)
    factors = graph.size()
    with open(args.graph) as fh:
        fixed = [int(f[1]) for f in (line.split() for line in fh) if f and f[0] == "FIX"]
    held = gtsam.NonlinearFactorGraph(graph)
    for i in fixed:
        held.add(
            gtsam.PriorFactorPose3(i, initial.atPose3(i), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6))
        )
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(args.iterations)
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-12)
    optimizer = gtsam.LevenbergMarquardtOptimizer(held, initial, params)
    result = optimizer.optimize()
    keys = sorted(int(k) for k in result.keys())  # noqa: SIM118 (gtsam.Values, not a dict)
    hand_back(
        args.poses,
        np.array([result.atPose3(k).matrix() for k in keys]),
        "gtsam",
        chi2_start=2 * graph.error(initial),
        chi2=2 * graph.error(result),
        iterations=optimizer.iterations(),
        vertices=len(keys),
        edges=factors,
        fixed=fixed,
    )


if __name__ == "__main__":
    main()
