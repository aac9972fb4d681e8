"""Training batches from the overlap ground truth: groups of related scans, batch-hard mining.

The pair table (``<sequence>/ground_truth/overlaps.npz``, written by ``gen-data``) holds the
overlap of every pair of scans closer than its radius. A batch is made of groups of
1 + ``positives`` + ``negatives`` scans (by default 1 + 2 + 1 = ``GROUP`` = 4):

    anchor, positive, positive, near miss

(OverlapTransformer's tuples are 1 + 6 + 6: ``BatchPlan(positives=6, negatives=6)``.)

- positives have overlap > ``positive_threshold`` (0.3) with the anchor;
- the near miss lies within the table's radius but overlaps at most
  ``negative_threshold``: the hardest kind of negative, a place close by that looks
  different (when the anchor has none, any scan that does not overlap it);
- for half of the anchors (``revisit_fraction``), the first positive is an *old* pass of
  the same place (more than ``min_revisit_gap`` scans earlier or later) when the anchor has
  one, so loop closures, not only neighbouring frames, drive the loss;
- with mined hard negatives (:mod:`overlapmamba.train.mining`), a share of the groups take their
  anchor from the mined pool and, instead of the near miss, a distant scan that the current
  model finds alike;
- with a band share (``band``, for :class:`~overlapmamba.train.losses.BandRanking`), that share of
  the other groups take, instead of the near miss, a scan of the anchor's ambiguous band
  (overlap above ``negative_threshold`` but not above ``positive_threshold``).

Every other scan of the batch is a negative of the anchor unless the table says they
overlap more than ``negative_threshold``: the loss reads the batch's full (B, B) overlap
matrix (batch-hard mining), so positives and negatives across groups count too. Pairs between
the two thresholds (neighbouring places that share a little) are neither.

The table stores overlap(query, reference) for query > reference only; it is used for both
orders (overlap is nearly symmetric between scans of similar density).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import sparse

from overlapmamba.core.datasets.base import Sequence
from overlapmamba.core.errors import DatasetError
from overlapmamba.train.drives import drive_pairs, group_drives
from overlapmamba.train.mining import HardNegatives

GROUP = 4


def read_pair_table(root: Path) -> dict[str, np.ndarray]:
    path = root / "ground_truth" / "overlaps.npz"
    if not path.is_file():
        raise DatasetError(
            f"{root}: no ground_truth/overlaps.npz; training needs the pairwise overlap table "
            "that `overlapmamba gen-data` writes beside every synthetic sequence",
            missing=str(path),
        )
    with np.load(path, allow_pickle=False) as z:
        kind = str(z["pair_table"]) if "pair_table" in z.files else "all"
        if kind != "all":
            raise DatasetError(
                f"{root}: its pair table holds only loop candidates (pair_table={kind!r}, as "
                "validation and test towns are generated); training samples positives and near "
                "misses from neighbouring frames and needs pair_table='all' (gen-data for a "
                "training split)",
                pair_table=kind,
            )
        return {k: z[k] for k in ("query", "reference", "overlap")}


@dataclass
class PairIndex:
    """Overlap between scans of several sequences, as one symmetric sparse matrix over
    global scan indices (sequence k's scans follow sequence k−1's). Renderings of one drive
    by other sensors or mountings share its pair table (:mod:`overlapmamba.train.drives`)."""

    overlap: sparse.csr_matrix  # (N, N) float32; absent pairs: 0 (farther than the radius)
    near: sparse.csr_matrix  # (N, N) bool: within the table's radius (any overlap)
    offsets: np.ndarray  # (S + 1,) first global index of each sequence, then N
    frame: np.ndarray | None = None  # (N,) each scan's frame in its drive (None: global order)

    @classmethod
    def from_sequences(cls, seqs: list[Sequence]) -> PairIndex:
        rows, cols, vals = [], [], []
        offsets = np.cumsum([0, *[len(s) for s in seqs]])
        has_table = lambda s: (s.root / "ground_truth" / "overlaps.npz").is_file()  # noqa: E731
        for drive in group_drives(seqs, has_table):
            ref = seqs[drive.reference]
            t = read_pair_table(ref.root)
            if len(t["query"]) and int(max(t["query"].max(), t["reference"].max())) >= len(ref):
                raise DatasetError(f"{ref.root}: overlaps.npz names scans the sequence lacks")
            r_, c_, v_ = drive_pairs(drive, t, offsets, len(ref))
            rows += r_
            cols += c_
            vals += v_
        n = int(offsets[-1])
        r, c = np.concatenate(rows), np.concatenate(cols)
        v = np.concatenate(vals).astype(np.float32)
        overlap = sparse.csr_matrix((v, (r, c)), shape=(n, n))
        near = sparse.csr_matrix((np.ones(len(r), bool), (r, c)), shape=(n, n))
        frame = np.concatenate([np.arange(len(s)) for s in seqs]) if seqs else np.zeros(0, int)
        return cls(overlap=overlap, near=near, offsets=offsets, frame=frame)

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def submatrix(self, idx: np.ndarray) -> np.ndarray:
        """(B, B) float32 overlap among the given scans; 1 on the diagonal."""
        m = self.overlap[idx][:, idx].toarray()
        np.fill_diagonal(m, 1.0)
        return m


@dataclass(frozen=True)
class BatchPlan:
    batch_size: int = 16  # a multiple of the group size 1 + positives + negatives
    positive_threshold: float = 0.3
    revisit_fraction: float = 0.5
    min_revisit_gap: int = 100
    negative_threshold: float = 0.3  # near misses overlap at most this
    positives: int = 2  # per anchor
    negatives: int = 1  # near misses per anchor

    @property
    def group(self) -> int:
        return 1 + self.positives + self.negatives


class BatchSampler:
    """Draws an epoch of batches (global scan indices) from a :class:`PairIndex`."""

    def __init__(self, pairs: PairIndex, plan: BatchPlan) -> None:
        if plan.positives < 1 or plan.negatives < 0:
            raise ValueError(
                f"groups need at least one positive and no negative count below 0; got "
                f"positives={plan.positives}, negatives={plan.negatives}"
            )
        g = plan.group
        if plan.batch_size < g or plan.batch_size % g:
            raise ValueError(
                f"batch size {plan.batch_size} is not allowed: use a multiple of {g} (anchor, "
                f"{plan.positives} positives, {plan.negatives} near misses)"
            )
        self.plan = plan
        self.pairs = pairs
        ov = pairs.overlap
        pos = ov.copy()
        pos.data = (pos.data > plan.positive_threshold).astype(np.float32)
        pos.eliminate_zeros()
        self.positives = [pos.indices[pos.indptr[i] : pos.indptr[i + 1]] for i in range(len(pairs))]
        above = ov > plan.negative_threshold  # within the radius and not clearly different
        self.related = [
            above.indices[above.indptr[i] : above.indptr[i + 1]] for i in range(len(pairs))
        ]
        near = pairs.near.astype(np.float32) - above.astype(np.float32)
        near.eliminate_zeros()
        self.near_misses = [
            near.indices[near.indptr[i] : near.indptr[i + 1]] for i in range(len(pairs))
        ]
        band = ov.multiply(above)
        band.data = (band.data <= plan.positive_threshold).astype(np.float32)
        band.eliminate_zeros()
        self.band = [band.indices[band.indptr[i] : band.indptr[i + 1]] for i in range(len(pairs))]
        # a revisit is far from the anchor in its drive's time: another rendering's copy of
        # the anchor's own frame is a positive, never a revisit
        frame = pairs.frame if pairs.frame is not None else np.arange(len(pairs))
        self.revisits = [
            p[np.abs(frame[p] - frame[i]) > plan.min_revisit_gap]
            for i, p in enumerate(self.positives)
        ]
        self.anchors = np.array(
            [i for i, p in enumerate(self.positives) if len(p) >= plan.positives], np.int64
        )
        self.revisit_anchors = np.array(
            [i for i in self.anchors if len(self.revisits[i])], np.int64
        )
        if len(self.anchors) == 0:
            raise DatasetError(
                f"no scan has {plan.positives} positives (overlap > "
                f"{plan.positive_threshold}) in the training data: nothing to learn from"
            )

    def batch(
        self,
        rng: np.random.Generator,
        hard: HardNegatives | None = None,
        share: float = 0.0,
        band: float = 0.0,
    ) -> np.ndarray:
        """One batch: (batch_size,) global scan indices in groups, no repeats. With ``hard``,
        each group is a mined one with probability ``share``: its anchor comes from the
        mined pool and its negatives from the anchor's mined candidates. Each negative of
        the other groups is, with probability ``band``, a scan of the anchor's ambiguous
        band (when it has one free). With ``band`` = 0 no random number is drawn for it, so
        the batches are those drawn before the option existed."""
        p = self.plan
        hard_revisit = (
            np.intersect1d(hard.anchors, self.revisit_anchors)
            if hard is not None
            else np.zeros(0, np.int64)
        )
        chosen: list[int] = []
        taken: set[int] = set()

        def free(cands: np.ndarray) -> list[int]:
            return [int(c) for c in cands if int(c) not in taken]

        def pick(cands: list[int]) -> int:
            return cands[int(rng.integers(len(cands)))]

        for _ in range(50 * p.batch_size):  # bounded: a tiny data set may run out of anchors
            if len(chosen) == p.batch_size:
                break
            mined = hard is not None and share > 0 and rng.random() < share
            revisit = len(self.revisit_anchors) > 0 and rng.random() < p.revisit_fraction
            if mined:
                assert hard is not None
                revisit = revisit and len(hard_revisit) > 0
                anchors = free(hard_revisit if revisit else hard.anchors)
            else:
                anchors = free(self.revisit_anchors if revisit else self.anchors)
            if not anchors:
                continue
            anchor = pick(anchors)
            positives = free(self.positives[anchor])
            firsts = free(self.revisits[anchor]) if revisit else positives
            if len(positives) < p.positives or not firsts:
                continue  # its partners are in the batch already: draw another anchor
            first = pick(firsts)
            rest = [c for c in positives if c != first]
            group = [anchor, first]
            for _ in range(p.positives - 1):
                group.append(rest.pop(int(rng.integers(len(rest)))))
            taken.update(group)
            for _ in range(p.negatives):
                if mined:
                    assert hard is not None
                    alike = free(hard.candidates[anchor])
                    if alike:
                        group.append(pick(alike))
                        taken.add(group[-1])
                        continue
                elif band > 0 and rng.random() < band:
                    between = free(self.band[anchor])
                    if between:
                        group.append(pick(between))
                        taken.add(group[-1])
                        continue
                misses = free(self.near_misses[anchor])
                if not misses:  # none close by: any scan that does not overlap the anchor
                    misses = free(
                        np.setdiff1d(
                            rng.integers(len(self.pairs), size=8 * GROUP), self.related[anchor]
                        )
                    )
                if misses:
                    group.append(pick(misses))
                    taken.add(group[-1])
            chosen += group
        if len(chosen) < p.batch_size:
            raise DatasetError(
                f"cannot fill a batch of {p.batch_size} scans from {len(self.pairs)} scans with "
                "this overlap table; use a smaller batch size or more data"
            )
        return np.array(chosen[: p.batch_size], np.int64)

    def steps(self, scans: int) -> int:
        """Batches in an epoch of ``scans`` scans."""
        return max(1, scans // self.plan.batch_size)

    def epoch(
        self,
        rng: np.random.Generator,
        scans: int,
        hard: HardNegatives | None = None,
        share: float = 0.0,
        band: float = 0.0,
    ) -> list[np.ndarray]:
        return [self.batch(rng, hard, share, band) for _ in range(self.steps(scans))]
