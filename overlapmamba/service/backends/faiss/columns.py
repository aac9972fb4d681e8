"""Per-row metadata held beside a FAISS index, for the masks that query filters become."""

from __future__ import annotations

import numpy as np

from overlapmamba.service.domain import Filters

_NAMES = ("robot", "session", "ts", "alive")


class FilterColumns:
    """Per-row metadata by row id, for filter masks: robot, session, timestamp, alive.

    The columns cover the row ids from ``base`` (a multiple of 8, so that a mask over them is
    whole bytes of a bitmap over every id) to the highest added. Row ids only grow (the
    store's AUTOINCREMENT), and a map that keeps its latest keyframes deletes its oldest:
    once the rows below the first live one fill half the columns, they are cut off, so the
    columns hold the live rows' span, not every row the map ever held.

    Robot and session ids are held as integer codes, each counted by the live rows that use
    it: a code no live row uses is let go (and given to the next new id), so ids that come
    and go (a robot a mission, a session a run) do not grow the map's memory for ever."""

    def __init__(self) -> None:
        self.base = 0
        self.robot = np.zeros(0, np.int32)
        self.session = np.zeros(0, np.int32)
        self.ts = np.zeros(0, np.float64)
        self.alive = np.zeros(0, bool)
        self._codes: dict[str, int] = {}
        self._values: list[str | None] = []  # code → id (None: free)
        self._uses: list[int] = []  # code → live rows using it
        self._free: list[int] = []
        self._removed = 0  # rows removed since the columns were last cut

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

    def _cover(self, low: int, high: int) -> None:
        """Grow the columns to cover row ids ``low`` to ``high``."""
        if not len(self.alive):  # the first rows (a map opened, rebuilt): start at them
            self.base = (low // 8) * 8
        if low < self.base:  # below the cut (only after every row was removed): extend down
            shift = self.base - (low // 8) * 8
            for name in _NAMES:
                old = getattr(self, name)
                arr = np.zeros(len(old) + shift, old.dtype)
                arr[shift:] = old
                setattr(self, name, arr)
            self.base -= shift
        size = high + 1 - self.base
        if size <= len(self.alive):
            return
        new = max(size, 2 * len(self.alive), 1024)
        for name in _NAMES:
            old = getattr(self, name)
            arr = np.zeros(new, old.dtype)
            arr[: len(old)] = old
            setattr(self, name, arr)

    def add(self, ids: np.ndarray, meta: list[tuple[str, str, float]]) -> None:
        if not len(ids):
            return
        ids = np.asarray(ids, dtype=np.int64)
        self._cover(int(ids.min()), int(ids.max()))
        self.remove(ids)  # a row written again (a rebuild) gives back the codes it held
        self._cover(int(ids.min()), int(ids.max()))  # the removal may have cut below them
        at = ids - self.base
        self.robot[at] = [self.code(m[0]) for m in meta]
        self.session[at] = [self.code(m[1]) for m in meta]
        self.ts[at] = [m[2] for m in meta]
        self.alive[at] = True

    def remove(self, ids: np.ndarray) -> None:
        at = np.asarray(ids, dtype=np.int64) - self.base
        at = at[(at >= 0) & (at < len(self.alive))]
        for i in np.unique(at[self.alive[at]]):
            self._release(int(self.robot[i]))
            self._release(int(self.session[i]))
            self._removed += 1
        self.alive[at] = False
        if self._removed > max(1024, len(self.alive) // 4):
            self._cut()

    def _cut(self) -> None:
        """Drop the columns below the first live row, once they are half of them."""
        self._removed = 0
        live = np.flatnonzero(self.alive)
        first = int(live[0]) if len(live) else len(self.alive)
        cut = (first // 8) * 8
        if cut < max(1024, len(self.alive) // 2):
            return
        for name in _NAMES:
            setattr(self, name, getattr(self, name)[cut:].copy())
        self.base += cut

    def mask(self, f: Filters) -> np.ndarray | None:
        """The rows ``f`` lets through, over the columns' rows from :attr:`base` (None: every
        row)."""
        if not f.restricts_rows:
            return None
        mask = self.alive.copy()
        if f.exclude_session is not None:
            mask &= self.session != self.lookup(f.exclude_session)
        if f.exclude_robot is not None:
            mask &= self.robot != self.lookup(f.exclude_robot)
        if f.exclude_recent_s is not None:
            assert f.session_id is not None and f.timestamp is not None  # Filters checked it
            own = self.session == self.lookup(f.session_id)
            if f.robot_id is not None:  # another robot's session of the same name is not own
                own &= self.robot == self.lookup(f.robot_id)
            mask &= ~(own & (self.ts > f.timestamp - f.exclude_recent_s))
        if f.time_from is not None:
            mask &= self.ts >= f.time_from
        if f.time_to is not None:
            mask &= self.ts <= f.time_to
        return mask
