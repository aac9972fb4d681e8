"""The keyframes searched last, kept for the next queries: each one's record (with its
descriptor, when the backend read it) and the spectrum of its yaw features
(:class:`overlapmamba.core.yaw.Spectrum`), least recently used out first, within a budget of
bytes shared by every map of the service (``index.row_cache_mb``).

A query re-ranks its shortlist by correlating its yaw features with every candidate's
(:mod:`overlapmamba.service.ranking`). Without this, each candidate's features are read from
the store and transformed again for every query, though a robot's consecutive queries meet
mostly the same keyframes; from kept spectra a correlation is a product, a sum and one
inverse FFT a candidate. ``/v1/stats`` reports its hits and misses (``row_cache``), and
``python benchmarks/fleet_views.py`` the fleet's rate with it.

Keys are (token, key). The faiss backend gives each map instance a fresh token
(:meth:`RowCache.token`) and keys its rows by row id, which is never reused, so an entry
cannot outlive what it describes; a map drops a deleted keyframe's entry under its write lock
and puts entries under its read lock, so a search never meets a deleted keyframe here. The
qdrant backend keys spectra by (collection, keyframe id, content hash): the same content has
the same features, and the keyframe itself always comes from the search's answer.
"""

from __future__ import annotations

import itertools
import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable, Mapping, Sequence
from typing import TypeVar

import numpy as np

from overlapmamba.core.yaw import Spectrum, as_spectra
from overlapmamba.service.domain import Keyframe

ENTRY_OVERHEAD = 1024  # bytes an entry costs besides its spectrum: the record, the key, links

Row = tuple[Keyframe, Spectrum | None]  # None: the keyframe has no yaw features
K = TypeVar("K", bound=Hashable)


class RowCache:
    """Thread-safe LRU of :data:`Row` by (token, key), at most ``max_bytes`` (0: keeps
    nothing)."""

    def __init__(self, max_bytes: int) -> None:
        if max_bytes < 0:
            raise ValueError(f"max_bytes must be 0 or more; got {max_bytes}")
        self.max_bytes = max_bytes
        self._rows: OrderedDict[tuple[int, Hashable], tuple[Row, int]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self._tokens = itertools.count(1)
        self.hits = 0
        self.misses = 0

    def token(self) -> int:
        """A namespace for one map instance's rows."""
        with self._lock:
            return next(self._tokens)

    def get(self, token: int, ids: Sequence[K]) -> dict[K, Row]:
        """The rows of ``ids`` held, each marked as used now."""
        out: dict[K, Row] = {}
        if not self.max_bytes:
            return out
        with self._lock:
            for i in ids:
                entry = self._rows.get((token, i))
                if entry is None:
                    continue
                self._rows.move_to_end((token, i))
                out[i] = entry[0]
            self.hits += len(out)
            self.misses += len(ids) - len(out)
        return out

    def put(self, token: int, rows: Mapping[K, Row]) -> None:
        """Hold ``rows``, letting the least recently used go beyond the budget (a row larger
        than the whole budget is not held)."""
        if not self.max_bytes:
            return
        with self._lock:
            for i, row in rows.items():
                size = ENTRY_OVERHEAD + (row[1].nbytes if row[1] is not None else 0)
                size += row[0].descriptor.nbytes if row[0].descriptor is not None else 0
                if size > self.max_bytes:
                    continue
                old = self._rows.pop((token, i), None)
                if old is not None:
                    self._bytes -= old[1]
                self._rows[(token, i)] = (row, size)
                self._bytes += size
            while self._bytes > self.max_bytes:
                _, (_, size) = self._rows.popitem(last=False)
                self._bytes -= size

    def read(
        self,
        token: int,
        ids: list[int],
        first: int | None,
        read: Callable[[list[int]], dict[int, tuple[Keyframe, np.ndarray | None]]],
    ) -> dict[int, tuple[Keyframe, np.ndarray | Spectrum | None]]:
        """The rows of ``ids`` for a query that correlates the ``first`` (None: all) with its
        yaw features: those held come from here with their spectra; ``read`` (the store, under
        the map's read lock) gives the others, and those among the first are transformed
        (one FFT call) and held. Rows ``read`` does not know (deleted) are left out."""
        head = ids if first is None else ids[:first]
        held = self.get(token, head)
        fetched = read([i for i in ids if i not in held])
        made = with_spectra({i: fetched[i] for i in head if i in fetched})
        self.put(token, made)
        return {**fetched, **held, **made}

    def discard(self, token: int, ids: Sequence[Hashable]) -> None:
        with self._lock:
            for i in ids:
                old = self._rows.pop((token, i), None)
                if old is not None:
                    self._bytes -= old[1]

    def drop(self, token: int) -> None:
        """Let every row of one map instance go (it closed)."""
        with self._lock:
            for key in [k for k in self._rows if k[0] == token]:
                self._bytes -= self._rows.pop(key)[1]

    def info(self) -> dict[str, int]:
        with self._lock:
            return {
                "max_bytes": self.max_bytes,
                "bytes": self._bytes,
                "rows": len(self._rows),
                "hits": self.hits,
                "misses": self.misses,
            }


def with_spectra(rows: Mapping[K, tuple[Keyframe, np.ndarray | None]]) -> dict[K, Row]:
    """Rows with their yaw features (or None) → the same rows with the features' spectra, all
    transformed in one FFT call: what a backend puts in the cache."""
    features = [(key, f) for key, (_, f) in rows.items() if f is not None]
    made = as_spectra([f for _, f in features])
    by_key = {key: sp for (key, _), sp in zip(features, made, strict=True)}
    return {key: (kf, by_key.get(key)) for key, (kf, _) in rows.items()}
