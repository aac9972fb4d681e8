"""Two-stage retrieval (overlapmamba.core.rerank) and the service's re-ranked answers
(overlapmamba.service.ranking)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from overlapmamba.core.metrics import evaluate_loop_closure, evaluate_retrieval
from overlapmamba.core.rerank import (
    OFF,
    Rerank,
    aligned_correlation,
    rerank,
    rerank_ranked,
    two_stage,
)

RNG = np.random.default_rng(7)


def _feats(n: int, c: int = 4, w: int = 32) -> np.ndarray:
    return RNG.normal(size=(n, c, w))


def test_the_score_orders_the_shortlist_and_ties_keep_the_descriptor_order():
    q = _feats(1)[0]
    refs = np.stack([_feats(1)[0], np.roll(q, 5, axis=-1), _feats(1)[0]])
    d2 = np.array([0.010, 0.012, 0.014])  # the turned copy of q is second by descriptor
    order, s, c = rerank(q, refs, d2, Rerank(shortlist=3, weight=0.2))
    assert order[0] == 1 and math.isclose(c[0], 1.0)  # an exact roll correlates fully
    assert np.all(np.diff(s) >= 0)
    assert np.allclose(s, d2[order] - 0.2 * c)
    # equal scores: descriptor order
    same = np.stack([refs[1], refs[1]])
    order, _, _ = rerank(q, same, np.array([0.02, 0.02]), Rerank(shortlist=2, weight=0.2))
    assert list(order) == [0, 1]
    # weight 0 is the descriptor order
    order, s, _ = rerank(q, refs, d2, Rerank(shortlist=3, weight=0.0))
    assert list(order) == [0, 1, 2] and np.allclose(s, d2)


def test_aligned_correlation_is_the_best_rolls_cosine():
    q = _feats(1)[0]
    c = aligned_correlation(q, np.stack([np.roll(q, 11, axis=-1), -q]))
    assert math.isclose(c[0], 1.0, rel_tol=1e-9) and c[1] < 1.0


def test_bad_parameters_are_named():
    with pytest.raises(ValueError, match="shortlist must be ≥ 1"):
        Rerank(shortlist=0)
    with pytest.raises(ValueError, match="weight must be a finite number ≥ 0"):
        Rerank(weight=-0.1)
    with pytest.raises(ValueError, match="weight must be a finite number ≥ 0"):
        Rerank(weight=float("nan"))
    for bad in ("20", "x,0.2", "20,0.2,1", "2.5,0.2"):
        with pytest.raises(ValueError, match="is not K,WEIGHT"):
            Rerank.parse(bad)
    assert Rerank.parse("off") == OFF and not OFF.on
    assert Rerank.parse("10, 0.5") == Rerank(10, 0.5)
    with pytest.raises(ValueError, match="shortlist must be ≥ 1"):
        Rerank.parse("0,0.2")


def test_a_result_table_is_reranked_in_its_first_k_columns_only_and_padding_stays_last():
    db = _feats(6)
    queries = np.stack([db[3], db[5]])
    ranked = np.array([[0, 1, 3, 2, 4], [5, 2, -1, -1, -1]])
    d2 = np.array([[0.1, 0.2, 0.3, 0.4, 0.5], [0.1, 0.2, np.inf, np.inf, np.inf]])
    r, s = rerank_ranked(queries, db, ranked, d2, Rerank(shortlist=3, weight=1.0))
    assert r[0, 0] == 3 and sorted(r[0, :3]) == [0, 1, 3]  # itself (c = 1) first
    assert list(r[0, 3:]) == [2, 4] and list(s[0, 3:]) == [0.4, 0.5]  # beyond k: untouched
    assert r[1, 0] == 5 and list(r[1, 2:]) == [-1, -1, -1] and np.isinf(s[1, 2:]).all()
    r_off, s_off = rerank_ranked(queries, db, ranked, d2, OFF)
    assert (r_off == ranked).all() and np.array_equal(s_off, d2)


def test_two_stages_find_the_place_the_descriptor_ranks_second():
    """A sequence whose revisits have a look-alike nearer by descriptor than the true place;
    the yaw features tell them apart, so Recall@1 rises from 0 to 1, and the three
    subsets' queries share one computation (the same answers as asked one by one)."""
    n, c, w = 60, 4, 32
    base = RNG.normal(size=(n, 16))
    feats = _feats(n, c, w)
    desc = base.copy()
    positives = [np.zeros(0, np.int64) for _ in range(n)]
    for q, place, decoy in ((50, 5, 30), (55, 10, 35)):
        desc[q] = base[place] + 0.05 * RNG.normal(size=16)
        desc[decoy] = desc[q] + 0.01 * RNG.normal(size=16)  # nearer than the place
        feats[q] = np.roll(feats[place], 7, axis=-1) + 0.1 * RNG.normal(size=(c, w))
        positives[q] = np.array([place])
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    plain = evaluate_loop_closure(desc, positives, exclude_recent_frames=10)
    assert plain.recall_at_1 == 0.0
    retrieve = two_stage(desc, feats, Rerank(shortlist=5, weight=0.2))
    staged = evaluate_retrieval(retrieve, n, positives, exclude_recent_frames=10)
    assert staged.recall_at_1 == 1.0 and staged.f1max > plain.f1max
    queries = np.arange(11, n)
    ranked, score = retrieve(queries, queries - 10, 5)
    one = [retrieve(np.array([q]), np.array([q - 10]), 5) for q in queries]
    assert np.array_equal(ranked, np.concatenate([r for r, _ in one]))
    assert np.allclose(score, np.concatenate([s for _, s in one]))


def test_the_services_answer_is_reranked_only_when_every_candidate_can_be_scored():
    from overlapmamba.service.domain import Keyframe, Match
    from overlapmamba.service.ranking import rerank_matches, shortlist

    def match(kid: str, dist: float, conf: float | None) -> Match:
        kf = Keyframe(0, kid, "r", "s", 0.0, None, "h", 0, 0.0)
        return Match(kf, 1 - dist * dist / 2, dist, None if conf is None else 0.0, conf)

    p = Rerank(shortlist=3, weight=0.2)
    found = [match("a", 0.10, 0.2), match("b", 0.11, 0.9), match("c", 0.12, 0.5)]
    found.append(match("d", 0.13, None))  # the runner-up fetched beyond the shortlist
    out = rerank_matches(found, p)
    assert [m.keyframe.keyframe_id for m in out] == ["b", "c", "a", "d"]
    assert out[0].score == pytest.approx(0.11**2 - 0.2 * 0.9) and out[3].score is None
    # a keyframe without yaw features among the first k: descriptor order, no scores
    mixed = [found[0], match("x", 0.105, None), found[1]]
    assert rerank_matches(mixed, p) == mixed
    assert rerank_matches(found, OFF) == found
    assert shortlist(5, p) == 5 and shortlist(2, p) == 3 and shortlist(2, OFF) == 2


def test_the_services_answer_scored_by_the_network_part_uses_each_candidates_stored_descriptor():
    """With ``part`` the score's d² is between the leading parts at unit length of the query's
    descriptor and each candidate's stored one (not the match's distance); a candidate
    whose descriptor was not read, or no query descriptor, leaves the answer unscored."""
    from dataclasses import replace

    from overlapmamba.service.domain import Keyframe, Match
    from overlapmamba.service.ranking import rerank_matches

    rng = np.random.default_rng(11)

    def unit(x: np.ndarray) -> np.ndarray:
        return (x / np.linalg.norm(x)).astype(np.float32)

    query = unit(rng.normal(size=12))
    stored = [unit(rng.normal(size=12)) for _ in range(3)]
    conf = [0.2, 0.9, 0.5]
    found = [
        Match(
            Keyframe(0, k, "r", "s", 0.0, None, "h", 0, 0.0, descriptor=d),
            0.9,
            0.1 + j / 100,
            0.0,
            c,
        )
        for j, (k, d, c) in enumerate(zip("abc", stored, conf, strict=True))
    ]
    p = Rerank(shortlist=3, weight=0.2, part=4)
    out = rerank_matches(found, p, query)
    want = [
        float(((unit(d[:4]) - unit(query[:4])) ** 2).sum()) - 0.2 * c
        for d, c in zip(stored, conf, strict=True)
    ]
    assert [m.score for m in out] == pytest.approx(sorted(want), abs=1e-6)
    assert [m.keyframe.keyframe_id for m in out] == ["abc"[i] for i in np.argsort(want)]
    whole = rerank_matches(found, replace(p, part=None), query)  # the match's own distance
    assert whole[0].score == pytest.approx(
        min(m.distance**2 - 0.2 * c for m, c in zip(found, conf, strict=True))
    )
    unread = [found[0], replace(found[1], keyframe=replace(found[1].keyframe, descriptor=None))]
    assert rerank_matches(unread + found[2:], p, query) == unread + found[2:]
    assert rerank_matches(found, p) == found  # no query descriptor


def test_the_service_scores_by_the_network_only_where_the_models_first_stage_holds_it():
    """rerank.score "network": a mixed first stage scores by its network part (the floats
    ahead of channels × bins), a descriptor first stage by the whole vector, and a spectrum
    alone stops the service naming the model and what is allowed."""
    from types import SimpleNamespace

    from overlapmamba.service.ranking import rerank_params
    from overlapmamba.service.settings import RerankSettings

    def meta(stage: str, dim: int, reduction: dict[str, Any] | None = None) -> Any:
        return SimpleNamespace(
            model_id="om-x",
            first_stage=stage,
            descriptor_dim=dim,
            yaw_channels=16,
            reduction=reduction or {},
        )

    network = RerankSettings(shortlist=10, weight=0.5, score="network")
    assert rerank_params(network, meta("mixed:0.75:32:sqrt", 768)).part == 256
    assert rerank_params(RerankSettings(), meta("mixed:0.75:32:sqrt", 768)).part is None
    assert rerank_params(network, meta("descriptor", 256)).part is None
    with pytest.raises(ValueError, match="om-x.*holds no network descriptor.*allowed"):
        rerank_params(network, meta("spectrum:32:sqrt", 512))
    # a reduced first stage (overlapmamba.train.reduce_head): its network part, if split
    split = meta("mixed:0.75:32:sqrt", 256, {"dim": 256, "network_part": 96})
    assert rerank_params(network, split).part == 96
    assert rerank_params(RerankSettings(), split).part is None
    with pytest.raises(ValueError, match="om-x.*no longer hold the network's own.*allowed"):
        rerank_params(network, meta("mixed:0.75:32:sqrt", 256, {"dim": 256}))
    with pytest.raises(ValueError, match="needs the model's first stage"):
        rerank_params(network)
    with pytest.raises(ValueError, match="score"):
        RerankSettings(score="spectrum")


def test_the_service_takes_a_shortlist_up_to_200_and_names_the_bound_past_it():
    """The row cache keeps a long shortlist's spectra, so the service takes up to 200."""
    from pydantic import ValidationError

    from overlapmamba.service.settings import Settings

    assert Settings(rerank={"shortlist": 200}).rerank.shortlist == 200
    with pytest.raises(ValidationError, match="less than or equal to 200"):
        Settings(rerank={"shortlist": 201})
