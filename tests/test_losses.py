"""Losses: hand-computed values, the no-positive case, and batch-hard mining."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from model_export.losses import (  # noqa: E402
    ImTrihardParams,
    batch_hard_imtrihard,
    imtrihard_loss,
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
    got = batch_hard_imtrihard(desc, overlap)
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
