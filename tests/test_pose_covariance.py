"""The covariance a verified loop closure carries (overlapmamba.core.posecov): its
convention (the error on the right, in the query's frame, translation first), GICP's
Hessian read in it, the conversion g2o takes, the calibration benchmark's rule, and the
answer over HTTP and in the client."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import benchmark_module
from scipy.linalg import expm
from service_kit import OCTET, running, scan

from overlapmamba.core import posecov
from overlapmamba.core.poses import quaternion, rotation_z


def exp_se3(delta: np.ndarray) -> np.ndarray:
    """Exp of δ = (ρ, φ): the matrix exponential of its twist."""
    rho, phi = delta[:3], delta[3:]
    m = np.zeros((4, 4))
    m[:3, :3] = [[0, -phi[2], phi[1]], [phi[2], 0, -phi[0]], [-phi[1], phi[0], 0]]
    m[:3, 3] = rho
    return expm(m)


def pose(yaw: float, xyz: tuple[float, float, float]) -> np.ndarray:
    T = rotation_z(yaw)
    T[:3, 3] = xyz
    return T


@pytest.mark.parametrize("size", [1e-4, 0.05, 0.8])
def test_error_is_the_right_perturbation_translation_first(size):
    """error(T, T · Exp(δ)) = δ, small or large: the log of SE(3), not a difference of
    translations (which differs once the rotation is large)."""
    rng = np.random.default_rng(1)
    T = pose(33.0, (4.0, -2.0, 0.5)) @ exp_se3(rng.normal(0, 0.2, 6))
    for _ in range(5):
        delta = rng.normal(0, size, 6)
        assert np.allclose(posecov.error(T, T @ exp_se3(delta)), delta, atol=1e-9 + 1e-7 * size)
    assert np.allclose(posecov.error(T, T), 0.0)


def test_from_hessian_inverts_swaps_and_refuses_what_has_no_covariance():
    rng = np.random.default_rng(2)
    a = rng.normal(size=(6, 6))
    h = a @ a.T + 6 * np.eye(6)  # rotation first, as small_gicp orders it
    cov = posecov.from_hessian(h, 2.5)
    assert cov is not None
    inv = np.linalg.inv(h) * 2.5
    assert np.allclose(cov[:3, :3], inv[3:, 3:]) and np.allclose(cov[3:, 3:], inv[:3, :3])
    assert np.allclose(cov[:3, 3:], inv[3:, :3]) and np.allclose(cov, cov.T)
    singular = h.copy()
    singular[:, 0] = singular[0, :] = 0.0  # one rotation unconstrained
    assert posecov.from_hessian(singular, 1.0) is None
    assert posecov.from_hessian(np.full((6, 6), np.nan), 1.0) is None
    assert posecov.from_hessian(np.eye(4), 1.0) is None
    with pytest.raises(ValueError, match="scale must be > 0"):
        posecov.from_hessian(h, 0.0)
    # the residual estimator scales by the cost per inlier pair; none without one
    assert np.allclose(posecov.covariance(h, 0.5, "residual", 2.5), cov * 0.5)
    assert np.allclose(posecov.covariance(h, None, "hessian", 2.5), cov)
    assert posecov.covariance(h, 0.0, "residual", 1.0) is None
    assert posecov.covariance(None, 1.0, "hessian", 1.0) is None
    with pytest.raises(ValueError, match="allowed"):
        posecov.covariance(h, 1.0, "icp", 1.0)


def test_g2o_information_describes_g2o_s_own_error():
    """g2o's EDGE_SE3:QUAT error of a measurement off by Exp(δ) is (translation, quaternion
    vector part) of Exp(δ): sampled, its covariance is the inverse of g2o_information."""
    rng = np.random.default_rng(3)
    a = rng.normal(size=(6, 6)) * 0.01
    cov = a @ a.T + np.diag([4e-4, 1e-4, 9e-4, 1e-6, 4e-6, 1e-5])
    deltas = rng.multivariate_normal(np.zeros(6), cov, 40_000)
    errs = []
    for d in deltas:
        e = exp_se3(d)
        errs.append(np.r_[e[:3, 3], quaternion(e[:3, :3])[:3]])
    sample = np.cov(np.array(errs), rowvar=False)
    expected = np.linalg.inv(posecov.g2o_information(cov))
    scale = np.sqrt(np.outer(np.diag(expected), np.diag(expected)))
    assert np.abs(sample - expected).max() / scale.max() < 0.03
    assert np.abs(np.diag(sample) / np.diag(expected) - 1).max() < 0.05


def _registered(kf: np.ndarray) -> np.ndarray:
    """``kf`` registered from a query turned a quarter (T_keyframe←query: 90° and
    (0.5, −0.3, 0)) as the service registers it → the covariance (hessian, scale 1)."""
    from overlapmamba.service.registration import keyframe_geometry, prepare, register
    from overlapmamba.service.settings import VerifySettings
    from overlapmamba.service.verify import params_of

    T = pose(90.0, (0.5, -0.3, 0.0))
    q = (np.linalg.inv(T) @ np.c_[kf, np.ones(len(kf))].T).T[:, :3]
    p = params_of(VerifySettings())
    geometry = keyframe_geometry(prepare(kf.astype(np.float32), p), p)
    reg = register(prepare(q.astype(np.float32), p), geometry, -90.0, p)
    assert reg.hessian is not None and reg.residual is not None and reg.residual > 0
    cov = posecov.covariance(reg.hessian, reg.residual, "hessian", 1.0)
    assert cov is not None
    return cov


def test_gicp_hessian_leaves_free_what_the_geometry_leaves_free_in_the_query_frame():
    """Two long walls and a ground: the registration pins the position across the corridor
    and leaves it loose along it. The query is turned a quarter, so the corridor's axis (the
    keyframe's x) is the query's y: the loosest translation is y, read in the query's frame.
    A room of four walls on a sparse ground: its height is the loosest, while its yaw is the
    best pinned of all; only with the translation first does δ's z come out loosest."""
    rng = np.random.default_rng(0)
    n = 60_000
    across = rng.choice([-4.0, 4.0], n) + rng.normal(0, 0.02, n)  # 4 m either side
    walls = np.c_[rng.uniform(-30, 30, n), across, rng.uniform(-1.7, 1.3, n)]
    ground = np.c_[
        rng.uniform(-30, 30, n // 2), rng.uniform(-4, 4, n // 2), rng.normal(-1.73, 0.02, n // 2)
    ]
    sd = np.sqrt(np.diag(_registered(np.r_[walls, ground])))
    assert sd[1] > 5 * sd[0] and sd[1] > 2 * sd[2], sd  # across the corridor: pinned

    n = 30_000
    long = np.c_[rng.uniform(-10, 10, n), rng.choice([-6.0, 6.0], n), rng.uniform(-1.7, 1.3, n)]
    short = np.c_[rng.choice([-10.0, 10.0], n), rng.uniform(-6, 6, n), rng.uniform(-1.7, 1.3, n)]
    few = np.c_[rng.uniform(-10, 10, 300), rng.uniform(-6, 6, 300), rng.normal(-1.73, 0.02, 300)]
    room = np.r_[long, short, few]
    room[:, :2] += rng.normal(0, 0.02, (len(room), 2))
    sd = np.sqrt(np.diag(_registered(room)))
    assert sd[2] > 2 * max(sd[0], sd[1]), sd


def test_calibration_recovers_the_scale_and_prefers_the_hessian_to_one_ellipsoid():
    """Closures whose errors follow s · H⁻¹ with H varying from closure to closure: the rule
    finds s, 95% lie in their 95% ellipsoid, and the covariance that follows H scores a lower
    negative log-likelihood than the one ellipsoid fitted to all of them."""
    pc = benchmark_module("pose_covariance")
    rng = np.random.default_rng(4)
    records = []
    for _ in range(3000):
        a = rng.normal(size=(6, 6))
        h = a @ a.T + np.diag(rng.uniform(0.5, 50, 6))  # rotation first
        cov = posecov.from_hessian(h, 2.0)
        records.append(
            {
                "delta": rng.multivariate_normal(np.zeros(6), cov),
                "hessian": h,
                "residual": 1.0,
            }
        )
    fit = pc.calibrate(records)
    hess = fit["fits"]["hessian"]
    assert hess["scale"] == pytest.approx(2.0, rel=0.1)
    assert hess["inside"]["0.95"] == pytest.approx(0.95, abs=0.005)
    assert hess["inside"]["0.5"] == pytest.approx(0.5, abs=0.05)
    assert hess["nll"] < fit["fits"]["constant"]["nll"] - 0.5
    assert hess["without_covariance"] == 0
    # the residual estimator's divisor is the registration's: halving it halves the scale
    for r in records:
        r["residual"] = 0.5
    assert pc.calibrate(records)["fits"]["residual"]["scale"] == pytest.approx(
        2 * hess["scale"], rel=1e-6
    )
    # several validation towns (the every-sensor option's, one a sensor) are pooled, and
    # the chosen covariance is shown on each; a town without a right closure shows nothing
    towns = [
        {"town": f"val-{k}", "queries": 1500, "wrong": k, "right": records[k * 1500 :][:1500]}
        for k in range(2)
    ] + [{"town": "val-none", "queries": 9, "wrong": 0, "right": []}]
    val = pc.validation_fit(towns)
    assert val["queries"] == 3009 and val["wrong"] == 1 and val["town"].count(",") == 2
    assert val["fits"] == pc.calibrate(records)["fits"]
    assert [t["town"] for t in val["each"]] == ["val-0", "val-1"]
    assert [t["closures"] for t in val["each"]] == [1500, 1500]
    assert "each" not in pc.validation_fit(towns[:1])


def test_closures_across_sensors_are_scored_as_the_service_calls_them():
    """benchmarks/verify_across.py scores the covariance of the closure each query's answer
    verified (the first passing candidate, the ambiguity margin applied) when its pose is
    right, never a skipped, wrong or Hessian-less one; pose_covariance's scoring reports a
    covariance no closure has as none, and scores only the covariances it is given."""
    from overlapmamba.service.calibrated_settings import CovarianceSettings
    from overlapmamba.service.settings import VerifySettings

    pc, va = benchmark_module("pose_covariance"), benchmark_module("verify_across")
    h = np.diag([400.0, 400.0, 900.0, 1e4, 1e4, 1e4])

    def cand(fitness, rival, t_err, delta, hessian=h):
        return dict(
            keyframe=1, distance=0.1, fitness=fitness, rmse=0.2, rival=rival, t_err=t_err,
            yaw_err=0.1, loop=True, delta=np.full(6, delta), hessian=hessian, residual=1.0,
        )  # fmt: skip

    v = VerifySettings(min_fitness=0.5, max_rmse_m=0.7, ambiguity_margin=0.2, gate_distance=0.3)
    far = cand(0.95, 0.1, 0.02, 0.04) | {"distance": 0.4}  # beyond the gate: not registered
    queries = [
        # an ambiguous first candidate is skipped: the second closes, and is right
        {"candidates": [cand(0.9, 0.85, 0.0, 9.0), cand(0.8, 0.1, 0.02, 0.01)]},
        {"candidates": [cand(0.9, 0.1, 3.0, 3.0)]},  # verified, but the pose is wrong
        {"candidates": [cand(0.9, 0.1, 0.02, 0.02, hessian=None)]},  # nothing to score
        {"candidates": [cand(0.3, 0.1, 0.02, 0.03)]},  # not verified
        # the first verified closes (stop_at_first), not the fitter wrong one after it
        {"candidates": [cand(0.6, 0.1, 0.02, 0.05), cand(0.95, 0.1, 3.0, 0.06)]},
        {"candidates": [far]},
    ]
    right = va.right_closures(queries, v)
    assert [r["delta"][0] for r in right] == [0.01, 0.05]
    best = va.right_closures(queries, v.model_copy(update={"stop_at_first": False}))
    assert [r["delta"][0] for r in best] == [0.01]  # the fitter one is wrong, not scored
    ungated = va.right_closures(queries, v.model_copy(update={"gate_distance": None}))
    assert [r["delta"][0] for r in ungated] == [0.01, 0.05, 0.04]
    served = CovarianceSettings(estimator="hessian", scale=2.0)
    fit = {"fits": {"constant": {"scale": 1.5}}}
    assert pc.covariances(CovarianceSettings(), None) == {}
    assert pc.covariances(CovarianceSettings(), fit) == {"constant": ("constant", 1.5)}
    kinds = pc.covariances(served, fit)
    assert kinds == {"served": ("hessian", 2.0), "constant": ("constant", 1.5)}
    got = pc.scored_kinds(right, kinds, np.eye(6) * 1e-4)
    assert got["served"]["closures"] == got["constant"]["closures"] == 2
    c2 = [r["delta"] @ h @ r["delta"] / 2.0 for r in right]
    assert got["served"]["chi2_median"] == pytest.approx(np.median(c2))
    none = pc.scored_kinds([], kinds, np.eye(6))
    assert none["served"] == {
        "estimator": "hessian", "scale": 2.0, "without_covariance": 0, "closures": 0
    }  # fmt: skip


def test_covariance_settings_go_together():
    from pydantic import ValidationError

    from overlapmamba.service.settings import Settings

    assert Settings().covariance.scale is None
    with pytest.raises(ValidationError, match="go together"):
        Settings(covariance={"scale": 2.0})
    with pytest.raises(ValidationError, match="residual"):
        Settings(covariance={"estimator": "icp", "scale": 2.0})
    assert Settings(covariance={"estimator": "hessian", "scale": 2.0}).covariance.scale == 2.0


async def turned_keyframe_closure(c) -> dict:
    """A new map of keyframes k0, k1 (scans 0, 1), then scan 1 turned by 40° queried: the
    answer's loop closure."""
    assert (await c.put("/v1/maps/town")).status_code == 201
    for i in range(2):
        r = await c.post(
            "/v1/maps/town/keyframes",
            params={"keyframe_id": f"k{i}", "timestamp": 100.0 + i},
            content=scan(i).tobytes(),
            headers=OCTET,
        )
        assert r.status_code == 201, r.text
    q = await c.post("/v1/maps/town/query", content=scan(1, 40.0).tobytes(), headers=OCTET)
    assert q.status_code == 200, q.text
    return q.json()["loop_closure"]


@pytest.mark.anyio
async def test_a_verified_closure_carries_the_model_s_covariance(tmp_path, encoder):
    """The shipped model's file carries its covariance calibration: a turned copy of a
    keyframe closes verified with a 6 × 6 symmetric positive-definite covariance, the one
    posecov computes from the registration; /readyz names where it came from. A setting
    overrides the model's."""
    from overlapmamba.client import LoopClosure
    from overlapmamba.service.settings import Settings

    async with running(Settings(data_dir=tmp_path / "data"), encoder) as c:
        ready = (await c.get("/readyz")).json()
        text = str(ready)
        assert "covariance.scale" in text and "pose_covariance.py" in text
        lc = await turned_keyframe_closure(c)
        assert lc["verified"] is True and lc["keyframe_id"] == "k1"
        cov = np.array(lc["covariance"]).reshape(6, 6)
        assert np.allclose(cov, cov.T) and np.linalg.eigvalsh(cov).min() > 0
        parsed = LoopClosure.from_json(lc)
        assert parsed.covariance is not None and np.array_equal(parsed.covariance, cov)
    doubled = {"estimator": "residual", "scale": 1.0}
    settings = Settings(data_dir=tmp_path / "data2", covariance=doubled)
    async with running(settings, encoder) as c:
        one = np.array((await turned_keyframe_closure(c))["covariance"]).reshape(6, 6)
    served = encoder.meta.calibration["covariance"].values
    assert served["estimator"] == "residual"
    assert np.allclose(cov, one * float(served["scale"]), rtol=1e-6)  # type: ignore[arg-type]


@pytest.mark.anyio
async def test_a_model_without_the_calibration_closes_verified_with_no_covariance(
    tmp_path, encoder
):
    """The shipped model's file without its covariance section, and no setting: the same
    verified closure answers ``covariance: null`` (the client reads None), and /readyz shows
    the scale as the null default, chosen by no command."""
    import copy

    from overlapmamba.client import LoopClosure
    from overlapmamba.service.settings import Settings

    bare = copy.copy(encoder)
    kept = {k: v for k, v in encoder.meta.calibration.items() if k != "covariance"}
    bare.meta = encoder.meta.model_copy(update={"calibration": kept})
    async with running(Settings(data_dir=tmp_path / "data"), bare) as c:
        shown = (await c.get("/readyz")).json()["detail"]["thresholds"]["covariance.scale"]
        assert shown == {"value": None, "source": "default"}
        lc = await turned_keyframe_closure(c)
    assert lc["verified"] is True and lc["keyframe_id"] == "k1"
    assert "covariance" in lc and lc["covariance"] is None
    assert len(lc["relative_pose"]) == 16
    assert LoopClosure.from_json(lc).covariance is None


def test_a_pose_graph_counts_what_it_leaves_out_and_reads_back(tmp_path):
    from overlapmamba.client.posegraph import PoseGraph, odometry_information, read_g2o

    info = odometry_information(0.1, 1.0)
    assert np.allclose(np.diag(info), [100] * 3 + [4 / np.deg2rad(1.0) ** 2] * 3)
    with pytest.raises(ValueError, match="must be > 0"):
        odometry_information(0.0, 1.0)
    g = PoseGraph(info, others_from=10)
    cov = np.diag([1e-4] * 3 + [1e-6] * 3)
    rel = pose(5.0, (0.2, 0.1, 0.0))
    g.scan(0, pose(0.0, (0, 0, 0)), "a:0")
    g.scan(1, [1.0, 0, 0, 0, 0, 0, 1], None)  # as a drive gives it
    g.scan(2, None, None)  # no pose: no vertex
    assert g.closure(1, "a:0", rel, cov)
    assert not g.closure(1, "a:0", rel, None)
    assert not g.closure(2, "a:0", rel, cov)
    assert not g.closure(1, "b:7", rel, cov)  # another drive's, no stored pose
    assert g.closure(1, "b:7", rel, cov, [5.0, 5.0, 0, 0, 0, 0, 1])
    assert g.closure(0, "b:7", rel, cov, [5.0, 5.0, 0, 0, 0, 0, 1])  # the same vertex again
    assert g.left_out == {
        "the answer carries no covariance (no calibration, or a loose direction)": 1,
        "its scan has no pose": 1,
        "its keyframe is another drive's, with no pose in the answer": 1,
    }
    with pytest.raises(ValueError, match="others_from"):
        g.scan(10, pose(0.0, (0, 0, 0)), None)
    path = tmp_path / "g.g2o"
    g.write(path)
    vertices, edges = read_g2o(path)
    assert sorted(vertices) == [0, 1, 10] and np.allclose(vertices[10][:3, 3], [5, 5, 0])
    assert [(a, b) for a, b, _, _ in edges] == [(0, 1), (0, 1), (10, 1), (10, 0)]
    assert np.allclose(edges[0][2][:3, 3], [1, 0, 0]) and np.allclose(edges[0][3], info)
    assert np.allclose(edges[1][2], rel) and np.allclose(edges[1][3], posecov.g2o_information(cov))
    assert path.read_text().splitlines()[-1] == "FIX 0"
    # for GTSAM's readG2o, which takes the rotation block over the rotation vector: the
    # inverse covariance as it is, the odometry's too; g2o's has the rotation doubled
    from overlapmamba.client._cli_options import GraphReader
    from overlapmamba.client.posegraph import READERS, file_information

    a = np.random.default_rng(5).normal(size=(6, 6)) * 0.01
    correlated = a @ a.T + cov  # the cross blocks too
    gt = PoseGraph.for_reader(0.1, 1.0, others_from=10, reader="gtsam")
    assert gt.reader == "gtsam"
    assert np.allclose(np.diag(gt.odometry), [100] * 3 + [1 / np.deg2rad(1.0) ** 2] * 3)
    gt.scan(0, pose(0.0, (0, 0, 0)), "a:0")
    gt.scan(1, pose(0.0, (1, 0, 0)), None)
    assert gt.closure(1, "a:0", rel, correlated)
    assert np.allclose(gt.loops[0][3], np.linalg.inv(correlated))
    two = np.diag([1.0, 1, 1, 2, 2, 2])
    assert np.allclose(file_information(correlated, "g2o"), two @ gt.loops[0][3] @ two)
    with pytest.raises(ValueError, match="one of g2o, gtsam; got 'ros'"):
        file_information(cov, "ros")
    with pytest.raises(ValueError, match="one of g2o, gtsam; got 'ros'"):
        PoseGraph(info, others_from=10, reader="ros")  # at once, not at the first closure
    assert {r.value for r in GraphReader} == set(READERS)  # the CLI offers each reader
    path.write_text("VERTEX_SE2 0 0 0 0\n")
    with pytest.raises(ValueError, match="g.g2o:1: not a VERTEX_SE3:QUAT"):
        read_g2o(path)


def test_a_pose_graph_is_kept_beside_its_path_when_the_replay_or_the_write_fails(
    tmp_path, monkeypatch
):
    """PoseGraph.written_to: Ctrl-C inside keeps the graph so far as NAME.incomplete.g2o; a
    write at the path that fails (a full disk) keeps it there too and says the write failed;
    where nothing can be kept, why is recorded; a graph without a scan keeps nothing."""
    from overlapmamba.client.posegraph import PoseGraph, odometry_information, read_g2o
    from overlapmamba.core import outfiles

    def graph() -> PoseGraph:
        g = PoseGraph(odometry_information(0.1, 1.0), others_from=10)
        g.scan(0, pose(0.0, (0, 0, 0)), None)
        g.scan(1, pose(5.0, (1, 0, 0)), None)
        return g

    path = tmp_path / "drive.g2o"
    g = graph()
    with pytest.raises(KeyboardInterrupt), g.written_to(path):
        raise KeyboardInterrupt
    assert g.incomplete == tmp_path / "drive.incomplete.g2o" and not g.write_failed
    assert sorted(read_g2o(g.incomplete)[0]) == [0, 1] and not path.exists()
    whole = outfiles.write_whole

    def full(where, text):
        if where == path:
            raise OSError(28, "No space left on device")
        whole(where, text)

    monkeypatch.setattr(outfiles, "write_whole", full)
    g = graph()
    with pytest.raises(OSError, match="No space"), g.written_to(path):
        pass
    assert g.write_failed and g.incomplete == tmp_path / "drive.incomplete-2.g2o"
    monkeypatch.setattr(outfiles, "write_whole", lambda where, text: full(path, text))
    g = graph()
    with pytest.raises(ConnectionError), g.written_to(path):
        raise ConnectionError("gone")
    assert g.incomplete is None and g.lost is not None and "No space" in g.lost
    empty = PoseGraph(odometry_information(0.1, 1.0), others_from=10)
    with pytest.raises(ConnectionError), empty.written_to(path):
        raise ConnectionError("gone")
    assert empty.incomplete is None and empty.lost is None


def test_observe_refuses_a_pose_graph_it_cannot_write_before_replaying(synthetic_seq_dir, tmp_path):
    """Each refusal before a scan is sent (nothing listens at the URL: a check that came
    after connecting would fail there instead)."""
    import shutil

    from typer.testing import CliRunner

    from overlapmamba.client.cli import app

    unposed = tmp_path / "unposed"
    shutil.copytree(synthetic_seq_dir, unposed)
    (unposed / "poses.txt").unlink()
    env = {"OVERLAPMAMBA_URL": "http://127.0.0.1:9"}
    for drive, out, says in (
        (synthetic_seq_dir, tmp_path / "graph.txt", "allowed formats are g2o"),
        (synthetic_seq_dir, synthetic_seq_dir / "g.g2o", "would overwrite what is being replayed"),
        (unposed, tmp_path / "graph.g2o", "--g2o needs the drive's poses"),
    ):
        args = ["observe", str(drive), "--map", "m", "--g2o", str(out)]
        res = CliRunner().invoke(app, args, env=env)
        text = " ".join(res.output.replace("│", " ").split())
        assert res.exit_code == 2 and says in text, text
        assert not out.exists()
    same = tmp_path / "both.g2o"  # the recording and the graph at one file
    args = ["observe", str(synthetic_seq_dir), "--map", "m", "--g2o", str(same), "--record"]
    res = CliRunner().invoke(app, [*args, str(same)], env=env)
    text = " ".join(res.output.replace("│", " ").split())
    assert res.exit_code == 2 and "--record and --g2o are the same file" in text, text
    res = CliRunner().invoke(  # a reader named, no file to write for it
        app, ["observe", str(synthetic_seq_dir), "--map", "m", "--g2o-for", "gtsam"], env=env
    )
    text = " ".join(res.output.replace("│", " ").split())
    assert res.exit_code == 2 and "--g2o-for gtsam says whom --g2o FILE is for" in text, text
    res = CliRunner().invoke(app, [*args[:-1], "--g2o-for", "ros"], env=env)
    assert res.exit_code == 2 and "'ros' is not one of" in " ".join(res.output.split())
