"""overlapmamba.service.keyframing: when an observation becomes a keyframe (insert=auto), from
the robot's last keyframe, remembered or read back from its map."""

from __future__ import annotations

import asyncio
from types import SimpleNamespace
from typing import Any

from overlapmamba.service import keyframing
from overlapmamba.service.answers import Observation
from overlapmamba.service.keyframing import KeyframeSchedule
from overlapmamba.service.settings import ObserveSettings


class StoredMap:
    """The two reads the schedule makes of a map, over a dict of keyframes; counts the reads."""

    def __init__(self, map_id: str, keyframes: dict[str, Any] | None = None) -> None:
        self.map_id = map_id
        self.keyframes = keyframes or {}
        self.reads = 0

    def last_keyframe(self, robot: str, session: str) -> Any:
        self.reads += 1
        mine = [
            k for k in self.keyframes.values() if (k.robot_id, k.session_id) == (robot, session)
        ]
        return max(mine, key=lambda k: k.timestamp, default=None)

    def get(self, keyframe_id: str) -> Any:
        return self.keyframes.get(keyframe_id)


def kf(robot: str, t: float, pose: list[float] | None, session: str = "s") -> Any:
    return SimpleNamespace(robot_id=robot, session_id=session, timestamp=t, pose=pose)


def due(s: KeyframeSchedule, m: StoredMap, **obs: Any) -> Any:
    return asyncio.run(s.due(m, Observation(**{"robot_id": "r", "session_id": "s", **obs})))


def test_reasons_follow_the_interval_and_the_distance_since_the_last_keyframe() -> None:
    s = KeyframeSchedule(ObserveSettings(insert_min_distance_m=2.0, insert_min_interval_s=10.0))
    m = StoredMap("m")
    assert due(s, m, timestamp=0.0, pose=[0, 0, 0]) == "first"
    s.remember("m", "r", "s", 0.0, [0, 0, 0])
    assert due(s, m, timestamp=1.0, pose=[1.9, 0, 0]) is None
    assert due(s, m, timestamp=1.0, pose=[2.0, 0, 0]) == "distance"
    assert due(s, m, timestamp=1.0, pose=None) is None  # no pose: only time counts
    assert due(s, m, timestamp=10.0, pose=None) == "time"
    assert due(s, m, timestamp=-10.0, pose=None) == "time"  # a clock that went back
    assert due(s, m, timestamp=1.0, insert="always") == "always"
    assert due(s, m, timestamp=99.0, insert="never") is None


def test_an_older_keyframe_never_replaces_a_newer_one() -> None:
    s = KeyframeSchedule(ObserveSettings())
    m = StoredMap("m")
    s.remember("m", "r", "s", 5.0, [0, 0, 0])
    s.remember("m", "r", "s", 4.0, [50, 0, 0])  # a late insert of an earlier scan
    assert due(s, m, timestamp=5.5, pose=[1, 0, 0]) is None
    assert m.reads == 0


def test_a_forgotten_or_dropped_robot_is_read_back_from_its_map(monkeypatch: Any) -> None:
    monkeypatch.setattr(keyframing, "REMEMBERED", 2)
    s = KeyframeSchedule(ObserveSettings())
    m = StoredMap("m", {"a": kf("r", 3.0, [0, 0, 0])})
    for robot in ("r", "x", "y"):  # r is dropped: two pairs at most
        s.remember("m", robot, "s", 3.0, [0, 0, 0])
    assert due(s, m, timestamp=3.5, pose=[0.5, 0, 0]) is None and m.reads == 1
    s.forget("m")
    assert due(s, m, timestamp=3.5, pose=[0.5, 0, 0]) is None and m.reads == 2
    assert due(s, StoredMap("m"), timestamp=3.5, pose=[0.5, 0, 0]) is None  # remembered again
    s.forget("m")
    assert due(s, StoredMap("m"), timestamp=3.5) == "first"  # an empty map


def test_a_retry_is_recognised_only_when_its_own_keyframe_is_there() -> None:
    s = KeyframeSchedule(ObserveSettings())
    obs = Observation(robot_id="r", session_id="s", timestamp=7.0)
    stored = StoredMap("m", {obs.keyframe_id: kf("r", 7.0, None)})
    assert not asyncio.run(s.retried(stored, obs))  # nothing remembered yet
    s.remember("m", "r", "s", 7.0, None)
    assert asyncio.run(s.retried(stored, obs))
    assert not asyncio.run(s.retried(StoredMap("m"), obs))  # remembered, but not in the map
    later = Observation(robot_id="r", session_id="s", timestamp=8.0)
    assert not asyncio.run(s.retried(stored, later))


def test_a_new_session_keeps_its_own_schedule() -> None:
    """Found in review: the schedule was the robot's across its sessions, so a restarted node
    whose clock began below its last session's (time since boot, sim time) found every
    observation "due by time" against the old session's last keyframe, and inserted each
    until its clock caught up. A session is the robot's clock and odometry frame: the new one
    starts with its first keyframe and is then due by its own interval and distance."""
    s = KeyframeSchedule(ObserveSettings(insert_min_distance_m=2.0, insert_min_interval_s=10.0))
    m = StoredMap("m", {"a": kf("r", 1000.0, [0, 0, 0], session="a")})
    assert due(s, m, session_id="a", timestamp=1001.0, pose=[0.1, 0, 0]) is None
    assert due(s, m, session_id="b", timestamp=0.0, pose=[0, 0, 0]) == "first"
    s.remember("m", "r", "b", 0.0, [0, 0, 0])
    for t in (1.0, 2.0, 3.0):
        assert due(s, m, session_id="b", timestamp=t, pose=[0.1 * t, 0, 0]) is None
    assert due(s, m, session_id="b", timestamp=10.0, pose=[1, 0, 0]) == "time"
    assert due(s, m, session_id="a", timestamp=1002.0, pose=[0.2, 0, 0]) is None  # a's stands
