"""Optimise a ``.g2o`` pose graph with g2o itself: the half of ``benchmarks/g2o_check.py``
that runs under another Python, one with g2o's bindings (``pip install g2o-python
"numpy<2"``: its wheels crash with numpy 2). It imports neither this project nor scipy.

g2o-python does not register the file types its ``load`` would need (it reads nothing and
says it succeeded), so the file is read here by g2o's documented format and built as g2o's
own ``VertexSE3`` and ``EdgeSE3``: ``VERTEX_SE3:QUAT id x y z qx qy qz qw``; ``EDGE_SE3:QUAT
a b x y z qx qy qz qw`` then the information's upper triangle row by row (21 numbers);
``FIX id``. g2o's error, Jacobians, update and Levenberg–Marquardt do the rest.

    python benchmarks/g2o_solve.py GRAPH.g2o POSES.npy [--iterations 200]

Writes the optimised poses (n, 4, 4), in the order of the vertex ids, and prints one JSON
line (``solve_kit.hand_back``): the χ² g2o computes before and after, and the versions.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from solve_kit import arguments, hand_back


def rotation(q: np.ndarray) -> np.ndarray:
    """The rotation matrix of a unit quaternion (x, y, z, w)."""
    x, y, z, w = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def isometry(fields: list[str]) -> Any:
    """x y z qx qy qz qw → g2o's Isometry3d."""
    import g2o  # type: ignore[import-not-found]  # only in the Python that runs this

    f = np.array(fields, dtype=np.float64)
    return g2o.Isometry3d(rotation(f[3:7]), f[:3])


def information(fields: list[str]) -> np.ndarray:
    """The upper triangle, row by row → the symmetric 6 × 6."""
    info = np.zeros((6, 6))
    info[np.triu_indices(6)] = np.array(fields, dtype=np.float64)
    return info + np.triu(info, 1).T


def main() -> None:
    args = arguments(__doc__)
    import g2o

    opt = g2o.SparseOptimizer()
    solver = g2o.BlockSolverSE3(g2o.LinearSolverEigenSE3())
    algorithm = g2o.OptimizationAlgorithmLevenberg(solver)
    opt.set_algorithm(algorithm)
    vertices: dict[int, Any] = {}
    edges, fixed = [], []
    with open(args.graph) as fh:
        for n, line in enumerate(fh, 1):
            f = line.split()
            if not f:
                continue
            if f[0] == "VERTEX_SE3:QUAT" and len(f) == 9:
                v = g2o.VertexSE3()
                v.set_id(int(f[1]))
                v.set_estimate(isometry(f[2:9]))
                opt.add_vertex(v)
                vertices[int(f[1])] = v
            elif f[0] == "EDGE_SE3:QUAT" and len(f) == 31:
                e = g2o.EdgeSE3()
                e.set_vertex(0, vertices[int(f[1])])
                e.set_vertex(1, vertices[int(f[2])])
                e.set_measurement(isometry(f[3:10]))
                e.set_information(information(f[10:31]))
                opt.add_edge(e)
                edges.append(e)
            elif f[0] == "FIX" and len(f) == 2:
                fixed.append(int(f[1]))
            else:
                raise SystemExit(f"{args.graph}:{n}: not a line this reader knows: {line!r}")
    for i in fixed:
        vertices[i].set_fixed(True)
    opt.initialize_optimization()
    opt.compute_active_errors()
    start = opt.active_chi2()
    iterations = opt.optimize(args.iterations)
    opt.compute_active_errors()
    hand_back(
        args.poses,
        np.array([vertices[i].estimate().matrix() for i in sorted(vertices)]),
        "g2o-python",
        chi2_start=start,
        chi2=opt.active_chi2(),
        iterations=iterations,
        vertices=len(vertices),
        edges=len(edges),
        fixed=fixed,
    )


if __name__ == "__main__":
    main()
