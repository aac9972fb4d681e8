"""verify.ambiguity_margin: a closure that a pose turned by a quarter, a half or three quarters
fits nearly as well is refused (overlapmamba.service.verify.rival_fitness), in the verify stage,
in the benchmarks' scoring of recorded candidates, in the statistics and over HTTP."""

from __future__ import annotations

import numpy as np
import pytest
from service_kit import OCTET, ROOT, running

from overlapmamba.service.registration import keyframe_geometry, prepare
from overlapmamba.service.settings import Settings, VerifySettings
from overlapmamba.service.stats import Stats
from overlapmamba.service.verify import Verdict, params_of, verify_candidates

# four blocks at the corners of a crossing: the same place turned by any quarter
CROSSING = [(6, 30, 6, 30), (-30, -6, 6, 30), (-30, -6, -30, -6), (6, 30, -30, -6)]
# blocks of different sizes along a street: no turned pose fits
STREET = [
    (6, 30, 6, 14),
    (-30, -10, 8, 30),
    (-20, -6, -30, -12),
    (12, 18, -25, -6),
    (25, 28, -10, 0),
]


def scene(blocks: list[tuple[int, int, int, int]], step: float = 0.25) -> np.ndarray:
    """(N, 4) float32 xyzi: a ground plane 1.7 m below the sensor and 8 m walls around each
    block (x0, x1, y0, y1)."""
    g = np.arange(-40.0, 40.0, 0.5)
    gx, gy = np.meshgrid(g, g)
    parts = [np.c_[gx.ravel(), gy.ravel(), np.full(gx.size, -1.7)]]
    zs = np.arange(-1.7, 6.3, step)
    for x0, x1, y0, y1 in blocks:
        xs, ys = np.arange(x0, x1, step), np.arange(y0, y1, step)
        for y in (y0, y1):
            a, z = np.meshgrid(xs, zs)
            parts.append(np.c_[a.ravel(), np.full(a.size, y), z.ravel()])
        for x in (x0, x1):
            a, z = np.meshgrid(ys, zs)
            parts.append(np.c_[np.full(a.size, x), a.ravel(), z.ravel()])
    xyz = np.concatenate(parts)
    return np.c_[xyz, np.full(len(xyz), 0.5)].astype(np.float32)


def verdicts(blocks, margin: float | None, n: int = 1) -> list[Verdict]:
    v = VerifySettings(gate_distance=None, ambiguity_margin=margin)
    p = params_of(v)
    pts = scene(blocks)[:, :3]
    blob = keyframe_geometry(prepare(pts, p), p)
    return verify_candidates(prepare(pts, p), [(blob, 3.0, 0.1)] * n, v)


def test_a_crossing_that_a_quarter_turn_maps_onto_itself_is_refused_as_ambiguous():
    [crossing] = verdicts(CROSSING, 0.3)
    assert crossing.verified is False and crossing.fitness is not None and crossing.fitness > 0.9
    assert crossing.reason is not None and "ambiguous" in crossing.reason
    assert "verify.ambiguity_margin 0.3" in crossing.reason
    assert crossing.rival_fitness is not None and crossing.rival_fitness > crossing.fitness - 0.3
    assert crossing.relative_pose is not None  # the pose it found, as for any refusal
    [street] = verdicts(STREET, 0.3)
    assert street.verified is True and street.reason is None
    assert street.fitness is not None and street.rival_fitness is not None
    assert street.fitness - street.rival_fitness >= 0.3
    # off (null, a file calibrated before the check): the crossing verifies, nothing is checked
    [unchecked] = verdicts(CROSSING, None)
    assert unchecked.verified is True and unchecked.rival_fitness is None
    assert unchecked.public()["rival_fitness"] is None


def test_an_ambiguous_candidate_does_not_stop_the_later_ones_from_registering():
    """verify.stop_at_first stops at the first that verifies; a refusal is not one."""
    first, second = verdicts(CROSSING, 0.3, n=2)
    assert first.verified is False and second.verified is False
    assert second.fitness is not None and "ambiguous" in (second.reason or "")


def test_a_turn_whose_seed_cannot_rival_is_not_registered(monkeypatch):
    """register's screen: below it the seed pose is the answer, GICP never runs; at or above it
    the registration is the unscreened one. The service screens its rivals at the fit that
    would refuse: the street's turns cost no registration, and the verdict is the one every
    turn registered gives, at each margin (crossing and street)."""
    import overlapmamba.service.registration as registration
    from overlapmamba.core.poses import yaw_deg
    from overlapmamba.service.verify import rival_fitness, unambiguous

    v = VerifySettings(gate_distance=None)
    p = params_of(v)
    pts = scene(STREET)[:, :3]
    q = prepare(pts, p)
    blob = keyframe_geometry(q, p)
    assert blob is not None
    seed = registration.register(q, blob, 93.0, p, screen=1.01)
    assert seed.iterations == 0 and seed.reach is not None and seed.reach < 1.01
    assert seed.relative_pose is not None and seed.fitness is not None
    assert abs(float(yaw_deg(seed.relative_pose)) - -93.0) < 1e-6  # the seed's rotation
    assert seed.fitness <= seed.reach  # within 1 m is within GICP's 2 m reach
    plain, screened = (
        registration.register(q, blob, 3.0, p),
        registration.register(q, blob, 3.0, p, screen=0.0),
    )
    assert screened.iterations == plain.iterations > 0 and screened.fitness == plain.fitness
    assert plain.reach is None and screened.reach is not None

    calls = []
    align = registration.small_gicp.align
    monkeypatch.setattr(
        registration.small_gicp, "align", lambda *a, **k: calls.append(1) or align(*a, **k)
    )
    for blocks in (CROSSING, STREET):
        q = prepare(scene(blocks)[:, :3], p)
        blob = keyframe_geometry(q, p)
        assert blob is not None
        for margin in (0.1, 0.3, 0.5):
            calls.clear()
            [served] = verdicts(blocks, margin)
            assert served.verified is not None and served.fitness is not None
            assert served.relative_pose is not None
            if blocks is STREET:  # the verifying registration, no turn
                assert len(calls) == 1, (margin, len(calls))
                calls.clear()  # unscreened (benchmarks/ambiguity_cost.py): every turn
                v = VerifySettings(gate_distance=None, ambiguity_margin=margin)
                assert verify_candidates(q, [(blob, 3.0, 0.1)], v, screen=False)[0].verified
                assert len(calls) == 4, (margin, len(calls))
            own = float(yaw_deg(served.relative_pose))
            every = rival_fitness(q, blob, 3.0, own, p, screen=0.0)
            judged = verdicts(blocks, None)[0]
            assert unambiguous(judged, every, margin).verified == served.verified, margin


def test_a_margin_is_validated_like_every_setting(monkeypatch):
    with pytest.raises(ValueError, match="ambiguity_margin"):
        VerifySettings(ambiguity_margin=1.5)
    with pytest.raises(ValueError, match="ambiguity_margin"):
        VerifySettings(ambiguity_margin=-0.1)
    with pytest.raises(ValueError, match="ambiguity_margin"):
        VerifySettings(ambiguity_margin="sometimes")
    # "off" where null cannot be written (TOML, a variable): set, and off
    assert VerifySettings(ambiguity_margin="off").ambiguity_margin is None
    monkeypatch.setenv("OVERLAPMAMBA_VERIFY__AMBIGUITY_MARGIN", "off")
    v = Settings().verify
    assert v.ambiguity_margin is None and "ambiguity_margin" in v.model_fields_set
    monkeypatch.setenv("OVERLAPMAMBA_VERIFY__AMBIGUITY_MARGIN", "0.25")
    assert Settings().verify.ambiguity_margin == 0.25


def test_closure_kit_scores_the_margin_as_the_service_calls_it():
    """benchmarks/closure_kit.py: a passing candidate whose rival fits within the margin is
    skipped, the next passing one closes; a passing candidate without a recorded rival is an
    error, not a silent pass."""
    from conftest import benchmark_module

    kit = benchmark_module("closure_kit")

    def cand(keyframe, fitness, rival, t_err):
        return dict(
            keyframe=keyframe,
            distance=0.1,
            fitness=fitness,
            rmse=0.5,
            rival=rival,
            t_err=t_err,
            yaw_err=0.1,
            loop=True,
        )

    q = {"has_loop": True, "candidates": [cand(1, 0.6, 0.55, 70.0), cand(2, 0.8, 0.3, 0.2)]}
    off = kit.score([q], 0.5, 0.7, stop_at_first=True)
    on = kit.score([q], 0.5, 0.7, stop_at_first=True, margin=0.3)
    assert (off["correct"], off["precision"], off["registered_per_query"]) == (0, 0.0, 1.0)
    assert (on["correct"], on["precision"], on["recall"]) == (1, 1.0, 1.0)
    assert on["registered_per_query"] == 2.0 and on["ambiguity_margin"] == 0.3
    del q["candidates"][0]["rival"]
    with pytest.raises(KeyError, match="rivals_from"):
        kit.score([q], 0.5, 0.7, margin=0.3)


def test_calibrating_each_pair_chooses_the_margin_with_the_fitness():
    """verify_threshold.py --calibrate --each: where a pair of drives closes a loop a quarter
    turn wrong with a fit above its right ones, the fitness alone must rise above every right
    closure of that pair to keep it at the target; chosen together with the fitness, the
    margin refuses the wrong one and keeps them (joint)."""
    from conftest import benchmark_module

    kit, vt = benchmark_module("closure_kit"), benchmark_module("verify_rules")

    def query(group, fitness, rival, t_err):
        c = dict(keyframe=0, distance=0.1, fitness=fitness, rmse=0.5, rival=rival)
        c |= dict(t_err=t_err, yaw_err=0.1, loop=True)
        return {"has_loop": True, "candidates": [c], "group": group}

    queries = [query("town", 0.8, 0.1, 0.2) for _ in range(50)]
    queries += [query("pair", 0.5, 0.05, 0.2) for _ in range(50)]
    queries += [query("pair", 0.55, 0.5, 70.0)]  # a quarter turn wrong, fitting better
    holds = vt.target_holds(queries, 0.99, each=True)

    sweep = [kit.score(queries, float(f), 0.7) for f in vt.FITNESS]
    alone = max((s for s in sweep if s["accepted"] and holds(s)), key=lambda s: s["recall"])
    assert alone["min_fitness"] > 0.55 and alone["recall"] == 50 / 101
    both = vt.joint(queries, sweep, holds)
    assert both["min_fitness"] == 0.5 and both["ambiguity_margin"] == 0.44
    assert (both["precision"], both["recall"]) == (1.0, 100 / 101)


def test_calibration_chooses_thresholds_then_gate_then_margin_and_scores_both():
    """verify_rules.calibrate, the whole --calibrate --each rule on the same queries: the
    fitness and margin together, then the nearest gate that keeps their recall, then the
    largest margin that does; the thresholds in force (no margin) are scored beside them,
    and their worst group is the pair whose quarter-turn-wrong closure they accept."""
    from conftest import benchmark_module

    rules = benchmark_module("verify_rules")

    def query(group, fitness, rival, t_err, distance):
        c = dict(keyframe=0, distance=distance, fitness=fitness, rmse=0.5, rival=rival)
        c |= dict(t_err=t_err, yaw_err=0.1, loop=True)
        return {"has_loop": True, "candidates": [c], "group": group}

    queries = [query("town", 0.8, 0.1, 0.2, 0.2) for _ in range(50)]
    queries += [query("pair", 0.5, 0.05, 0.2, 0.3) for _ in range(50)]
    queries += [query("pair", 0.55, 0.5, 70.0, 0.3)]
    in_force = dict(min_fitness=0.5, max_rmse_m=0.7, gate_distance=None, ambiguity_margin=None)
    out = rules.calibrate(queries, 0.99, True, in_force)
    cal = out["calibration"]
    assert (cal["chosen"]["min_fitness"], cal["chosen"]["ambiguity_margin"]) == (0.5, 0.44)
    assert cal["gate"]["gate_distance"] == 0.3  # the nearest that keeps every right closure
    assert cal["ambiguity"]["ambiguity_margin"] == 0.44  # 0.46 refuses the pair's right ones
    assert len(out["sweep"]) == 4 * len(rules.FITNESS) and len(out["ambiguity_sweep"]) > 1
    assert (cal["calibrated"]["precision"], cal["calibrated"]["recall"]) == (1.0, 100 / 101)
    assert cal["in_force"]["worst_group"]["group"] == "pair"
    assert cal["in_force"]["worst_group"]["precision"] == 50 / 51
    # without --each the target is over all queries, where the wrong closure is 1 of 101
    # accepted: the fitness alone keeps it (precision 0.990), with no margin chosen with it
    alone = rules.calibrate(queries, 0.99, False, in_force)["calibration"]
    assert alone["rule"] == "one after the other" and alone["chosen"]["ambiguity_margin"] is None
    assert alone["chosen"]["min_fitness"] == 0.5 and alone["chosen"]["precision"] == 100 / 101


def test_statistics_count_ambiguous_refusals_among_the_rejected():
    class M:
        def __init__(self, v):
            self.verification = v

    s = Stats("m")
    amb = Verdict(False, 0.9, 0.1, "ambiguous: …", np.eye(4), rival_fitness=0.85)
    low = Verdict(False, 0.2, 0.5, "fitness 0.200 is below 0.5", np.eye(4))
    ok = Verdict(True, 0.9, 0.1, None, np.eye(4), rival_fitness=0.2)
    s.query("town", "r1", True, [M(amb), M(low), M(ok)])
    v = s.total.public()["verification"]
    assert (v["verified"], v["rejected"], v["ambiguous"], v["registered"]) == (1, 2, 1, 3)

    def towns() -> list[str]:  # the /metrics series of the ambiguous count labelled "town"
        samples = [x for m in s.p_ambiguous.collect() for x in m.samples]
        return [x.name for x in samples if x.labels.get("map") == "town"]

    assert towns()
    s.forget_map("town")  # the map was deleted: its series go, the ambiguous count's too
    assert towns() == []


@pytest.mark.anyio
async def test_an_ambiguous_closure_over_http(tmp_path, encoder):
    """A crossing's keyframe queried by the same scan: registration fits, but so does a
    quarter turn, and the answer says so; a street's closes, with the rival's fit beside it.
    /v1/stats and /metrics count the refusal."""
    verify = {"gate_distance": None, "ambiguity_margin": 0.3}
    async with running(Settings(data_dir=tmp_path / "data", verify=verify), encoder) as c:
        for name, blocks in (("crossing", CROSSING), ("street", STREET)):
            assert (await c.put(f"/v1/maps/{name}")).status_code == 201
            body = scene(blocks).tobytes()
            params = {"keyframe_id": "k0", "timestamp": 1.0, "robot_id": "r1", "session_id": "s1"}
            r = await c.post(
                f"/v1/maps/{name}/keyframes", params=params, content=body, headers=OCTET
            )
            assert r.status_code == 201, r.text
            q = await c.post(f"/v1/maps/{name}/query", content=body, headers=OCTET)
            assert q.status_code == 200, q.text
            v, lc = q.json()["matches"][0]["verification"], q.json()["loop_closure"]
            if name == "crossing":
                assert v["verified"] is False and "ambiguous" in v["reason"]
                assert v["rival_fitness"] > v["fitness"] - 0.3
                assert lc["accepted"] is False and lc["verified"] is False
            else:
                assert v["verified"] is True and v["fitness"] - v["rival_fitness"] >= 0.3
                assert lc["accepted"] is True and lc["keyframe_id"] == "k0"
        stats = (await c.get("/v1/maps/crossing/stats")).json()["verification"]
        assert stats["ambiguous"] == 1 and stats["rejected"] >= 1
        assert (await c.get("/v1/maps/street/stats")).json()["verification"]["ambiguous"] == 0
        metrics = (await c.get("/metrics")).text
        assert 'overlapmamba_ambiguous_closures_total{map="crossing"} 1.0' in metrics


def test_a_file_calibrated_before_the_margin_serves_with_the_check_off(caplog):
    """A calibration without ``ambiguity_margin`` leaves it at its default, null: the start-up
    log names its source, and does not warn that another model's threshold serves."""
    import logging

    from overlapmamba.service.calibration import Threshold, log_thresholds

    used = {
        "verify.min_fitness": Threshold(0.5, "model", "verify_threshold.py on val"),
        "verify.ambiguity_margin": Threshold(None, "default"),
    }
    with caplog.at_level(logging.INFO, logger="overlapmamba.service"):
        log_thresholds("om-x", used)
    assert "verify.ambiguity_margin=None (default)" in caplog.text
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    used["verify.gate_distance"] = Threshold(0.29, "default")
    with caplog.at_level(logging.INFO, logger="overlapmamba.service"):
        log_thresholds("om-x", used)
    [warning] = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert "verify.gate_distance" in warning.getMessage()
    assert "ambiguity_margin" not in warning.getMessage()


def test_a_model_whose_first_stage_is_its_descriptor_has_no_score_to_calibrate(caplog):
    """Found in review: the shipped file warned at every start that it "carries no
    calibration for rerank.score", a choice its first stage does not have (both scores are
    its descriptor's); a mixed first stage's uncalibrated score still warns."""
    import logging

    from overlapmamba.service.calibration import log_thresholds, read_model_metadata, resolve
    from overlapmamba.service.settings import Settings

    for name, warns in (("overlapmamba-hdl64", False), ("overlapmamba-any-sensor", True)):
        meta = read_model_metadata(ROOT / "models" / f"{name}.onnx")
        _, used = resolve(Settings(), meta)
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="overlapmamba.service"):
            log_thresholds(meta.model_id, used)
        warned = [r for r in caplog.records if r.levelno >= logging.WARNING]
        assert bool(warned) == warns, (name, [r.getMessage() for r in warned])
        assert used["rerank.score"].value == "stage"
