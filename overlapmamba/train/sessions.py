"""Place recognition across sessions: the paper's NCLT protocol (its Fig. 5) on our towns.

One drive through a town is the database; a second drive through the same static town
(along the first drive's streets in its own order and directions, with different parked
cars, traffic, pedestrians and scan noise: ``gen-data --session 1``) gives the queries.
Each query retrieves its top N database scans by descriptor distance; it is a hit at N
when one of them lies within ``radius`` metres
(5 m, as OverlapTransformer-style NCLT evaluations count a hit). Queries with no database
scan within the radius are left out. AR@N is the share of hits over the evaluated queries.
Each result also says how far the wrong first answers lie from their query
(``wrong_top1``, in the bands of :data:`MISS_BANDS_M`): a top-1 a few metres beyond the
radius is the right stretch of street found too coarsely, one beyond 50 m another place.

Positions are compared in the town's frame: each synthetic sequence's manifest records
``world_from_sequence`` (its poses are relative to its first scan, as KITTI's are). For
other data the two sequences' poses must already share a frame.
"""

from __future__ import annotations

import itertools
import json
from dataclasses import asdict
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from overlapmamba.core.datasets.base import Sequence
from overlapmamba.core.errors import DatasetError
from overlapmamba.core.metrics import nearest
from overlapmamba.core.rerank import OFF, Rerank, rerank_ranked
from overlapmamba.core.scancontext import ScanContextParams
from overlapmamba.core.scancontext import retrieve as sc_retrieve

HIT_RADIUS = 5.0
RECALL_AT = (1, 5, 20)
MISS_BANDS_M = (10.0, 20.0, 50.0)  # upper bounds of the wrong top-1's distance bands


def _manifest(seq: Sequence) -> dict[str, Any] | None:
    path = seq.root / "manifest.json"
    return json.loads(path.read_text()) if path.is_file() else None


def town_positions(seq: Sequence) -> np.ndarray:
    """(N, 3) scan positions in the town's frame (the manifest's ``world_from_sequence``
    applied to the poses; the poses themselves when there is no manifest)."""
    poses = seq.poses
    m = _manifest(seq)
    if m is not None and "world_from_sequence" in m:
        poses = np.asarray(m["world_from_sequence"], dtype=np.float64) @ poses
    return poses[:, :3, 3]


def check_sessions(database: Sequence, queries: Sequence, radius: float = HIT_RADIUS) -> None:
    """Refuse two sequences that are not two sessions of one town (when manifests say), or
    whose drives never come within ``radius`` of each other (nothing to recall)."""
    _check_town(database, queries)
    near, _ = cKDTree(town_positions(database)[:, :2]).query(town_positions(queries)[:, :2])
    if not (near <= radius).any():
        raise DatasetError(
            f"no scan of {queries.root} passes within {radius:g} m of a scan of "
            f"{database.root} (closest {near.min():.0f} m): the drives share no place to "
            "recall; generate the second session with generator 1.5.0 or later, which keeps "
            "to the first session's streets"
        )


def _check_town(database: Sequence, queries: Sequence) -> None:
    a, b = _manifest(database), _manifest(queries)
    if (
        a is None
        or b is None
        or "seed" not in a.get("config", {})
        or "seed" not in b.get("config", {})
    ):
        return  # foreign data: the caller vouches for a shared frame
    ca, cb = a["config"], b["config"]
    if ca["seed"] != cb["seed"]:
        raise DatasetError(
            f"{queries.root} and {database.root} are different towns (seed {cb['seed']} vs "
            f"{ca['seed']}); cross-session queries need another session of the database's "
            "town: gen-data --preset NAME --session 1 (or the same --seed with --session)"
        )
    world_a = a.get("resolved", {}).get("world", ca.get("world", {}))
    world_b = b.get("resolved", {}).get("world", cb.get("world", {}))
    if world_a != world_b:
        raise DatasetError(
            f"{queries.root} and {database.root} share seed {ca['seed']} but not the town's "
            "parameters (street grid, block sizes, terrain): they are different towns"
        )
    if ca.get("session", 0) == cb.get("session", 0):
        raise DatasetError(
            f"{queries.root} and {database.root} are the same session "
            f"({ca.get('session', 0)}); give a second drive (gen-data --session k)"
        )


def ground_truth(pos_db: np.ndarray, pos_q: np.ndarray, radius: float = HIT_RADIUS) -> np.ndarray:
    """(Q, M) bool: database scan within ``radius`` of the query."""
    d2 = ((pos_q[:, None, :2] - pos_db[None, :, :2]) ** 2).sum(-1)
    return d2 <= radius * radius


def _wrong_top1(top1_m: np.ndarray, radius: float) -> dict[str, int]:
    """How many wrong first answers lie within each band of :data:`MISS_BANDS_M` of their
    query (horizontal distance in metres), and how many farther."""
    edges = [radius, *(b for b in MISS_BANDS_M if b > radius)]
    out = {
        f"{lo:g}-{hi:g} m": int(((top1_m > lo) & (top1_m <= hi)).sum())
        for lo, hi in itertools.pairwise(edges)
    }
    out[f"> {edges[-1]:g} m"] = int((top1_m > edges[-1]).sum())
    return out


def recall_at(
    ranked: np.ndarray, near: np.ndarray, ks: tuple[int, ...], prefix: str = "ar@"
) -> dict[str, float]:
    """The share of queries with any database scan within reach (``near``, (Q, M) bool) that
    have one among their first K answers (``ranked``, (Q, ≥ max K) indices, −1 for none),
    for each K in ``ks``: ``{prefix}K`` (NaN when no query has any)."""
    evaluated = np.asarray(near.any(1))
    hits = np.take_along_axis(near, np.clip(ranked, 0, None), 1) & (ranked >= 0)
    out = {}
    for n in ks:
        ok = np.asarray(hits[:, :n].any(1))[evaluated]
        out[f"{prefix}{n}"] = float(ok.mean()) if len(ok) else float("nan")
    return out


def _recalls(
    ranked: np.ndarray, near: np.ndarray, pos_db: np.ndarray, pos_q: np.ndarray, radius: float
) -> dict[str, Any]:
    evaluated = np.asarray(near.any(1))
    hits = np.take_along_axis(near, np.clip(ranked, 0, None), 1) & (ranked >= 0)
    out: dict[str, Any] = {"queries": int(evaluated.sum()), "queries_total": len(near)}
    out.update(recall_at(ranked, near, RECALL_AT))
    wrong = evaluated & ~np.asarray(hits[:, 0]) & (ranked[:, 0] >= 0)
    top1 = pos_db[ranked[wrong, 0], :2]
    out["wrong_top1"] = _wrong_top1(np.linalg.norm(top1 - pos_q[wrong, :2], axis=1), radius)
    return out


def descriptor_recall(
    desc_db: np.ndarray,
    pos_db: np.ndarray,
    desc_q: np.ndarray,
    pos_q: np.ndarray,
    radius: float = HIT_RADIUS,
    *,
    yaw: tuple[np.ndarray, np.ndarray] | None = None,
    rerank: Rerank = OFF,
) -> dict[str, Any]:
    """AR@1/5/20 of queries (descriptors, positions) against a database, by squared L2; with
    ``rerank`` on, each query's ``rerank.shortlist`` nearest re-ranked by the yaw features ``yaw``
    = (database's (M, C, W), queries' (Q, C, W)): :mod:`overlapmamba.core.rerank` (the score's
    d² between ``rerank.rows`` of the descriptors)."""
    k = min(max(max(RECALL_AT), rerank.shortlist), len(desc_db))
    ranked, dist = nearest(desc_q, desc_db, k)
    if rerank.on:
        if yaw is None:
            raise ValueError("re-ranking needs the yaw features of both sessions")
        ranked, _ = rerank_ranked(yaw[1], yaw[0], ranked, dist, rerank, (desc_q, desc_db))
    near = ground_truth(pos_db, pos_q, radius)
    out = _recalls(ranked[:, : max(RECALL_AT)], near, pos_db, pos_q, radius)
    return {"radius_m": radius, **out, **({"rerank": asdict(rerank)} if rerank.on else {})}


def scan_context_recall(
    sc_db: np.ndarray,
    pos_db: np.ndarray,
    sc_q: np.ndarray,
    pos_q: np.ndarray,
    radius: float = HIT_RADIUS,
    params: ScanContextParams | None = None,
) -> dict[str, Any]:
    """The same protocol for Scan Context (ring-key pre-selection, then shift distance)."""
    p = params or ScanContextParams()
    k = min(max(RECALL_AT), len(sc_db))
    contexts = np.concatenate([sc_db, sc_q])
    queries = len(sc_db) + np.arange(len(sc_q))
    ranked, _ = sc_retrieve(contexts, queries, np.full(len(sc_q), len(sc_db)), k, p.candidates)
    near = ground_truth(pos_db, pos_q, radius)
    return {"radius_m": radius, **_recalls(ranked, near, pos_db, pos_q, radius)}
