"""Relative yaw between two scans from their per-column features (circular cross-correlation).

The model's yaw features are equivariant: turning the sensor rolls them along the columns.
With the projection's convention (columns sweep clockwise, column 0 looks backwards), a
reference scan taken from the same place with the sensor turned by +θ (counter-clockwise
seen from above) has its features rolled by +θ·W/360 columns. So the roll that best aligns
the reference's features with the query's gives θ — the yaw of the reference frame in the
query frame, the same quantity as :func:`overlapmamba.core.poses.yaw_deg` of T_query←ref.

The best integer roll comes from an FFT correlation over all W rolls at once; a parabola
through the peak and its neighbours refines it below one column (0.4° at W = 900).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Spectrum:
    """A reference's yaw features as :func:`correlate` takes them: each channel's spectrum
    (C, W // 2 + 1) complex128, the features' norm once each channel's mean is taken out, and
    the width W. A map's keyframe gives the same one to every query, so a service keeps the
    spectra of the keyframes searched last (``overlapmamba.service.backends.rows``)."""

    bins: np.ndarray
    norm: float
    width: int

    @property
    def nbytes(self) -> int:
        return int(self.bins.nbytes)


def _spectra(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K, C, W) float64 → spectra (K, C, F) and centred norms (K,). The norms come from sums
    and the DC bins (‖r − r̄‖² = Σ r² − Σ_c DC_c² / W), so no centred copy is made.

    The difference cancels where the maps are (nearly) constant: what is left of it is
    rounding, not variance, and such a map's norm is 0 (it correlates with nothing)."""
    W = x.shape[-1]
    bins = np.fft.rfft(x, axis=-1)
    # einsum, not vdot: BLAS would wake its own thread pool on cores the encoder is using
    total = np.einsum("kcw,kcw->k", x, x)
    centred = total - (bins[..., 0].real ** 2).sum(-1) / W
    centred = np.where(centred > _CANCELLED * total, centred, 0.0)
    return bins, np.sqrt(centred)


# rounding leaves about W·ε (≈ 1e-13 at W = 900) of Σ r² in the difference
_CANCELLED = 1e-9


def spectra(refs: np.ndarray) -> list[Spectrum]:
    """refs (K, C, W) or (C, W), of any float type (stored: float16) → one
    :class:`Spectrum` each, from one FFT call in float64."""
    r = np.asarray(refs)
    if r.ndim == 2:
        r = r[None]
    if r.ndim != 3:
        raise ValueError(f"yaw features must have shape (K, C, W) or (C, W); got {r.shape}")
    bins, norms = _spectra(r.astype(np.float64))
    W = r.shape[-1]
    return [Spectrum(b, float(n), W) for b, n in zip(bins, norms, strict=True)]


def as_spectra(refs: Sequence[np.ndarray | Spectrum]) -> list[Spectrum]:
    """Yaw features (C, W) and spectra, mixed → spectra; the features transformed in one FFT
    call."""
    arrays = [(j, r) for j, r in enumerate(refs) if not isinstance(r, Spectrum)]
    out = {j: r for j, r in enumerate(refs) if isinstance(r, Spectrum)}
    if arrays:
        made = spectra(np.stack([r for _, r in arrays]))
        out.update({j: sp for (j, _), sp in zip(arrays, made, strict=True)})
    return [out[j] for j in range(len(refs))]


def correlate(query: np.ndarray, refs: Sequence[Spectrum]) -> np.ndarray:
    """query (C, W), K reference spectra → (K, W): cosine similarity of the query with each
    reference rolled back by k columns, for every k, each map taken zero-mean per channel.

    The query's spectrum without its DC bins is the zero-mean query, which makes the
    references' means drop out of every product; corr[k] = Σ_c Σ_w q[c, w] · r[c, w + k] is
    one inverse FFT of the channels' summed products per reference."""
    q = np.asarray(query, dtype=np.float64)
    if q.ndim != 2:
        raise ValueError(f"the query's yaw features must have shape (C, W); got {q.shape}")
    C, W = q.shape
    F = W // 2 + 1
    for r in refs:
        if r.width != W or r.bins.shape != (C, F):
            raise ValueError(
                f"feature shapes differ: query {q.shape}, reference {(r.bins.shape[0], r.width)}"
            )
    if not refs:
        return np.zeros((0, W))
    qbins, qnorm = _spectra(q[None])
    qs = qbins[0].conj()
    qs[:, 0] = 0.0  # the query's channel means
    products = np.stack([r.bins for r in refs])  # (K, C, F): a copy, so the cached stay whole
    products *= qs
    num = np.fft.irfft(products.sum(axis=1), n=W, axis=-1)
    denom = qnorm[0] * np.array([r.norm for r in refs])
    # a constant map (norm 0) correlates with nothing: 0, never rounding over rounding
    cos = np.divide(num, denom[:, None], out=np.zeros_like(num), where=denom[:, None] > 0)
    return np.clip(cos, -1.0, 1.0)


def circular_correlation(query: np.ndarray, refs: np.ndarray) -> np.ndarray:
    """query (C, W), refs (K, C, W) or (C, W) → (K, W): :func:`correlate` of the query with
    the references' :func:`spectra`, computed in float64 (refs may come as stored, float16)."""
    q = np.asarray(query)
    r = np.asarray(refs)
    if r.ndim == 2:
        r = r[None]
    if q.ndim != 2 or q.shape != r.shape[1:]:
        raise ValueError(f"feature shapes differ: query {q.shape}, references {r.shape[1:]}")
    return correlate(q, spectra(r))


def estimate_yaw(
    query: np.ndarray, refs: np.ndarray | Sequence[Spectrum]
) -> tuple[np.ndarray, np.ndarray]:
    """Yaw (degrees, (−180, 180]) of each reference relative to the query, and a confidence:
    the cosine similarity of the features at the best roll, in [−1, 1].

    query: (C, W); refs: (K, C, W) or (C, W), or K :class:`Spectrum` → yaw (K,),
    confidence (K,)
    """
    if isinstance(refs, np.ndarray):
        corr = circular_correlation(query, refs)
    else:
        corr = correlate(query, list(refs))
    K, W = corr.shape
    k = corr.argmax(axis=1)
    rows = np.arange(K)
    left, mid, right = corr[rows, (k - 1) % W], corr[rows, k], corr[rows, (k + 1) % W]
    denom = left - 2 * mid + right
    # Vertex of the parabola through the three samples; flat peaks stay on the sample.
    frac = np.where(
        np.abs(denom) > 1e-12, 0.5 * (left - right) / np.where(denom == 0, 1, denom), 0.0
    )
    shift = k + np.clip(frac, -0.5, 0.5)
    yaw = shift * 360.0 / W
    yaw = (yaw + 180.0) % 360.0 - 180.0
    yaw = np.where(yaw == -180.0, 180.0, yaw)
    return yaw, mid
