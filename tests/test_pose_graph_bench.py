"""benchmarks/graph_kit.py, the pose-graph optimiser the covariance benchmark runs, and
benchmarks/pose_graph.py's graph: the optimum is right where it is known, the weights do
what a covariance is for, and the benchmark's pieces count what they build."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import benchmark_module

from overlapmamba.core import posecov

gk = benchmark_module("graph_kit")


def circle(n: int = 240, laps: float = 2.0) -> np.ndarray:
    """A drive round a 20 m circle, rolling and pitching a little."""
    ang = np.linspace(0, 2 * np.pi * laps, n)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3], poses[:, 1, 3] = 20 * np.cos(ang), 20 * np.sin(ang)
    poses[:, 2, 3] = 0.3 * np.sin(3 * ang)
    twist = np.c_[np.zeros((n, 3)), 0.02 * np.sin(ang), 0.03 * np.cos(ang), ang + np.pi / 2]
    poses[:, :3, :3] = gk.exp_se3(twist)[:, :3, :3]
    return poses


def test_exp_and_log_are_posecov_s_and_invert_each_other():
    xi = np.random.default_rng(0).normal(size=(40, 6)) * [2, 2, 2, 0.8, 0.8, 0.8]
    poses = gk.exp_se3(xi)
    np.testing.assert_allclose(gk.log_se3(poses), xi, atol=1e-10)
    for p in poses[:5]:  # the service's convention: δ = Log(estimate⁻¹ · truth)
        np.testing.assert_allclose(gk.log_se3(p[None])[0], posecov.error(np.eye(4), p), atol=1e-12)
    np.testing.assert_allclose(
        gk.inverse(poses) @ poses, np.tile(np.eye(4), (40, 1, 1)), atol=1e-12
    )
    np.testing.assert_allclose(gk.log_se3(gk.exp_se3(np.zeros((1, 6)))), 0.0, atol=0)


def test_the_optimum_is_the_truth_when_every_edge_is_and_undoes_drift_when_loops_are():
    truth = circle()
    n, rng = len(truth), np.random.default_rng(1)
    sigma = np.array([0.03, 0.02, 0.01, 0.002, 0.002, 0.006])
    pose_graph = benchmark_module("pose_graph")
    odo = pose_graph.odometry(truth, sigma, rng)
    start = pose_graph.dead_reckoning(truth[0], odo)
    drift = gk.position_errors(start, truth)
    assert drift.max() > 1.0  # the drift the loops must undo
    a = np.arange(0, n // 2, 6)
    b = a + n // 2
    loops = gk.Edges(
        a, b, gk.inverse(truth[a]) @ truth[b], np.tile(np.eye(6) * 1e4, (len(a), 1, 1))
    )
    exact = gk.Edges(odo.a, odo.b, gk.inverse(truth[:-1]) @ truth[1:], odo.info)
    solved = gk.optimise(start, gk.Edges.join(exact, loops))
    assert solved.converged and solved.cost < 1e-12
    assert gk.position_errors(solved.poses, truth).max() < 1e-4
    assert gk.rotation_errors_deg(solved.poses, truth).max() < 1e-4
    solved = gk.optimise(start, gk.Edges.join(odo, loops))  # noisy odometry, true loops
    assert solved.converged and solved.cost < solved.cost_start / 100
    assert gk.position_errors(solved.poses, truth).max() < drift.max() / 5
    with pytest.raises(ValueError, match="at least one edge"):
        gk.optimise(
            start, gk.Edges(np.zeros(0, int), np.zeros(0, int), loops.z[:0], loops.info[:0])
        )
    with pytest.raises(ValueError, match="outside 0 … 239"):
        gk.optimise(start, gk.Edges(np.array([0]), np.array([240]), loops.z[:1], loops.info[:1]))


def test_the_optimum_is_stationary_even_with_an_edge_metres_off_and_a_failure_says_so():
    """An edge 3 m and 17° off (a wrong closure): the cost's gradient at the answer, by
    finite differences of right perturbations, is nil (the exact Jacobian of Log, not its
    first-order stand-in); an edge that cannot be evaluated reports no convergence."""
    truth = circle(40, 1.0)
    odo = benchmark_module("pose_graph").odometry(truth, np.full(6, 0.01), np.random.default_rng(5))
    start = benchmark_module("pose_graph").dead_reckoning(truth[0], odo)
    wrong = gk.inverse(truth[:1]) @ truth[20:21] @ gk.exp_se3(np.array([[3.0, -1, 0.2, 0, 0, 0.3]]))
    loop = gk.Edges(np.array([0]), np.array([20]), wrong, np.eye(6)[None] * 1e2)
    graph = gk.Edges.join(odo, loop)
    solved = gk.optimise(start, graph)
    assert solved.converged
    base, h, grad = gk.cost(solved.poses, graph), 1e-6, []
    for v in (5, 20, 33):
        for k in range(6):
            xi = np.zeros((40, 6))
            xi[v, k] = h
            up = gk.cost(solved.poses @ gk.exp_se3(xi), graph)
            down = gk.cost(solved.poses @ gk.exp_se3(-xi), graph)
            grad.append((up - down) / (2 * h))
    assert np.abs(grad).max() < 1e-3 * max(1.0, base) ** 0.5, (np.abs(grad).max(), base)
    broken = gk.Edges(loop.a, loop.b, loop.z * np.nan, loop.info)
    assert not gk.optimise(start, gk.Edges.join(odo, broken)).converged


def test_a_loose_direction_weighted_as_loose_does_not_bend_the_map():
    """Loop edges whose measurement is off along query-frame x, where their covariance says
    they know nothing (a corridor): weighted by that covariance the map keeps to the
    odometry; weighted as one round ellipsoid the error bends it."""
    truth = circle(120, 1.0)
    n = len(truth)
    sigma = np.array([0.01, 0.01, 0.01, 0.0005, 0.0005, 0.001])
    odo = benchmark_module("pose_graph").odometry(truth, sigma, np.random.default_rng(2))
    start = benchmark_module("pose_graph").dead_reckoning(truth[0], odo)
    a = np.arange(0, 60, 4)
    b = (a + 60) % n
    off = gk.exp_se3(np.tile([0.5, 0, 0, 0, 0, 0], (len(a), 1)))  # 0.5 m along x
    z = gk.inverse(truth[a]) @ truth[b] @ off
    loose = np.diag([10.0**2, 0.02**2, 0.02**2, 1e-3**2, 1e-3**2, 1e-3**2])
    round_ = np.diag([0.02**2] * 3 + [1e-3**2] * 3)
    err = {}
    for name, cov in (("loose", loose), ("round", round_)):
        info = np.tile(np.linalg.inv(cov), (len(a), 1, 1))
        solved = gk.optimise(start, gk.Edges.join(odo, gk.Edges(a, b, z, info)))
        err[name] = np.sqrt((gk.position_errors(solved.poses, truth) ** 2).mean())
    assert err["loose"] < err["round"] / 3, err


def test_the_benchmark_builds_its_graph_from_the_closures_and_scores_each_way(tmp_path):
    pose_graph = benchmark_module("pose_graph")
    truth = circle(90, 1.5)
    rng = np.random.default_rng(3)

    def closure(j: int, i: int, wrong: bool = False) -> dict:
        rel = gk.inverse(truth[j : j + 1]) @ truth[i : i + 1]
        if wrong:
            rel = rel @ gk.exp_se3(np.array([[3.0, 0, 0, 0, 0, 0.2]]))
        hessian = posecov.swap_blocks(np.diag([1e4] * 3 + [1e6] * 3) * rng.uniform(0.5, 2))
        return {"query": i, "keyframe": j, "pose": rel[0], "hessian": hessian, "residual": 0.2}

    town = {
        "town": "data/synth/test-x",
        "right": [closure(j, j + 60) for j in range(0, 30, 3)],
        "wrong_closures": [closure(5, 70, wrong=True)],
    }
    town["right"][0]["hessian"] = np.zeros((6, 6))  # no covariance: left out, counted
    constant = np.diag([0.02**2] * 3 + [1e-3**2] * 3)
    sigma = np.array([0.02, 0.02, 0.02, 0.001, 0.001, 0.002])
    revisits = np.array([[i, i - 60] for i in range(60, 90)])
    out = pose_graph.town_graph(town, truth, revisits, ("hessian", 1.0), constant, sigma, 2)
    assert out["scans"] == 90 and out["loop_edges"] == 10 and out["without_covariance"] == 1
    assert out["revisit_pairs"] == 30
    with pytest.raises(ValueError, match="no revisit pair"):
        pose_graph.scores(truth, truth, np.zeros((0, 2), int))
    assert out["wrong_loop_edges"] == 1
    assert set(out["runs"]) == {"dead_reckoning", "served", "constant"}
    assert all(len(r) == 2 for r in out["runs"].values())
    mean = out["mean"]  # the wrong edge (3 m off, weighted as sure as the others) bends it
    assert mean["served"]["position_rms_m"] > mean["dead_reckoning"]["position_rms_m"]
    town["wrong_closures"] = []
    out = pose_graph.town_graph(town, truth, revisits, ("hessian", 1.0), constant, sigma, 2)
    mean = out["mean"]
    assert out["wrong_loop_edges"] == 0 and out["loop_edges"] == 9
    for way in ("served", "constant"):
        assert mean[way]["position_rms_m"] < mean["dead_reckoning"]["position_rms_m"] / 2
        assert mean[way]["revisit_rms_m"] < mean["dead_reckoning"]["revisit_rms_m"] / 5
        assert 0 <= mean[way]["within_0.1m"] <= 1 and mean[way]["iterations"] >= 1
    # the constant ellipsoid comes from the calibration's JSON of the same model only
    report = {
        "model_id": "om-1",
        "val": {
            "town": "data/synth/val",
            "constant_covariance": constant.tolist(),
            "fits": {"constant": {"scale": 2.0}},
        },
    }
    path = pose_graph.ROOT / "reports" / "service" / "pose_covariance.json"
    cov, source = pose_graph.read_constant(path, json.loads(path.read_text())["model_id"])
    assert cov.shape == (6, 6) and source["file"] == "reports/service/pose_covariance.json"
    other = tmp_path / "other.json"
    other.write_text(json.dumps(report))
    with pytest.raises(SystemExit, match="is of model om-1, not om-2"):
        pose_graph.read_constant(other, "om-2")


def test_the_g2o_check_writes_what_it_compares_and_reads_the_file_back(tmp_path):
    """benchmarks/g2o_check.py: the client's file for each back end carries each closure's
    information as posecov converts it for that reader; g2o_solve.py's reading of a line
    (run under g2o's Python) gives back the pose and information written; a Python without
    a back end's bindings is refused with what to install."""
    import importlib.util
    import sys

    from overlapmamba.client.posegraph import file_information, odometry_information, read_g2o
    from overlapmamba.core.poses import from_quaternion

    check, solve = benchmark_module("g2o_check"), benchmark_module("g2o_solve")
    truth = check.circle_drive(120)
    loops = check.closures(truth, np.random.default_rng(1))
    assert loops and all(q >= 70 and k < 60 for k, q, *_ in loops)
    for k, q, rel, cov in loops:
        assert np.all(np.linalg.eigvalsh(cov) > 0)
        assert np.linalg.norm(rel[:3, 3] - (np.linalg.inv(truth[k]) @ truth[q])[:3, 3]) < 0.5
    written = {}
    for reader in ("g2o", "gtsam"):
        path = tmp_path / f"{reader}.g2o"
        check.client_graph(truth, loops, (0.03, 0.15), reader).write(path)
        vertices, edges = read_g2o(path)
        written[reader] = edges
        assert len(vertices) == 120 and len(edges) == 119 + len(loops)
        got = edges[119][3]
        assert np.allclose(got, file_information(loops[0][3], reader))
        assert np.allclose(edges[0][3], odometry_information(0.03, 0.15, reader))
        line = path.read_text().splitlines()[120 + 119].split()  # the first loop edge
        assert line[0] == "EDGE_SE3:QUAT" and (int(line[1]), int(line[2])) == loops[0][:2]
        assert np.allclose(solve.information(line[10:31]), got)
        q = np.array(line[6:10], dtype=float)
        assert np.allclose(solve.rotation(q), from_quaternion(np.zeros(3), q)[:3, :3])
        assert np.allclose(solve.rotation(q), loops[0][2][:3, :3], atol=1e-9)
    # the g2o file's information is the GTSAM file's with the rotation's rows and columns
    # doubled, on every edge: correlations and all
    two = np.diag([1.0, 1, 1, 2, 2, 2])
    for (*_, g2o_info), (*_, gtsam_info) in zip(written["g2o"], written["gtsam"], strict=True):
        assert np.allclose(g2o_info, two @ gtsam_info @ two)
    a, b = truth[:5], truth[:5].copy()
    b[2, 0, 3] += 0.01
    assert check.gaps(a, b)["position_max_m"] == pytest.approx(0.01)
    for backend, module, needs in (("g2o", "g2o", "g2o-python"), ("gtsam", "gtsam", "gtsam")):
        if importlib.util.find_spec(module) is None:  # this Python lacks it: refused, by name
            with pytest.raises(SystemExit, match=f"pip install {needs}"):
                check.solve(backend, sys.executable, tmp_path / "g2o.g2o", 5)
