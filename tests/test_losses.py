"""Losses: hand-computed values, the no-positive case, and batch-hard mining."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from overlapmamba.train.losses import (  # noqa: E402
    BandRanking,
    ImTrihardParams,
    batch_hard_imtrihard,
    batch_spread,
    batch_triplet,
    imtrihard_loss,
    pair_masks,
    triplet_loss,
)


def unit(*rows):
    return torch.nn.functional.normalize(torch.tensor(rows, dtype=torch.float64), dim=-1)


def case():
    q = unit([1.0, 0.0])
    pos = unit([1.0, 0.1], [0.8, 0.6])[None]  # d = 0.00997, 0.4
    neg = unit([0.6, 0.8], [-1.0, 0.0])[None]  # d = 0.8, 4.0
    return q, pos, torch.tensor([[True, True]]), neg, torch.tensor([[True, True]])


def test_triplet_loss_by_hand():
    q, pos, pm, neg, nm = case()
    # hardest positive d = 0.4: [0.5 + 0.4 − 0.8]₊ + [0.5 + 0.4 − 4]₊ = 0.1
    torch.testing.assert_close(triplet_loss(q, pos, pm, neg, nm).item(), 0.1, atol=1e-6, rtol=0)


def test_imtrihard_by_hand():
    q, pos, pm, neg, nm = case()
    d_pos = (1 - 1 / (1.01**0.5)) * 2  # |q − p|² for unit vectors = 2 − 2 cos
    mean_p = (d_pos + 0.4) / 2
    expected = 0.1 * mean_p + max(0.0, 0.5 + 0.4 - 0.8)
    torch.testing.assert_close(
        imtrihard_loss(q, pos, pm, neg, nm).item(), expected, atol=1e-6, rtol=0
    )
    literal = ImTrihardParams(hinge=False)
    solved = unit([-1.0, 0.0], [0.0, -1.0])[None]  # negatives far away: d = 4, 2
    value = imtrihard_loss(q, pos, pm, solved, nm, literal).item()
    torch.testing.assert_close(value, 0.1 * mean_p + 0.5 + 0.4 - 2.0, atol=1e-6, rtol=0)
    assert imtrihard_loss(q, pos, pm, solved, nm).item() == pytest.approx(0.1 * mean_p)


@pytest.mark.parametrize("loss", [triplet_loss, imtrihard_loss])
def test_query_without_positives_neither_crashes_nor_counts(loss):
    q, pos, pm, neg, nm = case()
    q2 = torch.cat([q, q]).requires_grad_()
    pos2, neg2 = torch.cat([pos, pos]), torch.cat([neg, neg])
    pm2 = torch.tensor([[True, True], [False, False]])
    value = loss(q2, pos2, pm2, neg2, torch.cat([nm, nm]))
    torch.testing.assert_close(value, loss(q, pos, pm, neg, nm))
    value.backward()
    assert torch.isfinite(q2.grad).all() and q2.grad[1].abs().sum() == 0
    none = loss(q2, pos2, torch.zeros_like(pm2), neg2, torch.cat([nm, nm]))
    assert none.item() == 0.0 and none.requires_grad


def test_batch_hard_mining_matches_explicit_tuples():
    g = torch.Generator().manual_seed(0)
    desc = torch.nn.functional.normalize(
        torch.randn(5, 8, generator=g, dtype=torch.float64), dim=-1
    )
    overlap = torch.rand(5, 5, generator=g, dtype=torch.float64)
    overlap = (overlap + overlap.T) / 2
    got = batch_hard_imtrihard(desc, overlap).value
    per_query = []
    for i in range(5):
        others = [j for j in range(5) if j != i]
        p = [j for j in others if overlap[i, j] > 0.3]
        n = [j for j in others if overlap[i, j] <= 0.3]
        if not p or not n:
            continue
        per_query.append(
            imtrihard_loss(
                desc[[i]],
                desc[p][None],
                torch.ones(1, len(p), dtype=torch.bool),
                desc[n][None],
                torch.ones(1, len(n), dtype=torch.bool),
            )
        )
    torch.testing.assert_close(got, torch.stack(per_query).mean())


def test_ambiguous_band_is_neither_positive_nor_negative():
    overlap = torch.tensor([[1.0, 0.8, 0.2, 0.05], [0.8, 1.0, 0.0, 0.3], [0.2, 0.0, 1.0, 0.1]])
    overlap = torch.cat([overlap, torch.tensor([[0.05, 0.3, 0.1, 1.0]])])
    pos, neg = pair_masks(overlap, 0.3, 0.1)
    assert pos[0].tolist() == [False, True, False, False]
    assert neg[0].tolist() == [False, False, False, True]  # 0.2 is in the band: neither
    assert neg[1].tolist() == [False, False, True, False]  # 0.3 is not above 0.3: neither
    old_pos, old_neg = pair_masks(overlap, 0.3, 0.3)  # the old split: everything else negative
    assert (old_pos | old_neg | torch.eye(4, dtype=torch.bool)).all()
    with pytest.raises(ValueError, match="must not exceed"):
        pair_masks(overlap, 0.3, 0.4)


def two_places(scale: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Two places of two scans each; every distance scales with ``scale``."""
    base = torch.tensor([[0.0, 0.0], [0.1, 0.0], [1.0, 0.0], [1.0, 0.12]], dtype=torch.float64)
    desc = torch.nn.functional.normalize(
        torch.cat([torch.ones(4, 1, dtype=torch.float64), base * scale], 1), dim=-1
    )
    overlap = torch.tensor(
        [[1, 0.9, 0, 0], [0.9, 1, 0, 0], [0, 0, 1, 0.9], [0, 0, 0.9, 1]], dtype=torch.float64
    )
    return desc, overlap


def test_relative_margin_follows_the_scale_and_active_counts_hinges():
    for scale in (0.05, 0.5):
        desc, overlap = two_places(scale)
        out = batch_hard_imtrihard(desc, overlap, params=ImTrihardParams(alpha=0.5, lam=0.0))
        assert out.active == 1.0 and out.margin == 0.5  # 0.5 dwarfs every distance here
        rel = batch_hard_imtrihard(
            desc, overlap, params=ImTrihardParams(alpha=0.5, lam=0.0), scale="relative"
        )
        spread = batch_spread(desc).item()
        assert rel.margin == pytest.approx(0.5 * spread)
        assert rel.active == 0.0 and rel.value.item() == 0.0  # every query solved at its scale
    # the same geometry at two scales: the relative margin gives the same verdict
    small = batch_triplet(*two_places(0.05), margin=3.0, scale="relative")
    large = batch_triplet(*two_places(0.5), margin=3.0, scale="relative")
    assert small.active == large.active == 1.0
    assert small.value.item() < large.value.item()


def test_batch_loss_with_no_usable_query_reports_nan_active():
    desc = torch.nn.functional.normalize(torch.randn(3, 4, dtype=torch.float64), dim=-1)
    out = batch_hard_imtrihard(desc.requires_grad_(), torch.eye(3, dtype=torch.float64))
    assert out.value.item() == 0.0 and out.value.requires_grad and out.active != out.active


def test_normalised_scale_makes_the_loss_blind_to_shrinking():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(8, 6, generator=g, dtype=torch.float64)
    overlap = (torch.rand(8, 8, generator=g, dtype=torch.float64) > 0.6).double()
    overlap = torch.maximum(overlap, overlap.T)
    params = ImTrihardParams(alpha=0.5, lam=0.1)
    big = batch_hard_imtrihard(x, overlap, params=params, scale="normalised")
    small = batch_hard_imtrihard(0.01 * x, overlap, params=params, scale="normalised")
    torch.testing.assert_close(big.value, small.value)  # the same loss at any scale
    assert small.margin == pytest.approx(1e-4 * big.margin)  # reported in distance units
    # the gradient has no component along "shrink everything": it is orthogonal to x
    x.requires_grad_(True)
    batch_hard_imtrihard(x, overlap, params=params, scale="normalised").value.backward()
    assert abs(float((x.grad * x.detach()).sum())) < 1e-9
    absolute = batch_hard_imtrihard(x.detach().requires_grad_(), overlap, params=params)
    assert absolute.value.item() > 0
    with pytest.raises(ValueError, match="allowed: absolute, relative, normalised"):
        batch_hard_imtrihard(x, overlap, scale="cosine")


def test_batch_spread_matches_pairwise_distances():
    x = torch.randn(5, 3, dtype=torch.float64)
    d = torch.cdist(x, x).pow(2)
    torch.testing.assert_close(batch_spread(x), d.sum() / 20)


def test_band_ranking_orders_neighbours_below_positives_and_nothing_else():
    """Scan 0 has a positive (1, overlap 0.8), a band neighbour (2, overlap 0.2) and a clear
    negative (3). The band term is weight · [α_b + d(0,1) − d(0,2)]₊ for each query with a
    positive and a band scan, averaged over those queries; the main term is unchanged."""
    desc = unit([1.0, 0.0], [0.6, 0.8], [0.8, 0.6], [-1.0, 0.0])  # d(0,1) 0.8, d(0,2) 0.4
    overlap = torch.tensor(
        [[1, 0.8, 0.2, 0], [0.8, 1, 0, 0], [0.2, 0, 1, 0], [0, 0, 0, 1]], dtype=torch.float64
    )
    params = ImTrihardParams(alpha=0.1, lam=0.0)
    plain = batch_hard_imtrihard(desc, overlap, params=params, negative=0.1)
    band = BandRanking(weight=0.5, alpha=0.1)
    both = batch_hard_imtrihard(desc, overlap, params=params, negative=0.1, band=band)
    # queries 0 and 2 have a band scan; only 0 also has a positive: 0.5·[0.1 + 0.8 − 0.4]₊
    assert both.value.item() == pytest.approx(plain.value.item() + 0.5 * 0.5)
    assert both.band_active == 1.0 and plain.band_active != plain.band_active  # NaN: off
    assert both.active == plain.active and both.margin == plain.margin
    # solved: the neighbour farther than the positive by more than α_b → no band loss
    far = unit([1.0, 0.0], [0.95, 0.3122], [0.0, 1.0], [-1.0, 0.0])
    solved = batch_hard_imtrihard(far, overlap, params=params, negative=0.1, band=band)
    unbanded = batch_hard_imtrihard(far, overlap, params=params, negative=0.1)
    assert solved.value.item() == pytest.approx(unbanded.value.item())
    assert solved.band_active == 0.0
    # the band term pushes the band scan away from the query (never pulls it) and pulls the
    # positive in: its own gradient (with band minus without) on each
    grads = []
    for b in (band, None):
        x = desc.clone().requires_grad_(True)
        batch_hard_imtrihard(x, overlap, params=params, negative=0.1, band=b).value.backward()
        grads.append(x.grad)
    g = grads[0] - grads[1]
    away = desc[2] - desc[0]
    assert float((-g[2] * away).sum()) > 0 and float((-g[1] * (desc[1] - desc[0])).sum()) < 0


def test_consistency_counts_moves_beyond_the_allowance_at_the_batchs_scale():
    from overlapmamba.train.losses import batch_spread, consistency

    g = torch.Generator().manual_seed(0)
    desc = torch.nn.functional.normalize(torch.randn(8, 16, generator=g), dim=1)
    turned = torch.nn.functional.normalize(desc + 0.05 * torch.randn(8, 16, generator=g), dim=1)
    spread = batch_spread(desc)
    moved = (desc - turned).pow(2).sum(1) / spread  # in units of the spread
    assert float(consistency(desc, desc, spread)) == 0.0
    full = consistency(desc, turned, spread)
    assert float(full) == pytest.approx(float(moved.mean()), rel=1e-6)
    # an allowance above every move makes the term 0; one in between counts the excess only
    assert float(consistency(desc, turned, spread, float(moved.max()) + 1e-6)) == 0.0
    mid = float(moved.median())
    expected = torch.relu(moved - mid).mean()
    assert float(consistency(desc, turned, spread, mid)) == pytest.approx(float(expected))
    # scale-free: every descriptor gathered towards one point (distances × 0.1) costs the same
    centre = desc.mean(0)
    small, small_t = centre + 0.1 * (desc - centre), centre + 0.1 * (turned - centre)
    gathered = consistency(small, small_t, batch_spread(small), mid)
    assert float(gathered) == pytest.approx(float(expected), rel=1e-4)
    # its gradient pulls each scan towards its turned copy
    x = desc.clone().requires_grad_(True)
    consistency(x, turned, batch_spread(x)).backward()
    step = x.detach() - 0.01 * x.grad
    assert float((step - turned).pow(2).sum(1).mean()) < float((desc - turned).pow(2).sum(1).mean())
