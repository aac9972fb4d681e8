"""Overlap ground truth (OverlapNet's definition) and loop-closure tables.

Overlap of a reference scan j with a query scan i:

    1. move j's points into i's frame with the relative pose T_i⁻¹ · T_j;
    2. project both with the same sensor profile (nearest point wins each pixel);
    3. overlap = #(pixels valid in both with |r_j − r_i| < τ) / #(valid pixels of i).

τ = 1 m by default. Overlap is asymmetric in general. Relative yaw is the rotation about z
of T_i⁻¹ · T_j, in degrees.

A *loop* for query i is a frame j with i − j > exclude_recent_frames (100), ‖t_i − t_j‖ < radius
(30 m) and overlap > min_overlap (0.3), as in OverlapTransformer's KITTI protocol.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from collections.abc import Sequence as Seq
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from tqdm.auto import tqdm

from overlapmamba.core.cache import cache_root
from overlapmamba.core.datasets.base import Sequence
from overlapmamba.core.errors import DatasetError
from overlapmamba.core.outfiles import replacing
from overlapmamba.core.poses import relative_transform, yaw_deg
from overlapmamba.core.projection import pixel_index
from overlapmamba.core.sensors import SensorProfile

GT_FORMAT_VERSION = 1


def overlap_and_yaw(
    query_xyz: np.ndarray,
    query_pose: np.ndarray,
    ref_xyz: Seq[np.ndarray],
    ref_poses: np.ndarray,
    profile: SensorProfile,
    *,
    threshold: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Overlap and relative yaw of K reference scans against one query, vectorised.

    query_xyz: (N, 3); query_pose: (4, 4); ref_xyz: K arrays (M_k, 3); ref_poses: (K, 4, 4)
    → overlap (K,) float32 in [0, 1], yaw (K,) float32 degrees.
    """
    return _overlap_and_yaw(
        coordinates(query_xyz),
        query_pose,
        [coordinates(x) for x in ref_xyz],
        ref_poses,
        profile,
        threshold,
    )


def coordinates(xyz: np.ndarray) -> np.ndarray:
    """(3, N) float32, C-contiguous: an (N, 3) or (N, 4) scan's x, y and z rows, as
    :func:`moved` takes them."""
    a = np.asarray(xyz)
    if a.ndim != 2 or a.shape[1] < 3:
        raise ValueError(f"points must have shape (N, 3) or (N, 4); got {a.shape}")
    return np.ascontiguousarray(a[:, :3].T, dtype=np.float32)


def moved(xyz: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """(3, N) float32 points after a 4×4 rigid transform, in float32: one (3, 3) @ (3, N)
    product, far cheaper than the float64 (N, 3) @ (3, 3) one that was the overlap tables'
    largest cost (benchmarks/overlap_tables.py), and within micrometres of it over the
    tables' 30 m and 120 m."""
    t = np.asarray(transform, dtype=np.float32)
    return t[:3, :3] @ xyz + t[:3, 3:]


def _overlap_and_yaw(
    query: np.ndarray,
    query_pose: np.ndarray,
    refs: list[np.ndarray],
    ref_poses: np.ndarray,
    profile: SensorProfile,
    threshold: float,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`overlap_and_yaw` of scans given as (3, N) float32 coordinates."""
    ref_poses = np.asarray(ref_poses, dtype=np.float64).reshape(-1, 4, 4)
    K = len(refs)
    if ref_poses.shape[0] != K:
        raise ValueError(f"{K} reference scans but {ref_poses.shape[0]} reference poses")
    rel = relative_transform(np.asarray(query_pose, dtype=np.float64), ref_poses)
    yaws = yaw_deg(rel).astype(np.float32)
    if K == 0:
        return np.zeros(0, np.float32), yaws
    H, W = profile.height, profile.width
    pix, depth = pixel_index(query, profile)
    nearest = np.full(H * W + 1, np.inf, dtype=np.float32)
    np.minimum.at(nearest, pix, depth)
    query_valid = np.isfinite(nearest[: H * W]).reshape(H, W)
    image = np.where(query_valid, nearest[: H * W].reshape(H, W), np.float32(0))
    n_query = int(query_valid.sum())

    # Each reference projected into its own H·W slab, one at a time: its temporaries stay
    # small enough for the cache (0.75× the time of one concatenated projection, same bits).
    # (One more pixel per slab takes the points out of range: pixel_index.)
    flat = np.full((K, H * W + 1), np.inf, dtype=np.float32)
    for slab, xyz, t in zip(flat, refs, rel, strict=True):
        np.minimum.at(slab, *pixel_index(moved(xyz, t), profile))
    moved_refs = flat[:, : H * W].reshape(K, H, W)

    hit = (
        np.isfinite(moved_refs) & query_valid & (np.abs(moved_refs - image) < np.float32(threshold))
    )
    if n_query == 0:
        return np.zeros(K, np.float32), yaws
    return (hit.reshape(K, -1).sum(axis=1) / n_query).astype(np.float32), yaws


def candidate_pairs(
    positions: np.ndarray, *, radius: float, min_gap: int = 0, chunk: int = 2048
) -> np.ndarray:
    """(P, 2) int pairs (i, j) with ‖p_i − p_j‖ < radius and i − j ≥ min_gap (j earlier).

    With min_gap = 0 every ordered pair within the radius is returned, i == j included.
    """
    pos = np.asarray(positions, dtype=np.float64)
    out = []
    for start in range(0, len(pos), chunk):
        q = pos[start : start + chunk]
        d2 = ((q[:, None, :] - pos[None, :, :]) ** 2).sum(-1)
        ok = d2 < radius * radius
        if min_gap > 0:
            i = np.arange(start, start + len(q))[:, None]
            ok &= (i - np.arange(len(pos))[None, :]) >= min_gap
        qi, rj = np.nonzero(ok)
        out.append(np.stack([qi + start, rj], axis=1))
    return np.concatenate(out).astype(np.int64) if out else np.zeros((0, 2), np.int64)


def pair_overlaps(
    seq: Sequence,
    pairs: np.ndarray,
    profile: SensorProfile,
    *,
    threshold: float = 1.0,
    progress: bool = True,
    desc: str = "overlap",
    cache_scans: int = 512,
) -> tuple[np.ndarray, np.ndarray]:
    """Overlap and yaw for arbitrary (query, reference) pairs of one sequence.

    Pairs are grouped by query so each query is projected once; scans are read through a
    small LRU cache because neighbouring queries share most of their references.
    """
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    overlaps = np.zeros(len(pairs), np.float32)
    yaws = np.zeros(len(pairs), np.float32)
    load: Callable[[int], np.ndarray] = lru_cache(maxsize=cache_scans)(
        lambda i: coordinates(seq.points(i).xyz)
    )
    order = np.argsort(pairs[:, 0], kind="stable")
    queries, starts = np.unique(pairs[order, 0], return_index=True)
    bounds = [*starts[1:], len(order)] if len(starts) else []  # no pairs: nothing to do
    for q, s, e in tqdm(
        list(zip(queries, starts, bounds, strict=True)),
        desc=desc,
        unit="query",
        disable=not progress,
    ):
        idx = order[s:e]
        refs = pairs[idx, 1]
        ov, yw = _overlap_and_yaw(
            load(int(q)),
            seq.poses[q],
            [load(int(j)) for j in refs],
            seq.poses[refs],
            profile,
            threshold,
        )
        overlaps[idx], yaws[idx] = ov, yw
    return overlaps, yaws


@dataclass(frozen=True)
class LoopGroundTruth:
    """Every candidate pair within the radius, with its overlap; loops are those above
    ``min_overlap``. Pairs are (query, reference) with reference earlier than query.

    query, reference: (P,) int64; overlap, yaw_deg, distance: (P,) float32
    """

    n_frames: int
    query: np.ndarray
    reference: np.ndarray
    overlap: np.ndarray
    yaw_deg: np.ndarray
    distance: np.ndarray
    params: dict = field(default_factory=dict)
    # the file it was read from or written to (not stored in it); None: computed, not kept
    source: Path | None = field(default=None, compare=False)

    @property
    def min_overlap(self) -> float:
        return float(self.params.get("min_overlap", 0.3))

    @property
    def is_loop(self) -> np.ndarray:
        return self.overlap > self.min_overlap

    def positives(self) -> list[np.ndarray]:
        """For each frame, the sorted earlier frames that are true loops."""
        loop = self.is_loop
        out: list[list[int]] = [[] for _ in range(self.n_frames)]
        for q, r in zip(self.query[loop], self.reference[loop], strict=True):
            out[int(q)].append(int(r))
        return [np.array(sorted(x), dtype=np.int64) for x in out]

    def has_loop(self) -> np.ndarray:
        """(n_frames,) bool: the frame revisits a place seen earlier."""
        mask = np.zeros(self.n_frames, dtype=bool)
        mask[self.query[self.is_loop]] = True
        return mask

    def best_loops(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each revisiting frame (ascending), the reference of its highest-overlap loop, and
        that pair's relative yaw in degrees: (F,) int64, (F,) int64, (F,) float32."""
        loop = self.is_loop
        q, r = self.query[loop], self.reference[loop]
        order = np.lexsort((-self.overlap[loop], q))  # by query, best overlap first (stable)
        q, r, yaw = q[order], r[order], self.yaw_deg[loop][order]
        first = np.r_[True, q[1:] != q[:-1]] if len(q) else np.zeros(0, bool)
        return q[first], r[first], yaw[first]

    def direction_masks(self) -> tuple[np.ndarray, np.ndarray]:
        """(n_frames,) bool masks of same- and reverse-direction revisits: a revisit is
        reverse when its best loop is turned by more than 90°."""
        frames, _, yaw = self.best_loops()
        same = np.zeros(self.n_frames, bool)
        reverse = np.zeros(self.n_frames, bool)
        same[frames[np.abs(yaw) <= 90]] = True
        reverse[frames[np.abs(yaw) > 90]] = True
        return same, reverse

    def save(self, path: str | Path) -> None:
        # a folder at path, a full disk: no half table left beside it (``.npz``: numpy
        # adds it to a name without it)
        with replacing(Path(path), ".npz") as tmp:
            np.savez_compressed(
                tmp,
                n_frames=self.n_frames,
                query=self.query,
                reference=self.reference,
                overlap=self.overlap,
                yaw_deg=self.yaw_deg,
                distance=self.distance,
                params=json.dumps(self.params, sort_keys=True),
            )

    @classmethod
    def load(cls, path: str | Path) -> LoopGroundTruth:
        with np.load(path, allow_pickle=False) as z:
            return cls(
                n_frames=int(z["n_frames"]),
                query=z["query"],
                reference=z["reference"],
                overlap=z["overlap"],
                yaw_deg=z["yaw_deg"],
                distance=z["distance"],
                params=json.loads(str(z["params"])),
                source=Path(path),
            )


def _fingerprint(seq: Sequence, params: dict) -> str:
    h = hashlib.sha256()
    h.update(json.dumps(params, sort_keys=True).encode())
    seq.update_digest(h)
    return h.hexdigest()[:16]


def default_cache_path(seq: Sequence, fingerprint: str) -> Path:
    """``$OVERLAPMAMBA_CACHE`` (default ``~/.cache/overlapmamba``)``/ground_truth/…``.

    Never the sequence folder itself: real data is shared and must stay untouched. Writers
    that own their folder (the synthetic generator) pass an explicit path instead.
    """
    return cache_root() / "ground_truth" / f"{seq.name}_loops_{fingerprint}.npz"


FILE_KEYS = {"exclude_recent": "exclude_recent_frames"}  # a loop table's params → LoopParams


class LoopParams(BaseModel):
    """What makes a pair of scans a loop, everywhere loops are counted (ground truth, the
    generator's tables, evaluation, training's validation, the CLI): the query is more than
    ``exclude_recent_frames`` after the reference, closer than ``radius`` metres, and they
    overlap by at least ``min_overlap`` (overlap of points within ``threshold`` metres of
    range). A table's saved ``params`` keep the file key ``exclude_recent`` (frames)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    exclude_recent_frames: int = Field(default=100, ge=0)
    radius: float = Field(default=30.0, gt=0)
    min_overlap: float = Field(default=0.3, ge=0, le=1)
    threshold: float = Field(default=1.0, gt=0)

    @classmethod
    def of(cls, table_params: dict) -> LoopParams:
        """The parameters a saved loop table (``LoopGroundTruth.params``) was made with."""
        saved = {FILE_KEYS.get(k, k): v for k, v in table_params.items()}
        return cls(**{k: saved[k] for k in cls.model_fields if k in saved})


def loop_params(seq: Sequence, profile: SensorProfile, loops: LoopParams | None = None) -> dict:
    """The parameters that identify a loop table, with their fingerprint over the sequence."""
    loops = loops or LoopParams()
    params = {
        "format": GT_FORMAT_VERSION,
        "exclude_recent": loops.exclude_recent_frames,  # the file's key
        "radius": loops.radius,
        "min_overlap": loops.min_overlap,
        "threshold": loops.threshold,
        "profile": profile.model_dump(),
    }
    params["fingerprint"] = _fingerprint(seq, params)
    return params


def loop_table_from_pairs(
    seq: Sequence,
    params: dict,
    query: np.ndarray,
    reference: np.ndarray,
    overlap: np.ndarray,
    yaw: np.ndarray,
) -> LoopGroundTruth:
    """A loop table from overlaps already computed for a superset of its candidate pairs
    (the same pairs :func:`loop_ground_truth` would compute, with the same overlap code)."""
    pos = seq.positions()
    query, reference = np.asarray(query, np.int64), np.asarray(reference, np.int64)
    dist = np.linalg.norm(pos[query] - pos[reference], axis=1)
    keep = (query - reference > params["exclude_recent"]) & (dist < params["radius"])
    content = _content(seq)  # beside the fingerprint, not in it: tables made before still match
    return LoopGroundTruth(
        n_frames=len(seq),
        query=query[keep],
        reference=reference[keep],
        overlap=np.asarray(overlap, np.float32)[keep],
        yaw_deg=np.asarray(yaw, np.float32)[keep],
        distance=dist[keep].astype(np.float32),
        params={**params, "content": content} if content else params,
    )


def _content(seq: Sequence) -> str:
    """The scans' sampled content digest (``Sequence.content_digest``; '' for a recording
    that has none, a bag, whose digest holds its message times)."""
    digest = getattr(seq, "content_digest", None)
    return digest() if digest is not None else ""


def _read_table(path: Path) -> LoopGroundTruth | None:
    """The loop table at ``path``; None where there is none or it cannot be read (empty, cut
    short, not a zip: numpy and zipfile refuse such files in many ways)."""
    if not path.is_file():
        return None
    try:
        return LoopGroundTruth.load(path)
    except Exception:
        return None


def _load_matching(path: Path, fingerprint: str, seq: Sequence) -> LoopGroundTruth | None:
    """The table at ``path`` if it was made from this sequence with these parameters, and
    (where it records one: tables since 2026-12-04) from these scans' content."""
    gt = _read_table(path)
    return gt if gt is not None and table_matches(gt, fingerprint, seq) else None


def _named_table(path: Path) -> LoopGroundTruth | None:
    """:func:`_read_table` of a table path the caller named, which may hold a loop table (of
    other parameters: written again) or a damaged ``.npz`` (a table is written as one), never
    another file: a file of another name that is not a loop table is refused, not
    overwritten."""
    if path.is_dir():
        raise DatasetError(f"{path} is a folder; give the .npz file the table is written to")
    gt = _read_table(path)
    if gt is None and path.exists() and path.suffix != ".npz":
        raise DatasetError(
            f"{path} exists and is not a loop table, which a table would overwrite; give "
            "another file, or delete it"
        )
    return gt


def table_matches(gt: LoopGroundTruth, fingerprint: str, seq: Sequence) -> bool:
    """Whether a loop table stands for ``seq``: its parameters' fingerprint is the one given,
    and the scans' content is the one it was made from (where it records it: tables made
    since 2026-12-04; the fingerprint reads no scan)."""
    if gt.params.get("fingerprint") != fingerprint:
        return False
    recorded = gt.params.get("content")
    return not recorded or recorded == _content(seq)


def loop_ground_truth(
    seq: Sequence,
    profile: SensorProfile,
    loops: LoopParams | None = None,
    *,
    cache: str | Path | bool = True,
    progress: bool = True,
) -> LoopGroundTruth:
    """Loop table of a sequence (OverlapTransformer protocol), cached to ``.npz``.

    ``cache=True`` uses :func:`default_cache_path`, after looking for a table the data's
    writer shipped in ``<sequence>/ground_truth/loops.npz`` (the synthetic generator does);
    a path uses that file; False disables. A table is reused only if sequence, profile and
    parameters are unchanged.
    """
    loops = loops or LoopParams()
    params = loop_params(seq, profile, loops)
    fp = params["fingerprint"]
    path = None
    if cache is not False:
        if cache is True:
            shipped = _load_matching(seq.root / "ground_truth" / "loops.npz", fp, seq)
            if shipped is not None:
                return shipped
        path = default_cache_path(seq, fp) if cache is True else Path(cache)
        cached = _read_table(path) if cache is True else _named_table(path)  # read once
        if cached is not None and table_matches(cached, fp, seq):
            return cached
    pos = seq.positions()
    pairs = candidate_pairs(pos, radius=loops.radius, min_gap=loops.exclude_recent_frames + 1)
    overlaps, yaws = pair_overlaps(
        seq, pairs, profile, threshold=loops.threshold, progress=progress, desc="loop ground truth"
    )
    gt = loop_table_from_pairs(seq, params, pairs[:, 0], pairs[:, 1], overlaps, yaws)
    if path is not None:
        gt.save(path)
        gt = replace(gt, source=path)
    return gt
