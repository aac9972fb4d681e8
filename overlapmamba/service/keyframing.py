"""When a robot's observation becomes a keyframe (``insert: "auto"``): the last keyframe of
the robot's session in each map, remembered as inserts happen and read back from the store
when it is not, against ``observe.insert_min_interval_s`` and ``observe.insert_min_distance_m``.
A session is the robot's clock and odometry frame: a new one (a restarted node, whose clock
may start below the last session's) starts its own schedule with a ``first`` keyframe.

:class:`~overlapmamba.service.places.PlaceService` owns one :class:`KeyframeSchedule`; it
tells the schedule of every keyframe inserted and asks it, per observation, why the scan is
due (or that it is not), and whether a retried observation's keyframe is already there.
"""

from __future__ import annotations

import asyncio
import weakref
from collections import OrderedDict
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import numpy as np

from overlapmamba.service.answers import InsertReason, Observation
from overlapmamba.service.backends.base import PlaceMap
from overlapmamba.service.settings import ObserveSettings
from overlapmamba.service.threads import in_thread

# (map, robot, session) keys remembered at most: the ids come from clients, so the memory is
# bounded; a key dropped is read back from the store at its robot's next observation
REMEMBERED = 10_000
_Key = tuple[str, str, str]  # (map, robot, session)


class KeyframeSchedule:
    """The sessions' last keyframes, (map, robot, session) → (timestamp, position or None)."""

    def __init__(self, settings: ObserveSettings) -> None:
        self.settings = settings
        self._last: OrderedDict[_Key, tuple[float, np.ndarray | None]] = OrderedDict()
        # one decision at a time per (map, robot); a lock nobody holds or waits for goes
        self._deciding: weakref.WeakValueDictionary[tuple[str, str], asyncio.Lock] = (
            weakref.WeakValueDictionary()
        )

    @asynccontextmanager
    async def deciding(self, map_id: str, robot: str) -> AsyncIterator[None]:
        """Hold while asking :meth:`due` and inserting what it said: a robot whose
        observations arrive together (a client that does not wait for each answer) would
        otherwise see them all due against the same last keyframe, and insert each."""
        key = (map_id, robot)
        lock = self._deciding.get(key)
        if lock is None:
            lock = self._deciding[key] = asyncio.Lock()
        async with lock:
            yield

    def remember(
        self, map_id: str, robot: str, session: str, timestamp: float, pose: list[float] | None
    ) -> None:
        """A keyframe of ``robot``'s ``session`` went into ``map_id`` (one older than known
        changes nothing)."""
        pos = None if pose is None else np.array(pose[:3])
        key = (map_id, robot, session)
        old = self._last.pop(key, None)
        self._last[key] = old if old and old[0] > timestamp else (timestamp, pos)
        while len(self._last) > REMEMBERED:
            self._last.popitem(last=False)

    def forget(self, map_id: str) -> None:
        """The map was deleted, or a keyframe of it (perhaps a robot's last): its robots' last
        keyframes are read back from the store at their next observations."""
        for key in [k for k in self._last if k[0] == map_id]:
            del self._last[key]

    async def _last_of(
        self, m: PlaceMap, obs: Observation
    ) -> tuple[float, np.ndarray | None] | None:
        key = (m.map_id, obs.robot_id, obs.session_id)
        if key not in self._last:
            kf = await in_thread(m.last_keyframe, obs.robot_id, obs.session_id)
            if kf is None:
                return None
            self.remember(*key, kf.timestamp, kf.pose)
        return self._last.get(key)

    async def retried(self, m: PlaceMap, obs: Observation) -> bool:
        """Whether this observation's own keyframe (``robot:session:timestamp``) is already
        in the map: its session's last keyframe is at its very timestamp, and it is there."""
        last = self._last.get((m.map_id, obs.robot_id, obs.session_id))
        if last is None or last[0] != obs.timestamp:
            return False
        return await in_thread(m.get, obs.keyframe_id) is not None

    async def due(self, m: PlaceMap, obs: Observation) -> InsertReason | None:
        """Why this observation becomes a keyframe, or None if it does not."""
        if obs.insert == "always":
            return "always"
        if obs.insert == "never":
            return None
        last = await self._last_of(m, obs)
        if last is None:
            return "first"
        if abs(obs.timestamp - last[0]) >= self.settings.insert_min_interval_s:
            return "time"
        if obs.pose is None or last[1] is None:
            return None
        moved = float(np.linalg.norm(np.array(obs.pose[:3]) - last[1]))
        return "distance" if moved >= self.settings.insert_min_distance_m else None
