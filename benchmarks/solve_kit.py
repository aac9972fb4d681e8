"""What ``g2o_solve.py`` and ``gtsam_solve.py`` hand back to ``g2o_check.py``, each run
under a Python with its back end's bindings (numpy only here, nothing of this project)."""

from __future__ import annotations

import argparse
import json
from importlib.metadata import version

import numpy as np


def hand_back(out: str, poses: np.ndarray, package: str, **said: object) -> None:
    """Save the optimised poses (n, 4, 4) at ``out`` and print one JSON line: what the back
    end said (χ² before and after, iterations, the graph's size, the fixed vertices) with
    the bindings' and numpy's versions."""
    np.save(out, poses)
    print(json.dumps({**said, package: version(package), "numpy": np.__version__}))


def arguments(doc: str) -> argparse.Namespace:
    """Both scripts' command line: ``GRAPH.g2o POSES.npy [--iterations N]``."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("graph")
    ap.add_argument("poses")
    ap.add_argument("--iterations", type=int, default=200)
    return ap.parse_args()
