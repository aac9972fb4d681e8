"""Scan Context (Kim & Kim, IROS 2018), written from the paper: the hand-crafted baseline.

    points (N, 3) → scan context (rings, sectors): max height per polar bin, 0 where empty
                  → ring key (rings,): fraction of occupied sectors per ring (rotation-invariant)

Search (paper §III-C/D): the ring keys pick ``candidates`` nearest neighbours; each is scored
by the column-shift distance

    d(q, c) = min_n  1 − (1/|V_n|) Σ_{j ∈ V_n} ⟨q_j, c_{j+n}⟩ / (‖q_j‖ ‖c_{j+n}‖)

over the sector shifts n (V_n: columns non-empty in both, as in the authors' code), and the
best shift is the yaw: turning the sensor by θ moves the columns by θ / (360° / sectors).

Heights are ``z + lidar_height`` clipped at 0, so the ground around a sensor mounted about
that high is ≈ 0 and empty bins stay distinguishable (the authors' code adds 2 m the same way).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from overlapmamba.core.metrics import nearest


@dataclass(frozen=True)
class ScanContextParams:
    rings: int = 20
    sectors: int = 60
    max_range: float = 80.0  # m
    lidar_height: float = 2.0  # m added to z
    candidates: int = 10  # ring-key nearest neighbours re-ranked by the shift distance

    def __post_init__(self) -> None:
        if self.rings < 1 or self.sectors < 1 or self.candidates < 1 or self.max_range <= 0:
            raise ValueError("rings, sectors and candidates must be ≥ 1 and max_range > 0")


def scan_context(xyz: np.ndarray, params: ScanContextParams = ScanContextParams()) -> np.ndarray:
    """(N, 3) points in the sensor frame → (rings, sectors) float32 max heights."""
    p = params
    xyz = np.asarray(xyz, dtype=np.float64)
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    r = np.hypot(x, y)
    keep = np.isfinite(r) & np.isfinite(z) & (r > 0) & (r < p.max_range)
    x, y, z, r = x[keep], y[keep], z[keep], r[keep]
    ring = np.minimum((r / p.max_range * p.rings).astype(np.int64), p.rings - 1)
    # Sector 0 starts at azimuth 0 (the x axis) and sectors grow counter-clockwise.
    az = np.mod(np.arctan2(y, x), 2 * np.pi)
    sector = np.minimum((az / (2 * np.pi) * p.sectors).astype(np.int64), p.sectors - 1)
    out = np.zeros(p.rings * p.sectors)
    np.maximum.at(out, ring * p.sectors + sector, np.maximum(z + p.lidar_height, 0.0))
    return out.reshape(p.rings, p.sectors).astype(np.float32)


def ring_key(sc: np.ndarray) -> np.ndarray:
    """(…, rings, sectors) → (…, rings): the occupied fraction of each ring (paper eq. 3)."""
    return (np.asarray(sc) > 0).mean(axis=-1).astype(np.float32)


def _unit_columns(sc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Column-normalised copies (zero columns stay zero) and the non-empty column masks."""
    norm = np.linalg.norm(sc, axis=-2, keepdims=True)
    valid = norm > 0
    return np.where(valid, sc / np.where(valid, norm, 1.0), 0.0), valid[..., 0, :]


def shift_distances(query: np.ndarray, cands: np.ndarray) -> np.ndarray:
    """(R, S) query, (K, R, S) candidates → (K, S) distance at every sector shift n, where
    shift n compares query column j with candidate column j + n (mod S). 1 where no column
    is non-empty in both."""
    S = query.shape[-1]
    q, vq = _unit_columns(np.asarray(query, dtype=np.float64))
    c, vc = _unit_columns(np.asarray(cands, dtype=np.float64))
    roll = (np.arange(S)[None, :] + np.arange(S)[:, None]) % S  # [n, j] → j + n
    sim = np.einsum("rj,krnj->kn", q, c[:, :, roll])
    count = np.einsum("j,knj->kn", vq.astype(np.float64), vc[:, roll].astype(np.float64))
    return np.where(count > 0, 1.0 - sim / np.maximum(count, 1.0), 1.0)


def match(query: np.ndarray, cands: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Best shift per candidate → distances (K,) and yaw in degrees (K,).

    The yaw is the turn θ of the query's sensor relative to the candidate's (counter-clockwise,
    about z), to within one sector: a point at azimuth φ in the candidate frame sits at φ − θ
    in the query frame, so query column j matches candidate column j + θ / sector width."""
    d = shift_distances(query, cands)
    n = d.argmin(axis=1)
    S = query.shape[-1]
    yaw = np.where(n > S // 2, n - S, n) * (360.0 / S)
    return d[np.arange(len(d)), n], yaw.astype(np.float64)


def brute_force_shift_distance(query: np.ndarray, cand: np.ndarray) -> float:
    """Slow, obvious twin of :func:`match`'s distance, one shift and one column at a time."""
    S = query.shape[1]
    best = np.inf
    for n in range(S):
        total, count = 0.0, 0
        for j in range(S):
            a, b = query[:, j].astype(np.float64), cand[:, (j + n) % S].astype(np.float64)
            na, nb = float(np.linalg.norm(a)), float(np.linalg.norm(b))
            if na > 0 and nb > 0:
                total += float(a @ b) / (na * nb)
                count += 1
        best = min(best, 1.0 - total / count if count else 1.0)
    return best


def retrieve(
    contexts: np.ndarray,
    queries: np.ndarray,
    db_size: np.ndarray,
    k: int,
    candidates: int = 10,
) -> tuple[np.ndarray, np.ndarray]:
    """Loop-closure retrieval over one sequence's scan contexts (N, R, S).

    Query ``queries[i]`` searches frames 0 … db_size[i] − 1: ring-key nearest neighbours,
    the first ``candidates`` re-ranked by the shift distance, the rest after them in ring-key
    order. → ranked (Q, k) indices padded with −1, distances (Q, k): the shift distance for
    re-ranked candidates, +inf beyond them (only ranks, not distances, exist there).
    """
    keys = ring_key(contexts)
    allowed = np.arange(len(contexts))[None, :] < np.asarray(db_size)[:, None]
    depth = max(k, candidates)
    order, _ = nearest(keys[queries], keys, depth, allowed=allowed)
    ranked = np.full((len(queries), k), -1, dtype=np.int64)
    dist = np.full((len(queries), k), np.inf)
    for row, (qi, cand) in enumerate(zip(queries, order, strict=True)):
        head = cand[:candidates]
        head = head[head >= 0]
        if len(head) == 0:
            continue
        d, _ = match(contexts[qi], contexts[head])
        o = np.argsort(d, kind="stable")
        merged = np.concatenate([head[o], cand[candidates:]])[:k]
        ranked[row, : len(merged)] = merged
        dist[row, : min(len(head), k)] = d[o][:k]
    return ranked, dist
