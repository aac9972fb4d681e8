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

import numpy as np


def circular_correlation(query: np.ndarray, refs: np.ndarray) -> np.ndarray:
    """query (C, W), refs (K, C, W) → (K, W): cosine similarity of the query with each
    reference rolled back by k columns, for every k, each map taken zero-mean per channel.

    Computed from spectra, in float64 (refs may come as stored, float16), the query and the
    references in one array and one FFT call: the query's spectrum without its DC bins is
    the zero-mean query, which makes the references' means drop out of every product; the
    norms come from sums and the DC bins (‖r − r̄‖² = Σ r² − Σ_c DC_c² / W), and the products
    are taken in place in the references' spectra, so no centred or normalised copy of a map
    is made. (One array and one FFT call instead of a cast and an FFT per side: estimate_yaw
    on five 16 × 900 references, old and new timed in turn, 0.39 → 0.37 ms p50 in one run
    and 0.73 → 0.54 ms in another, at the machine's slower speed.)"""
    q = np.asarray(query)
    r = np.asarray(refs)
    if r.ndim == 2:
        r = r[None]
    if q.ndim != 2 or q.shape != r.shape[1:]:
        raise ValueError(f"feature shapes differ: query {q.shape}, references {r.shape[1:]}")
    K, C, W = r.shape
    x = np.empty((K + 1, C, W), dtype=np.float64)
    x[0] = q
    x[1:] = r
    spectra = np.fft.rfft(x, axis=-1)  # (K + 1, C, F)
    # einsum, not vdot: BLAS would wake its own thread pool on cores the encoder is using
    centred = np.einsum("kcw,kcw->k", x, x) - (spectra[..., 0].real ** 2).sum(-1) / W
    norms = np.sqrt(np.maximum(centred, 0.0))
    qs = spectra[0].conj()
    qs[:, 0] = 0.0  # the query's channel means
    rs = spectra[1:]
    rs *= qs  # corr[k] = Σ_c Σ_w q[c, w] · r[c, w + k]
    num = np.fft.irfft(rs.sum(axis=1), n=W, axis=-1)
    return num / np.maximum(norms[0] * norms[1:], 1e-12)[:, None]


def estimate_yaw(query: np.ndarray, refs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Yaw (degrees, (−180, 180]) of each reference relative to the query, and a confidence:
    the cosine similarity of the features at the best roll, in [−1, 1].

    query: (C, W); refs: (K, C, W) or (C, W) → yaw (K,), confidence (K,)
    """
    corr = circular_correlation(query, refs)
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
