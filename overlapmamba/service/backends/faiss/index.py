"""The FAISS index of one map — derived from the store, never the source of truth.

Vectors are unit descriptors and the metric is the L2 distance between them (the metric the
model is evaluated with; cosine = 1 − d²/2). The index is an L2 index rather than an
inner-product one: FAISS computes a single query's L2 distances as sums of squared
differences, which stay accurate for near-identical vectors, while √(2 − 2·x·y) loses up to
≈3e-4 to float32 cancellation. Against the shipped model's loop threshold (0.1794) that is
small, but it costs nothing to avoid, and a re-visit of the very same place lies far closer.

    flat   IndexIDMap2(IndexFlatL2)       exact; the default
    ivf    IndexIVFFlat (L2)              approximate, for large maps: nlist ≈ √N lists,
                                          ``nprobe`` of them searched per query

Both take our row ids as FAISS ids and support ``remove_ids``. Filters become an
``IDSelectorBitmap`` over row ids. IVF can come back short when the eligible rows sit in
unprobed lists (a filter's, or a map shrunk by deletes below what its lists were sized for);
then the search is repeated over every list (exact), so a query returns k results whenever
k eligible keyframes exist.

:func:`search_reference` is the slow, obvious numpy twin for tests.

Thread safety (FAISS's rules): concurrent searches are fine, writes need exclusivity —
:class:`overlapmamba.service.backends.faiss.map.FaissMap` holds a readers–writer lock around these
calls.
"""

from __future__ import annotations

import math
from typing import Any

import faiss
import numpy as np

KINDS = ("flat", "ivf")


def set_threads(n: int) -> None:
    """FAISS's OpenMP threads, for the whole process. The service asks for 1 by default
    (``index.threads``): a query is one vector, and OpenMP workers that spin after each
    search take the cores the encoder and the event loop need: with the encoder busy on a
    2-core machine, the search stage over 10k keyframes had a p90 of 19.9 ms on 2 threads
    against 2.8 ms on 1 (benchmarks/sizing.py)."""
    if n < 1:
        raise ValueError(f"FAISS threads must be ≥ 1, got {n}")
    faiss.omp_set_num_threads(n)


def ivf_lists(n: int) -> int:
    """4·√N lists (≈250 vectors each at 1M): short lists keep a probe cheap
    (benchmarks/serving.py measures recall and latency against nprobe). At most N/39, the
    fewest training points per centroid FAISS's k-means accepts."""
    return int(max(1, min(16384, round(4 * math.sqrt(max(n, 1))), n // 39)))


def wants_ivf(kind: str, n: int, approximate_above: int) -> bool:
    """Whether a map of index ``kind`` (flat, ivf or auto) and ``n`` vectors calls for IVF:
    auto above ``approximate_above``; never below 64 vectors (IVF needs some to train on)."""
    auto = kind == "auto" and n > approximate_above
    return (kind == "ivf" or auto) and n >= 64


def needs_rebuild(index: VectorIndex, ivf: bool) -> bool:
    """Whether ``index`` is not what its map calls for: the other kind (e.g. an IVF snapshot
    of a map now flat), or IVF grown well past the lists it was sized for."""
    if not ivf:
        return index.kind != "flat"
    if index.kind != "ivf":
        return True
    return ivf_lists(index.ntotal) >= 2 * index.nlist


class VectorIndex:
    def __init__(self, index: faiss.Index, kind: str, *, nprobe: int = 24) -> None:
        self.index: Any = index  # FAISS's SWIG stubs do not match its Python API
        self.kind = kind
        self.nprobe = nprobe

    @classmethod
    def flat(cls, dim: int) -> VectorIndex:
        return cls(faiss.IndexIDMap2(faiss.IndexFlatL2(dim)), "flat")

    @classmethod
    def ivf(cls, train: np.ndarray, *, nprobe: int = 24, seed: int = 0) -> VectorIndex:
        """An empty IVF index whose coarse quantiser is trained on ``train`` (n, D)."""
        n, dim = train.shape
        nlist = ivf_lists(n)
        index = faiss.IndexIVFFlat(faiss.IndexFlatL2(dim), dim, nlist, faiss.METRIC_L2)
        index.cp.seed = seed
        index.cp.max_points_per_centroid = 64  # 64·nlist samples train as well, much faster
        index.train(np.ascontiguousarray(train, dtype=np.float32))
        return cls(index, "ivf", nprobe=nprobe)

    @property
    def dim(self) -> int:
        return int(self.index.d)

    @property
    def ntotal(self) -> int:
        return int(self.index.ntotal)

    @property
    def nlist(self) -> int:
        return int(self.index.nlist) if self.kind == "ivf" else 0

    def add(self, ids: np.ndarray, vectors: np.ndarray) -> None:
        if len(ids):
            self.index.add_with_ids(
                np.ascontiguousarray(vectors, dtype=np.float32), np.asarray(ids, dtype=np.int64)
            )

    def remove(self, ids: np.ndarray) -> int:
        if not len(ids):
            return 0
        return int(self.index.remove_ids(np.asarray(ids, dtype=np.int64)))

    def search(
        self, query: np.ndarray, k: int, allowed: np.ndarray | None = None, base: int = 0
    ) -> tuple[np.ndarray, np.ndarray]:
        """query (D,) → L2 distances (≤k,), ids (≤k,), nearest first. ``allowed`` is a bool
        mask over the row ids from ``base`` (a multiple of 8: ``allowed[i]`` is row
        ``base + i``); ids outside it are not allowed."""
        q = np.ascontiguousarray(query, dtype=np.float32).reshape(1, -1)
        k = min(k, self.ntotal)
        if k <= 0:
            return np.zeros(0, np.float32), np.zeros(0, np.int64)
        if allowed is None:
            return self._search(q, k, None)
        eligible = int(allowed.sum())
        k = min(k, eligible)
        if k <= 0:
            return np.zeros(0, np.float32), np.zeros(0, np.int64)
        assert base % 8 == 0, base
        bitmap = np.zeros(base // 8 + (len(allowed) + 7) // 8, np.uint8)  # the ids below: 0
        bitmap[base // 8 :] = np.packbits(allowed, bitorder="little")
        selector = faiss.IDSelectorBitmap(len(bitmap), faiss.swig_ptr(bitmap))  # n: bytes
        out = self._search(q, k, selector)
        del bitmap  # the selector points into it until here
        return out

    def _search(
        self, q: np.ndarray, k: int, selector: faiss.IDSelector | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The k nearest of ``q`` (1, D) among ``selector``'s ids (None: all); an IVF search
        that comes back short (the eligible rows in unprobed lists: a filter's, or a map
        shrunk by deletes) is repeated over every list."""
        d2, ids = self.index.search(q, k, params=self._params(selector, self.nprobe))
        dist, ids = _trim(d2[0], ids[0])
        if len(ids) < k and self.kind == "ivf":
            d2, ids = self.index.search(q, k, params=self._params(selector, self.nlist))
            dist, ids = _trim(d2[0], ids[0])
        return dist, ids

    def _params(self, selector: faiss.IDSelector | None, nprobe: int) -> Any:
        p: Any
        if self.kind == "ivf":
            p = faiss.SearchParametersIVF()
            p.nprobe = nprobe
        else:
            p = faiss.SearchParameters()
        if selector is not None:
            p.sel = selector
        return p

    def serialize(self) -> bytes:
        return faiss.serialize_index(self.index).tobytes()

    @classmethod
    def deserialize(cls, data: bytes, kind: str, *, nprobe: int = 24) -> VectorIndex:
        index = faiss.deserialize_index(np.frombuffer(data, dtype=np.uint8))
        return cls(index, kind, nprobe=nprobe)


def _trim(d2: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """FAISS's padded squared distances → distances of the real hits."""
    keep = ids >= 0
    return np.sqrt(np.maximum(d2[keep], 0.0)), ids[keep]


def search_reference(
    vectors: np.ndarray, ids: np.ndarray, query: np.ndarray, k: int
) -> tuple[np.ndarray, np.ndarray]:
    """Exact top-k by L2 distance, in float64: the ground truth for tests and recall."""
    diff = np.asarray(vectors, dtype=np.float64) - np.asarray(query, dtype=np.float64)
    dist = np.sqrt((diff * diff).sum(axis=1))
    order = np.argsort(dist, kind="stable")[:k]
    return dist[order], ids[order]
