"""Metrics: fast vs reference, cross-checked against scikit-learn, and edge cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from overlapmamba.core.metrics import (
    average_recall_at_n,
    evaluate_loop_closure,
    evaluate_retrieval,
    f1_max,
    nearest,
    pooled,
    pr_auc,
    pr_curve,
    pr_curve_reference,
    recall_at_n_curve,
    squared_distances,
)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 60))
def test_pr_curve_matches_reference(seed, n):
    rng = np.random.default_rng(seed)
    d = rng.integers(0, 8, n).astype(float)  # many ties on purpose
    d[rng.random(n) < 0.1] = np.nan  # no distance (a custom caller's): the worst, both ways
    has = rng.random(n) < 0.6
    ok = has & (rng.random(n) < 0.7)
    for fast, ref in zip(pr_curve(d, ok, has), pr_curve_reference(d, ok, has), strict=True):
        np.testing.assert_allclose(fast, ref)


def test_pr_curve_agrees_with_sklearn_when_loops_equal_correct_answers():
    """When every query with a loop retrieves a true loop and the others retrieve none,
    our protocol reduces to a plain binary PR curve over (correct, −distance)."""
    # imported here: scikit-learn takes ≈1.5 s to import, in every worker's collection
    from sklearn.metrics import auc as sk_auc
    from sklearn.metrics import precision_recall_curve

    rng = np.random.default_rng(3)
    d = rng.random(200)
    correct = rng.random(200) < 0.4
    d[correct] -= 0.3  # correct answers tend to be closer
    p, r, _ = pr_curve(d, correct, correct)
    sp, sr, _ = precision_recall_curve(correct, -d)
    ours = sorted(zip(r.round(12), p.round(12), strict=True))
    theirs = sorted(zip(sr.round(12), sp.round(12), strict=True))
    assert ours == theirs
    assert pr_auc(p, r) == pytest.approx(sk_auc(sr, sp))
    with np.errstate(invalid="ignore"):
        sk_f1 = np.nanmax(2 * sp * sr / (sp + sr))
    assert f1_max(p, r) == pytest.approx(sk_f1)


def test_pr_edge_cases():
    p, r, _ = pr_curve(np.array([]), np.array([], bool), np.array([], bool))
    assert (p.tolist(), r.tolist()) == ([1.0], [1.0])
    # No query has a loop: recall is 1 by definition, precision falls as FPs are accepted.
    p, r, _ = pr_curve(np.array([0.1, 0.2]), np.zeros(2, bool), np.zeros(2, bool))
    assert r.tolist() == [1.0, 1.0, 1.0] and p.tolist() == [1.0, 0.0, 0.0]


def test_wrong_answers_for_every_loop_query_give_zero_recall():
    p, r, _ = pr_curve(np.array([0.5, 0.5]), np.zeros(2, bool), np.ones(2, bool))
    assert r.tolist() == [0.0, 0.0] and pr_auc(p, r) == 0.0


def test_nearest_matches_brute_force_and_respects_allowed():
    rng = np.random.default_rng(0)
    q, db = rng.normal(size=(7, 5)), rng.normal(size=(30, 5))
    allowed = rng.random((7, 30)) < 0.5
    allowed[0] = False
    idx, dist = nearest(q, db, 4, allowed=allowed, chunk=3)
    assert (idx[0] == -1).all() and np.isinf(dist[0]).all()
    for i in range(1, 7):
        d = ((q[i] - db) ** 2).sum(1)
        d[~allowed[i]] = np.inf
        expect = np.argsort(d, kind="stable")[:4]
        expect = np.where(np.isinf(d[expect]), -1, expect)
        assert idx[i].tolist() == expect.tolist()
    np.testing.assert_allclose(squared_distances(q, db)[1, 2], ((q[1] - db[2]) ** 2).sum())


def test_recall_curve_and_ar():
    ranked = np.array([[3, 1, 2], [0, 5, 6], [9, 9, 9], [4, 2, -1]])
    positives = [np.array([1]), np.array([0]), np.array([], int), np.array([7])]
    curve = recall_at_n_curve(ranked, positives)
    assert curve.tolist() == pytest.approx([1 / 3, 2 / 3, 2 / 3])
    assert average_recall_at_n(curve, 2) == pytest.approx(0.5)
    assert math.isnan(recall_at_n_curve(ranked, [np.array([], int)] * 4)[0])


def _loop_world(n=300, noise=0.05, seed=0):
    """Frames 200+ revisit frames 0+ (same place → similar descriptor)."""
    rng = np.random.default_rng(seed)
    places = rng.normal(size=(200, 16))
    desc = np.concatenate([places, places[:100] + rng.normal(scale=noise, size=(100, 16))])
    positives = [np.array([], int)] * 200 + [np.array([i]) for i in range(100)]
    return desc, positives


def test_loop_closure_perfect_and_random():
    desc, pos = _loop_world()
    res = evaluate_loop_closure(desc, pos)
    assert res.n_queries == 300 - 101 and res.n_with_loop == 100
    assert res.recall_at_1 == 1.0 and res.recall_at_1pct == 1.0 and res.f1max == 1.0
    assert res.auc == pytest.approx(1.0)
    rnd = evaluate_loop_closure(np.random.default_rng(1).normal(size=desc.shape), pos)
    assert rnd.recall_at_1 < 0.1 and rnd.f1max < 0.6


def test_loop_closure_database_excludes_recent_frames():
    # Frame 150 is identical to frame 120, but 120 is too recent (150 − 120 ≤ 100).
    desc, _ = _loop_world()
    desc[150] = desc[120]
    pos = [np.array([], int)] * 300
    pos[150] = np.array([120])
    res = evaluate_loop_closure(desc[:151], pos[:151])
    # Frame 120 is outside query 150's database, so it does not count as a positive.
    assert res.n_with_loop == 0 and math.isnan(res.recall_at_1)
    # nothing to find: F1max and AUC are undefined, not a perfect 1 (or 0)
    assert math.isnan(res.f1max) and math.isnan(res.auc)
    assert res.n_queries == 50
    pos[150] = np.array([3, 120])  # one reachable positive, one not
    res = evaluate_loop_closure(desc[:151], pos[:151])
    assert res.n_with_loop == 1 and res.recall_at_1 == 0.0


def test_query_mask_scores_a_subset():
    desc, pos = _loop_world()
    mask = np.zeros(300, bool)
    mask[250:] = True
    res = evaluate_loop_closure(desc, pos, query_mask=mask)
    assert res.n_queries == 50 and res.n_with_loop == 50
    assert res.summary()["recall@1"] == 1.0


def test_errors_at_an_operating_point_sort_every_query_by_hand():
    """overlapmamba.core.anatomy on a hand-made retrieval: which accepted answers are true, which
    false alarms are neighbours (and overlap a little) or look-alikes, which loops are missed."""
    from overlapmamba.core.anatomy import errors_at_f1max
    from overlapmamba.core.metrics import evaluate_retrieval
    from overlapmamba.core.overlap import LoopGroundTruth

    n = 8
    # query → (top-1 candidate, distance); positives per frame; positions in metres
    answers = {2: (0, 0.1), 3: (0, 0.2), 4: (1, 0.25), 5: (1, 0.9), 6: (0, 0.15), 7: (3, 0.95)}
    positives = [np.array([], np.int64)] * n
    positives[2], positives[5], positives[6] = np.array([0]), np.array([1]), np.array([2])
    x = np.array([0.0, 500.0, 2.0, 20.0, 700.0, 501.0, 30.0, 900.0])
    positions = np.column_stack([x, np.zeros(n), np.zeros(n)])
    gt = LoopGroundTruth(  # the table: loops (> 0.3) and one neighbour below it (3, 0)
        n_frames=n,
        query=np.array([2, 5, 6, 3]),
        reference=np.array([0, 1, 2, 0]),
        overlap=np.array([0.8, 0.6, 0.7, 0.2], np.float32),
        yaw_deg=np.zeros(4, np.float32),
        distance=np.array([2.0, 1.0, 28.0, 20.0], np.float32),
        params={"min_overlap": 0.3},
    )

    def retrieve(queries, db_size, k):
        ranked = np.full((len(queries), k), -1)
        dist = np.full((len(queries), k), np.inf)
        for i, q in enumerate(queries):
            ranked[i, 0], dist[i, 0] = answers[int(q)]
        return ranked, dist

    r = evaluate_retrieval(retrieve, n, positives, exclude_recent_frames=1, max_n=1)
    assert r.queries.tolist() == [2, 3, 4, 5, 6, 7] and r.has_loop.sum() == 3
    e = errors_at_f1max(r, gt, positions, far=50.0, threshold=0.3)
    assert e["accepted"] == 4 and e["true_closures"] == 1  # 2 → 0 only
    fa = e["false_alarms"]
    # 3 → 0 (20 m, overlap 0.2), 6 → 0 (30 m, not in the table, has a loop), 4 → 1 (200 m)
    assert (fa["total"], fa["neighbours"], fa["look_alikes"]) == (3, 2, 1)
    assert fa["overlapping"] == 1 and fa["with_a_loop"] == 1 and fa["median_m"] == 30.0
    # loops of 5 (right top-1, 0.9 > 0.3: rejected) and 6 (wrong top-1)
    assert e["missed_loops"] == {"total": 2, "wrong_top1": 1, "rejected": 1}
    # by default, the threshold where F1 peaks: there F1 is F1max (the protocol counts a
    # loop accepted with a wrong candidate as a false positive, not as a false negative)
    best = errors_at_f1max(r, gt, positions)
    tp = best["true_closures"]
    fn = best["missed_loops"]["total"] - best["false_alarms"]["with_a_loop"]
    f1 = 2 * tp / (2 * tp + (best["accepted"] - tp) + fn)
    assert best["threshold"] == r.f1max_threshold and f1 == pytest.approx(r.f1max)


def _noisy_loops(seed: int, n: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """A sequence whose frames from 200 on revisit frames 0 … with noise, some not at all."""
    rng = np.random.default_rng(seed)
    desc = rng.normal(size=(n, 8))
    pos = [np.array([], int)] * n
    for i in range(200, n):
        if rng.random() < 0.7:
            j = i - 200
            desc[i] = desc[j] + rng.normal(scale=rng.uniform(0.1, 1.5), size=8)
            pos[i] = np.array([j])
    return desc, pos


def test_pooled_sequences_score_as_one_curve_with_each_query_in_its_own_past():
    (da, pa), (db, pb) = _noisy_loops(0, 320), _noisy_loops(1, 260)
    ra, rb = evaluate_loop_closure(da, pa), evaluate_loop_closure(db, pb)
    both = pooled([ra, rb])
    # independently: one sequence of both, each query searching only its own sequence's past
    off = len(da)
    desc = np.concatenate([da, db])
    pos = pa + [p + off for p in pb]

    def own_past(queries: np.ndarray, db_size: np.ndarray, k: int):
        j = np.arange(len(desc))[None, :]
        start = np.where(queries >= off, off, 0)[:, None]
        return nearest(desc[queries], desc, k, allowed=(j >= start) & (j < db_size[:, None]))

    mask = np.r_[np.ones(off, bool), np.arange(len(db)) > 100]
    ref = evaluate_retrieval(own_past, len(desc), pos, query_mask=mask)
    assert both.n_queries == ref.n_queries == ra.n_queries + rb.n_queries
    assert both.n_with_loop == ref.n_with_loop
    np.testing.assert_allclose(both.precision, ref.precision)
    np.testing.assert_allclose(both.recall, ref.recall)
    np.testing.assert_allclose(both.thresholds, ref.thresholds)
    assert both.f1max == pytest.approx(ref.f1max) and both.auc == pytest.approx(ref.auc)
    np.testing.assert_allclose(both.recall_curve, ref.recall_curve)
    assert both.recall_at_1 == pytest.approx(ref.recall_at_1)
    # one threshold for both: at each, F1 of the union lies between the two sequences' F1
    assert both.f1max <= max(ra.f1max, rb.f1max) + 1e-12


def test_pooled_ignores_recall_of_a_sequence_without_loops_and_refuses_nothing():
    desc, pos = _loop_world()
    with_loops = evaluate_loop_closure(desc, pos)
    without = evaluate_loop_closure(desc[:150], [np.array([], int)] * 150)
    assert math.isnan(without.recall_at_1)
    both = pooled([with_loops, without])
    assert both.recall_at_1 == with_loops.recall_at_1 and not math.isnan(both.recall_at_1pct)
    assert both.n_queries == with_loops.n_queries + without.n_queries
    with pytest.raises(ValueError, match="at least one"):
        pooled([])
