"""Losses: OverlapTransformer's triplet loss and ImTrihard (paper eq. 13).

Distances are squared L2 between unit descriptors, so d ∈ [0, 4].

Shapes:

    q:        (B, D)      query descriptors
    pos:      (B, P, D)   positive descriptors (overlap > 0.3), padded
    pos_mask: (B, P)      True where a positive exists
    neg:      (B, M, D)   negative descriptors, padded
    neg_mask: (B, M)      True where a negative exists

A query without any positive contributes nothing (the reference code crashes on it), and a
batch without any usable query gives a zero loss that still back-propagates.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


def _sqdist(q: Tensor, x: Tensor) -> Tensor:
    """(B, D), (B, K, D) → (B, K)."""
    return (x - q[:, None, :]).pow(2).sum(-1)


def _mean_over_queries(per_query: Tensor, valid: Tensor) -> Tensor:
    n = valid.sum()
    total = (per_query * valid).sum()
    return total / n.clamp_min(1)  # zero (with a graph) when no query is valid


def triplet_loss(
    q: Tensor, pos: Tensor, pos_mask: Tensor, neg: Tensor, neg_mask: Tensor, margin: float = 0.5
) -> Tensor:
    """OT's lazy triplet: Σ_n [m + max_p d(q, p) − d(q, n)]₊, averaged over queries that have
    at least one positive and one negative. m = 0.5 as in OverlapTransformer."""
    dp = _sqdist(q, pos).masked_fill(~pos_mask, float("-inf")).amax(1)  # hardest positive
    dn = _sqdist(q, neg)
    hinge = (margin + dp[:, None] - dn).clamp_min(0) * neg_mask
    valid = pos_mask.any(1) & neg_mask.any(1)
    per_query = torch.where(valid, hinge.sum(1), torch.zeros_like(dp))
    return _mean_over_queries(per_query, valid)


@dataclass(frozen=True)
class ImTrihardParams:
    """Constants of eq. 13; the paper gives none.

    - ``alpha`` (margin) = 0.5: OT's triplet margin, so the two losses ask for the same gap
      between the hardest positive and the hardest negative and Table IV compares like with
      like.
    - ``lam`` (compression) = 0.1: the absolute pull on positives. It is small against the
      margin term (whose gradient is 1 per hard pair) so it tightens clusters without
      collapsing descriptors; at 1.0 it would rival the margin term and favour a constant
      descriptor for every place.
    - ``k_p`` = ``k_n`` = 1: with one hardest positive and one hardest negative per query the
      "normalisation by the number of samples" is 1 each; queries are averaged.
    - ``hinge`` = True: clamp k_p(α + max d_p) − k_n min d_n at 0 (batch-hard triplet,
      Hermans et al. 2017). Eq. 13 as printed has no hinge; without it, a query that is
      already solved keeps pushing its negatives towards d = 4. ``hinge=False`` is eq. 13
      to the letter.
    """

    alpha: float = 0.5
    lam: float = 0.1
    k_p: float = 1.0
    k_n: float = 1.0
    hinge: bool = True


def imtrihard_loss(
    q: Tensor,
    pos: Tensor,
    pos_mask: Tensor,
    neg: Tensor,
    neg_mask: Tensor,
    params: ImTrihardParams = ImTrihardParams(),
) -> Tensor:
    """λ·mean_p d(q,p) + [k_p(α + max_p d(q,p)) − k_n min_n d(q,n)]₊, averaged over queries."""
    dp_all = _sqdist(q, pos)
    n_pos = pos_mask.sum(1)
    mean_p = (dp_all * pos_mask).sum(1) / n_pos.clamp_min(1)
    max_p = dp_all.masked_fill(~pos_mask, float("-inf")).amax(1)
    min_n = _sqdist(q, neg).masked_fill(~neg_mask, float("inf")).amin(1)
    valid = pos_mask.any(1) & neg_mask.any(1)
    hard = params.k_p * (params.alpha + max_p) - params.k_n * min_n
    if params.hinge:
        hard = hard.clamp_min(0)
    per_query = torch.where(valid, params.lam * mean_p + hard, torch.zeros_like(mean_p))
    return _mean_over_queries(per_query, valid)


def _batch_candidates(desc: Tensor, overlap: Tensor, threshold: float):
    """Every scan of the batch is a query; the others are its positives (overlap above the
    threshold) and negatives. desc: (B, D), overlap: (B, B) → (B, B, D), (B, B), (B, B)."""
    B = desc.shape[0]
    other = ~torch.eye(B, dtype=torch.bool, device=desc.device)
    pos_mask = (overlap > threshold) & other
    neg_mask = (overlap <= threshold) & other
    return desc[None].expand(B, B, -1), pos_mask, neg_mask


def batch_hard_imtrihard(
    desc: Tensor,
    overlap: Tensor,
    threshold: float = 0.3,
    params: ImTrihardParams = ImTrihardParams(),
) -> Tensor:
    """ImTrihard with batch-hard mining from the batch's overlap matrix.

    desc: (B, D); overlap: (B, B) ground-truth overlap between the batch's scans.
    """
    everyone, pos_mask, neg_mask = _batch_candidates(desc, overlap, threshold)
    return imtrihard_loss(desc, everyone, pos_mask, everyone, neg_mask, params)


def batch_triplet(
    desc: Tensor, overlap: Tensor, threshold: float = 0.3, margin: float = 0.5
) -> Tensor:
    """OT's lazy triplet over the batch: each scan's positives and negatives are the other
    scans of the batch, by overlap. desc: (B, D); overlap: (B, B)."""
    everyone, pos_mask, neg_mask = _batch_candidates(desc, overlap, threshold)
    return triplet_loss(desc, everyone, pos_mask, everyone, neg_mask, margin)


BATCH_LOSSES = {"imtrihard": batch_hard_imtrihard, "triplet": batch_triplet}
