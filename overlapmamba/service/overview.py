"""A picture of a map for operators: where its keyframes are, where each robot drove, and
where robots closed loops — what the dashboard's map panel draws
(``GET /v1/maps/{map_id}/overview``).

Keyframe positions come from the map itself (their poses, latest first, at most
``limit``). Tracks and loop-closure edges come from the traffic this process has answered:
each observation that carried a pose adds a point to its robot's track (the latest
``TRACK_POINTS`` per robot, ``MAX_ROBOTS`` robots per map) and, when it closed a loop with a
keyframe that has a pose, an edge from the robot's position to the keyframe's (the latest
``MAX_CLOSURES`` per map), marked verified when its relative pose was checked. They start
empty when the service starts; a map's are dropped when it is deleted. Only x and y are
kept: the picture is a bird's-eye view.
"""

from __future__ import annotations

import threading
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any

TRACK_POINTS = 300
MAX_ROBOTS = 64
MAX_CLOSURES = 1000


@dataclass
class _MapTraffic:
    tracks: OrderedDict[str, deque[tuple[float, float]]] = field(default_factory=OrderedDict)
    closures: deque[dict[str, Any]] = field(default_factory=lambda: deque(maxlen=MAX_CLOSURES))


class Overview:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._maps: dict[str, _MapTraffic] = {}

    def observed(
        self,
        map_id: str,
        robot: str,
        pose: list[float] | None,
        closure_to: list[float] | None = None,
        keyframe_id: str | None = None,
        verified: bool | None = None,
    ) -> None:
        """One observation: the robot's pose (x, y, z, …) if it sent one, and the pose of the
        keyframe it closed a loop with, if it did and that keyframe has one."""
        if pose is None:
            return
        x, y = float(pose[0]), float(pose[1])
        with self._lock:
            t = self._maps.setdefault(map_id, _MapTraffic())
            track = t.tracks.pop(robot, None) or deque(maxlen=TRACK_POINTS)
            t.tracks[robot] = track  # most recently seen last
            while len(t.tracks) > MAX_ROBOTS:
                t.tracks.popitem(last=False)
            track.append((x, y))
            if closure_to is not None:
                t.closures.append(
                    {
                        "robot_id": robot,
                        "from": [x, y],
                        "to": [float(closure_to[0]), float(closure_to[1])],
                        "keyframe_id": keyframe_id,
                        "verified": verified,
                    }
                )

    def forget(self, map_id: str) -> None:
        with self._lock:
            self._maps.pop(map_id, None)

    def public(self, map_id: str, positions: list[tuple[str, float, float]]) -> dict[str, Any]:
        """The picture: keyframes grouped by robot, tracks, closure edges (oldest first)."""
        keyframes: dict[str, list[list[float]]] = {}
        for robot, x, y in reversed(positions):  # oldest first, as a track is drawn
            keyframes.setdefault(robot, []).append([x, y])
        with self._lock:
            t = self._maps.get(map_id, _MapTraffic())
            tracks = {r: [list(p) for p in pts] for r, pts in t.tracks.items()}
            closures = list(t.closures)
        return {
            "map_id": map_id,
            "keyframes": keyframes,
            "tracks": tracks,
            "closures": closures,
        }
