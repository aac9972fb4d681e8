"""Per-row metadata held beside a FAISS index, for the masks that query filters become."""

from __future__ import annotations

import numpy as np


class FilterColumns:
    """Per-row metadata by row id, for filter masks: robot, session, timestamp, alive.

    Robot and session ids are held as integer codes, each counted by the live rows that use
    it: a code no live row uses is let go (and given to the next new id), so ids that come
    and go (a robot a mission, a session a run) do not grow the map's memory for ever."""

    def __init__(self) -> None:
        self.robot = np.zeros(0, np.int32)
        self.session = np.zeros(0, np.int32)
        self.ts = np.zeros(0, np.float64)
        self.alive = np.zeros(0, bool)
        self._codes: dict[str, int] = {}
        self._values: list[str | None] = []  # code → id (None: free)
        self._uses: list[int] = []  # code → live rows using it
        self._free: list[int] = []

    def code(self, value: str) -> int:
        """The code of ``value``, counted once more (a live row uses it)."""
        code = self._codes.get(value)
        if code is None:
            if self._free:
                code = self._free.pop()
                self._values[code] = value
            else:
                code = len(self._values)
                self._values.append(value)
                self._uses.append(0)
            self._codes[value] = code
        self._uses[code] += 1
        return code

    def _release(self, code: int) -> None:
        self._uses[code] -= 1
        if self._uses[code] == 0:
            value = self._values[code]
            if value is not None:
                del self._codes[value]
            self._values[code] = None
            self._free.append(code)

    def lookup(self, value: str) -> int:
        return self._codes.get(value, -1)

    @property
    def codes(self) -> int:
        """Robot and session ids held (those of live rows)."""
        return len(self._codes)

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
        self.remove(ids)  # a row written again (a rebuild) gives back the codes it held
        self.robot[ids] = [self.code(m[0]) for m in meta]
        self.session[ids] = [self.code(m[1]) for m in meta]
        self.ts[ids] = [m[2] for m in meta]
        self.alive[ids] = True

    def remove(self, ids: np.ndarray) -> None:
        ids = np.asarray(ids)
        ids = ids[ids < len(self.alive)]
        for i in np.unique(ids[self.alive[ids]]):
            self._release(int(self.robot[i]))
            self._release(int(self.session[i]))
        self.alive[ids] = False
