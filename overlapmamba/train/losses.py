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

**Margins and the descriptors' scale.** At initialisation the mean squared distance between
any two scans is ≈ 0.02, far below OverlapTransformer's margin of 0.5. With that margin every
hinge is active at every step, the loss is linear in the distances, and shrinking every
descriptor towards one point lowers it whenever the hardest positive is about as far as the
hardest negative: the loss sits at α while the descriptors collapse. Two remedies, both
options of the batch losses:

- an absolute margin at the descriptors' scale (``alpha``/``margin`` of a few hundredths);
- ``scale="relative"``: the margin is α times the batch's spread (mean squared distance
  between its scans, not back-propagated), so it follows the scale as training changes it.
  Measured: this alone does not stop a collapse (a margin that shrinks with the spread
  still lets shrinking lower the loss);
- ``scale="normalised"``: every distance is divided by the spread, gradient included, so the
  loss is invariant to the descriptors' scale and shrinking cannot lower it.

The batch losses also report how many hinge terms were active (:class:`BatchLoss`), the
number that shows a collapse: 100 % active with a falling spread.

**The ambiguous band** (neighbouring places, overlap between the negative and the positive
threshold) is neither pulled nor pushed by the main term. Measured on the shipped model
(val town, same-direction subset at its F1max threshold): 25 of its 31 false alarms were
such neighbours, 15–50 m away with overlap 0.12–0.30, ranked above the place's true loop or
accepted where there was none. :class:`BandRanking` is an optional second ImTrihard term
that only *orders* them: the hardest positive must be nearer than the nearest band scan by
its own, smaller margin — a band scan is never pulled, and is pushed only as far as the
positives are near.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import Tensor


def _sqdist(q: Tensor, x: Tensor) -> Tensor:
    """(B, D), (B, K, D) → (B, K)."""
    return (x - q[:, None, :]).pow(2).sum(-1)


def _mean_over_queries(per_query: Tensor, valid: Tensor) -> Tensor:
    n = valid.sum()
    total = (per_query * valid).sum()
    return total / n.clamp_min(1)  # zero (with a graph) when no query is valid


def _active(pre_hinge: Tensor, mask: Tensor) -> float:
    """Share of the hinge terms selected by ``mask`` that are > 0 (NaN when there are none)."""
    n = int(mask.sum())
    return float(((pre_hinge > 0) & mask).sum()) / n if n else float("nan")


def _triplet(q, pos, pos_mask, neg, neg_mask, margin: float) -> tuple[Tensor, float]:
    dp = _sqdist(q, pos).masked_fill(~pos_mask, float("-inf")).amax(1)  # hardest positive
    dn = _sqdist(q, neg)
    pre = margin + dp[:, None] - dn
    valid = pos_mask.any(1) & neg_mask.any(1)
    hinge = pre.clamp_min(0) * neg_mask
    per_query = torch.where(valid, hinge.sum(1), torch.zeros_like(dp))
    return _mean_over_queries(per_query, valid), _active(pre.detach(), neg_mask & valid[:, None])


def triplet_loss(
    q: Tensor, pos: Tensor, pos_mask: Tensor, neg: Tensor, neg_mask: Tensor, margin: float = 0.5
) -> Tensor:
    """OT's lazy triplet: Σ_n [m + max_p d(q, p) − d(q, n)]₊, averaged over queries that have
    at least one positive and one negative. m = 0.5 as in OverlapTransformer."""
    return _triplet(q, pos, pos_mask, neg, neg_mask, margin)[0]


@dataclass(frozen=True)
class ImTrihardParams:
    """Constants of eq. 13; the paper gives none.

    - ``alpha`` (margin) = 0.5: OT's triplet margin, so the two losses ask for the same gap
      between the hardest positive and the hardest negative. Measured: far above the
      descriptors' scale (see the module notes); the training recipe sets its own.
    - ``lam`` (compression) = 0.1: the absolute pull on positives. With every hinge active it
      adds to the collapse; the training recipe sets its own.
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


def _imtrihard(q, pos, pos_mask, neg, neg_mask, params: ImTrihardParams) -> tuple[Tensor, float]:
    dp_all = _sqdist(q, pos)
    n_pos = pos_mask.sum(1)
    mean_p = (dp_all * pos_mask).sum(1) / n_pos.clamp_min(1)
    max_p = dp_all.masked_fill(~pos_mask, float("-inf")).amax(1)
    min_n = _sqdist(q, neg).masked_fill(~neg_mask, float("inf")).amin(1)
    valid = pos_mask.any(1) & neg_mask.any(1)
    pre = params.k_p * (params.alpha + max_p) - params.k_n * min_n
    hard = pre.clamp_min(0) if params.hinge else pre
    per_query = torch.where(valid, params.lam * mean_p + hard, torch.zeros_like(mean_p))
    return _mean_over_queries(per_query, valid), _active(pre.detach(), valid)


def imtrihard_loss(
    q: Tensor,
    pos: Tensor,
    pos_mask: Tensor,
    neg: Tensor,
    neg_mask: Tensor,
    params: ImTrihardParams = ImTrihardParams(),
) -> Tensor:
    """λ·mean_p d(q,p) + [k_p(α + max_p d(q,p)) − k_n min_n d(q,n)]₊, averaged over queries."""
    return _imtrihard(q, pos, pos_mask, neg, neg_mask, params)[0]


@dataclass(frozen=True)
class BandRanking:
    """The band term: ``weight`` · [α_band + max_p d(q,p) − min_b d(q,b)]₊ per query that has
    a positive and a band scan (overlap in (negative, positive]); ``alpha`` is in the units
    of the main margin (the spread's, with the normalised scale)."""

    weight: float = 0.5
    alpha: float = 0.2


def _band_term(x: Tensor, pos_mask: Tensor, band_mask: Tensor, band: BandRanking):
    """→ (the term averaged over its queries, share of its hinges that were active)."""
    d = _sqdist(x, x[None].expand(x.shape[0], -1, -1))
    max_p = d.masked_fill(~pos_mask, float("-inf")).amax(1)
    min_b = d.masked_fill(~band_mask, float("inf")).amin(1)
    valid = pos_mask.any(1) & band_mask.any(1)
    pre = band.alpha + max_p - min_b
    per_query = torch.where(valid, band.weight * pre.clamp_min(0), torch.zeros_like(max_p))
    return _mean_over_queries(per_query, valid), _active(pre.detach(), valid)


@dataclass(frozen=True)
class BatchLoss:
    """A batch loss and what it did.

    - ``value``: the scalar to back-propagate;
    - ``active``: share of the hinge terms that were > 0 (ImTrihard: one per query; triplet:
      one per query and negative); NaN when the batch had no usable query;
    - ``margin``: the margin actually used, in squared-distance units (α, or α × spread);
    - ``band_active``: the band term's active share (NaN when it is off or had no query).
    """

    value: Tensor
    active: float
    margin: float
    band_active: float = math.nan


def pair_masks(
    overlap: Tensor, positive: float = 0.3, negative: float = 0.3
) -> tuple[Tensor, Tensor]:
    """(B, B) overlap → positive and negative masks over ordered pairs of distinct scans.

    Positives overlap more than ``positive``; negatives at most ``negative``. With
    ``negative`` < ``positive`` the pairs in between (an ambiguous band: neighbouring places
    that share a little) are neither."""
    if not negative <= positive:
        raise ValueError(f"negative threshold {negative} must not exceed positive {positive}")
    B = overlap.shape[0]
    other = ~torch.eye(B, dtype=torch.bool, device=overlap.device)
    return (overlap > positive) & other, (overlap <= negative) & other


def batch_spread(desc: Tensor) -> Tensor:
    """Mean squared distance between the distinct scans of a batch (B ≥ 2), a scalar:
    Σ_{i≠j} |x_i − x_j|² = 2B Σ|x_i|² − 2|Σ x_i|², with no square root to differentiate."""
    B = desc.shape[0]
    total = 2 * B * desc.pow(2).sum() - 2 * desc.sum(0).pow(2).sum()
    return total.clamp_min(0) / max(1, B * (B - 1))


def consistency(desc: Tensor, moved: Tensor, spread: Tensor, allowance: float = 0.0) -> Tensor:
    """How far scans' descriptors ``desc`` (T, D) are from those of copies of the same scans
    ``moved`` (T, D): turned about z by a continuous angle (the turn term) or seen as
    another sensor sees them (the sensor term). The mean of (squared distance ÷ the
    batch's ``spread`` − ``allowance``)⁺, the spread with its gradient. So a copy nearer
    than ``allowance`` spreads costs nothing, and gathering every descriptor towards
    one point lowers nothing: measured with an allowance in absolute units, the run shrank
    its spread 13× within 200 steps and met a cosine bar that way (README, Training: the
    turn term). The circular network ignores whole-column turns exactly, but a fraction of a
    column re-bins every point, and training alone let that move grow."""
    away = (desc - moved).pow(2).sum(1) / spread.clamp_min(1e-12)
    return torch.relu(away - allowance).mean()


def with_copy_terms(
    value: Tensor,
    desc: Tensor,
    turned: Tensor,
    looked_at: Any,  # (L,) indices into the batch, an index array or a list
    looked: Tensor,
    turn: tuple[float, float],
    look_weight: float,
) -> tuple[Tensor, float, float]:
    """The consistency terms of a batch's copies: ``turned`` (T, D) of its first T scans,
    ``looked`` of the scans ``looked_at`` seen as another sensor; ``turn`` is the turn
    term's (weight, allowance). → (the loss ``value`` with those terms added; the mean
    squared distance of a turned copy and of a sensor copy to its scan, NaN without)."""
    d_turn = d_look = math.nan
    if T := len(turned):
        value = value + turn[0] * consistency(desc[:T], turned, batch_spread(desc), turn[1])
        d_turn = float((desc[:T] - turned).detach().pow(2).sum(1).mean())
    if len(looked_at):
        value = value + look_weight * consistency(desc[looked_at], looked, batch_spread(desc))
        d_look = float((desc[looked_at] - looked).detach().pow(2).sum(1).mean())
    return value, d_turn, d_look


SCALES = ("absolute", "relative", "normalised")


def _scaled(desc: Tensor, base: float, scale: str) -> tuple[Tensor, float, float]:
    """→ (descriptors the loss sees, its margin, that margin in squared-distance units).

    - ``absolute``: the descriptors and the margin as given;
    - ``relative``: the margin is ``base`` × the batch's spread (not back-propagated);
    - ``normalised``: distances are divided by the batch's spread, *with* its gradient, so
      the loss is unchanged when every distance is scaled: shrinking the descriptors towards
      one point can no longer lower it; the margin is ``base`` in units of the spread."""
    if scale not in SCALES:
        raise ValueError(f"margin scale {scale!r} is unknown; allowed: {', '.join(SCALES)}")
    if scale == "absolute":
        return desc, base, base
    spread = batch_spread(desc)
    if scale == "relative":
        m = base * float(spread.detach())
        return desc, m, m
    return desc / spread.clamp_min(1e-12).sqrt(), base, base * float(spread.detach())


def batch_hard_imtrihard(
    desc: Tensor,
    overlap: Tensor,
    threshold: float = 0.3,
    params: ImTrihardParams = ImTrihardParams(),
    *,
    negative: float | None = None,
    scale: str = "absolute",
    band: BandRanking | None = None,
) -> BatchLoss:
    """ImTrihard with batch-hard mining from the batch's overlap matrix.

    desc: (B, D); overlap: (B, B) ground-truth overlap between the batch's scans. Every scan
    is a query; its positives and negatives are the other scans (:func:`pair_masks`,
    ``negative`` defaults to ``threshold``). ``band``: add :class:`BandRanking`'s term over
    the pairs between the two thresholds."""
    neg_t = threshold if negative is None else negative
    pos_mask, neg_mask = pair_masks(overlap, threshold, neg_t)
    x, alpha, used = _scaled(desc, params.alpha, scale)
    everyone = x[None].expand(x.shape[0], -1, -1)
    value, active = _imtrihard(
        x, everyone, pos_mask, everyone, neg_mask, replace(params, alpha=alpha)
    )
    band_active = math.nan
    if band is not None and band.weight > 0:
        other = ~torch.eye(x.shape[0], dtype=torch.bool, device=x.device)
        band_mask = other & ~pos_mask & ~neg_mask
        term, band_active = _band_term(x, pos_mask, band_mask, band)
        value = value + term
    return BatchLoss(value, active, used, band_active)


def batch_triplet(
    desc: Tensor,
    overlap: Tensor,
    threshold: float = 0.3,
    margin: float = 0.5,
    *,
    negative: float | None = None,
    scale: str = "absolute",
) -> BatchLoss:
    """OT's lazy triplet over the batch: each scan's positives and negatives are the other
    scans of the batch, by overlap. desc: (B, D); overlap: (B, B)."""
    pos_mask, neg_mask = pair_masks(overlap, threshold, threshold if negative is None else negative)
    x, m, used = _scaled(desc, margin, scale)
    everyone = x[None].expand(x.shape[0], -1, -1)
    value, active = _triplet(x, everyone, pos_mask, everyone, neg_mask, m)
    return BatchLoss(value, active, used)


BATCH_LOSSES: dict[str, Callable[..., BatchLoss]] = {
    "imtrihard": batch_hard_imtrihard,
    "triplet": batch_triplet,
}
