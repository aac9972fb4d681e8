"""Per-row metadata held beside a FAISS index, for the masks that query filters become."""

from __future__ import annotations

import numpy as np


class FilterColumns:
    """Per-row metadata by row id, for filter masks: robot, session, timestamp, alive."""

    def __init__(self) -> None:
        self.robot = np.zeros(0, np.int32)
        self.session = np.zeros(0, np.int32)
        self.ts = np.zeros(0, np.float64)
        self.alive = np.zeros(0, bool)
        self._codes: dict[str, int] = {}

    def code(self, value: str) -> int:
        return self._codes.setdefault(value, len(self._codes))

    def lookup(self, value: str) -> int:
        return self._codes.get(value, -1)

    def _grow(self, size: int) -> None:
        if size <= len(self.alive):
            return
        new = max(size, 2 * len(self.alive), 1024)
        for name in ("robot", "session", "ts", "alive"):
            old = getattr(self, name)
            arr = np.zeros(new, old.dtype)
            arr[: len(old)] = old
            setattr(self, name, arr)

    def add(self, ids: np.ndarray, meta: list[tuple[str, str, float]]) -> None:
        if not len(ids):
            return
        self._grow(int(ids.max()) + 1)
        self.robot[ids] = [self.code(m[0]) for m in meta]
        self.session[ids] = [self.code(m[1]) for m in meta]
        self.ts[ids] = [m[2] for m in meta]
        self.alive[ids] = True

    def remove(self, ids: np.ndarray) -> None:
        ids = ids[ids < len(self.alive)]
        self.alive[ids] = False
