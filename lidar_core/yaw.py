"""Relative yaw between two scans from their per-column features (circular cross-correlation).

The model's yaw features are equivariant: turning the sensor rolls them along the columns.
With the projection's convention (columns sweep clockwise, column 0 looks backwards), a
reference scan taken from the same place with the sensor turned by +θ (counter-clockwise
seen from above) has its features rolled by +θ·W/360 columns. So the roll that best aligns
the reference's features with the query's gives θ — the yaw of the reference frame in the
query frame, the same quantity as :func:`lidar_core.poses.yaw_deg` of T_query←ref.

The best integer roll comes from an FFT correlation over all W rolls at once; a parabola
through the peak and its neighbours refines it below one column (0.4° at W = 900).
"""

from __future__ import annotations

import numpy as np


def _normalise(f: np.ndarray) -> np.ndarray:
    """Zero-mean per channel, unit norm over the whole (C, W) map."""
    f = np.asarray(f, dtype=np.float64)
    f = f - f.mean(axis=-1, keepdims=True)
    n = np.sqrt((f * f).sum(axis=(-2, -1), keepdims=True))
    return f / np.maximum(n, 1e-12)


def circular_correlation(query: np.ndarray, refs: np.ndarray) -> np.ndarray:
    """query (C, W), refs (K, C, W) → (K, W): cosine similarity of the query with each
    reference rolled back by k columns, for every k."""
    q = _normalise(query)
    r = _normalise(refs)
    if r.ndim == 2:
        r = r[None]
    if q.shape != r.shape[1:]:
        raise ValueError(f"feature shapes differ: query {q.shape}, references {r.shape[1:]}")
    # corr[k] = Σ_c Σ_w q[c, w] · r[c, w + k]
    spec = np.conj(np.fft.rfft(q, axis=-1))[None] * np.fft.rfft(r, axis=-1)
    return np.fft.irfft(spec.sum(axis=1), n=q.shape[-1], axis=-1)


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
