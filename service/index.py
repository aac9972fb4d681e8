"""The FAISS index of one map — derived from the store, never the source of truth.

Vectors are unit descriptors; similarity is the inner product (= cosine) and the reported
distance is the L2 distance between unit vectors, √(2 − 2·cos), the metric the model is
evaluated with.

    flat   IndexIDMap2(IndexFlatIP)       exact; the default
    ivf    IndexIVFFlat (inner product)   approximate, for large maps: nlist ≈ √N lists,
                                          ``nprobe`` of them searched per query

Both take our row ids as FAISS ids and support ``remove_ids``. Filters become an
``IDSelectorBitmap`` over row ids. IVF with a selector can come back short when the eligible
rows sit in unprobed lists; then the search is repeated over every list (exact), so a
query returns k results whenever k eligible keyframes exist.

:func:`search_reference` is the slow, obvious numpy twin for tests.

Thread safety (FAISS's rules): concurrent searches are fine, writes need exclusivity —
:class:`service.maps.Map` holds a readers–writer lock around these calls.
"""

from __future__ import annotations

import math
from typing import Any

import faiss
import numpy as np

KINDS = ("flat", "ivf")


def ivf_lists(n: int) -> int:
    return int(min(4096, max(16, round(math.sqrt(max(n, 1))))))


class VectorIndex:
    def __init__(self, index: faiss.Index, kind: str, *, nprobe: int = 32) -> None:
        self.index: Any = index  # FAISS's SWIG stubs do not match its Python API
        self.kind = kind
        self.nprobe = nprobe

    @classmethod
    def flat(cls, dim: int) -> VectorIndex:
        return cls(faiss.IndexIDMap2(faiss.IndexFlatIP(dim)), "flat")

    @classmethod
    def ivf(cls, train: np.ndarray, *, nprobe: int = 32, seed: int = 0) -> VectorIndex:
        """An empty IVF index whose coarse quantiser is trained on ``train`` (n, D)."""
        n, dim = train.shape
        nlist = ivf_lists(n)
        index = faiss.IndexIVFFlat(faiss.IndexFlatIP(dim), dim, nlist, faiss.METRIC_INNER_PRODUCT)
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
        self, query: np.ndarray, k: int, allowed: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """query (D,) → similarities (≤k,), ids (≤k,), best first. ``allowed`` is a bool mask
        over row ids (index = id); ids beyond it are not allowed."""
        q = np.ascontiguousarray(query, dtype=np.float32).reshape(1, -1)
        k = min(k, self.ntotal)
        if k <= 0:
            return np.zeros(0, np.float32), np.zeros(0, np.int64)
        if allowed is None:
            params = self._params(None, self.nprobe)
            sims, ids = self.index.search(q, k, params=params)
            return _trim(sims[0], ids[0])
        eligible = int(allowed.sum())
        k = min(k, eligible)
        if k <= 0:
            return np.zeros(0, np.float32), np.zeros(0, np.int64)
        bitmap = np.packbits(allowed, bitorder="little")
        selector = faiss.IDSelectorBitmap(len(allowed), faiss.swig_ptr(bitmap))
        sims, ids = self.index.search(q, k, params=self._params(selector, self.nprobe))
        sims, ids = _trim(sims[0], ids[0])
        if len(ids) < k and self.kind == "ivf":  # eligible rows outside the probed lists
            sims, ids = self.index.search(q, k, params=self._params(selector, self.nlist))
            sims, ids = _trim(sims[0], ids[0])
        del bitmap  # the selector points into it until here
        return sims, ids

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
    def deserialize(cls, data: bytes, kind: str, *, nprobe: int = 32) -> VectorIndex:
        index = faiss.deserialize_index(np.frombuffer(data, dtype=np.uint8))
        return cls(index, kind, nprobe=nprobe)


def _trim(sims: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    keep = ids >= 0
    return sims[keep], ids[keep]


def search_reference(
    vectors: np.ndarray, ids: np.ndarray, query: np.ndarray, k: int
) -> tuple[np.ndarray, np.ndarray]:
    """Exact top-k by inner product with numpy: the ground truth for tests and recall."""
    sims = vectors @ np.asarray(query, dtype=np.float32)
    order = np.argsort(-sims, kind="stable")[:k]
    return sims[order], ids[order]
