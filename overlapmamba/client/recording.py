"""An offline picture of a replay: an MCAP file that Foxglove opens as a 3-D scene.

``overlapmamba-client observe DRIVE --record out.mcap`` writes, per observation that had a
pose, in the ``map`` frame:

    /overlapmamba/robots/<robot>   foxglove.PoseInFrame    where the robot was
    /overlapmamba/keyframes        foxglove.SceneUpdate    a sphere per inserted keyframe
    /overlapmamba/loop_closures    foxglove.SceneUpdate    a line from the robot to the
                                                           keyframe it closed a loop with:
                                                           green verified, orange
                                                           descriptor-only

MCAP rather than a rerun recording: robotics teams already open ROS 2 data in Foxglove,
the ``mcap`` writer is a small pure-Python package, and the file is read back by its own
reader (``mcap.reader``) in the tests. Messages are JSON with a JSON schema named after
Foxglove's message type; the schemas here list the fields written, not all of Foxglove's.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import IO, Any

from mcap.writer import Writer

from overlapmamba.core import outfiles

VERIFIED = {"r": 0.18, "g": 0.49, "b": 0.2, "a": 1.0}
DESCRIPTOR_ONLY = {"r": 0.94, "g": 0.42, "b": 0.0, "a": 1.0}
KEYFRAME = {"r": 0.12, "g": 0.47, "b": 0.71, "a": 0.8}
_VEC = {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}}
_QUAT = {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}}
_POSE = {"type": "object", "properties": {"position": _VEC, "orientation": _QUAT}}
_TIME = {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}
_ENTITIES = {"type": "array", "items": {"type": "object"}}
SCHEMAS: dict[str, dict[str, Any]] = {
    "foxglove.PoseInFrame": {
        "title": "foxglove.PoseInFrame",
        "type": "object",
        "properties": {"timestamp": _TIME, "frame_id": {"type": "string"}, "pose": _POSE},
    },
    "foxglove.SceneUpdate": {
        "title": "foxglove.SceneUpdate",
        "type": "object",
        "properties": {"deletions": {"type": "array"}, "entities": _ENTITIES},
    },
}


def _time(t: float) -> dict[str, int]:
    """Seconds → ROS time; the nanoseconds rounded first, so that 1.9999999999 s is 2 s, not
    1 s and 0 ns."""
    sec, nsec = divmod(round(t * 1e9), 1_000_000_000)
    return {"sec": int(sec), "nsec": int(nsec)}


def _pose(p: list[float]) -> dict[str, Any]:
    x, y, z, qx, qy, qz, qw = (float(v) for v in p[:7])
    return {
        "position": {"x": x, "y": y, "z": z},
        "orientation": {"x": qx, "y": qy, "z": qz, "w": qw},
    }


def _entity(entity_id: str, t: float, **shapes: list[dict[str, Any]]) -> dict[str, Any]:
    kinds = ("arrows", "cubes", "spheres", "cylinders", "lines", "triangles", "texts", "models")
    return {
        "timestamp": _time(t),
        "frame_id": "map",
        "id": entity_id,
        "lifetime": {"sec": 0, "nsec": 0},  # forever
        "frame_locked": False,
        "metadata": [],
        **{k: shapes.get(k, []) for k in kinds},
    }


class MapRecording:
    """Write observations into an MCAP file; use as a context manager."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if self.path.is_dir():
            raise ValueError(f"--record {self.path} is a folder; give the MCAP file to write")
        # written beside it and renamed over it when closed: what was at the path stays
        # whole until a whole recording replaces it
        self._part = self.path.with_name(f".{self.path.name}.part")
        self.incomplete: Path | None = None  # where a failed replay's recording was kept
        self._file: IO[bytes] = open(self._part, "wb")  # noqa: SIM115 - closed in close()
        self._writer = Writer(self._file)
        self._writer.start(profile="", library="overlapmamba-client")
        self._schemas = {
            name: self._writer.register_schema(
                name=name, encoding="jsonschema", data=json.dumps(schema).encode()
            )
            for name, schema in SCHEMAS.items()
        }
        self._channels: dict[str, int] = {}
        self.messages = 0

    def _write(self, topic: str, schema: str, t: float, message: dict[str, Any]) -> None:
        if topic not in self._channels:
            self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding="json", schema_id=self._schemas[schema]
            )
        ns = round(t * 1e9)
        self._writer.add_message(
            self._channels[topic],
            log_time=ns,
            publish_time=ns,
            data=json.dumps(message).encode(),
        )
        self.messages += 1

    def observation(
        self,
        robot: str,
        t: float,
        pose: list[float] | None,
        keyframe_id: str | None = None,
        closure: tuple[str, list[float], bool | None] | None = None,
    ) -> None:
        """One observation: the robot's pose (x, y, z, qx, qy, qz, qw; nothing is written
        without one), the keyframe it inserted (its id), the loop it closed (keyframe id,
        the keyframe's pose, verified)."""
        if pose is None:
            return
        here = {"x": float(pose[0]), "y": float(pose[1]), "z": float(pose[2])}
        self._write(
            f"/overlapmamba/robots/{robot}",
            "foxglove.PoseInFrame",
            t,
            {"timestamp": _time(t), "frame_id": "map", "pose": _pose(pose)},
        )
        if keyframe_id is not None:
            sphere = {"pose": _pose(pose), "size": {"x": 1.0, "y": 1.0, "z": 1.0}}
            entity = _entity(keyframe_id, t, spheres=[{**sphere, "color": KEYFRAME}])
            self._write(
                "/overlapmamba/keyframes",
                "foxglove.SceneUpdate",
                t,
                {"deletions": [], "entities": [entity]},
            )
        if closure is not None:
            target, to, verified = closure
            line = {
                "type": 0,  # LINE_STRIP
                "pose": _pose([0, 0, 0, 0, 0, 0, 1]),
                "thickness": 0.4,
                "scale_invariant": False,
                "points": [here, {"x": float(to[0]), "y": float(to[1]), "z": float(to[2])}],
                "color": VERIFIED if verified else DESCRIPTOR_ONLY,
                "colors": [],
                "indices": [],
            }
            entity = _entity(f"{robot}@{t:.3f}->{target}", t, lines=[line])
            self._write(
                "/overlapmamba/loop_closures",
                "foxglove.SceneUpdate",
                t,
                {"deletions": [], "entities": [entity]},
            )

    def observe(
        self, client: Any, map_id: str, robot: str, t: float, pose: Any, answer: Any
    ) -> None:
        """One observation as the CLI's ``observe`` answered it (``client``: the sync
        client, to fetch a closed loop's keyframe when it ranked below the answer's k)."""
        lc = answer.loop_closure
        closure = None
        if lc.accepted and lc.keyframe_id is not None:
            to = next((m.pose for m in answer.matches if m.keyframe_id == lc.keyframe_id), None)
            if to is None:
                to = client.get_keyframe(map_id, lc.keyframe_id).pose
            if to is not None:
                closure = (lc.keyframe_id, [float(v) for v in to], lc.verified)
        listed = None if pose is None else [float(v) for v in pose]
        self.observation(robot, t, listed, answer.keyframe, closure)

    def close(self) -> None:
        """Finish the recording and put it at its path; where finishing or the rename fails
        (a full disk, Ctrl-C), what was recorded is kept as :meth:`incomplete_path` and the
        error raised."""
        if self._file.closed:
            return
        err = self._end()
        if err is None:
            try:
                os.replace(self._part, self.path)
                return
            except OSError as failed:
                err = failed
        self._keep()
        raise err

    def __enter__(self) -> MapRecording:
        return self

    def __exit__(self, kind: object, *exc: object) -> None:
        if kind is None:
            self.close()
            return
        # the replay failed: what stood at the path stays; what was recorded is kept beside
        # it. The replay's error is the one raised: one while finishing (a full disk, a
        # second Ctrl-C) is dropped, the partial kept as far as it was written.
        if not self._file.closed:
            self._end()
            self._keep()

    def _end(self) -> BaseException | None:
        """Finish the writer (readable to its end) and close the file; what stopped that."""
        try:
            try:
                self._writer.finish()
            finally:
                self._file.close()
        except BaseException as err:  # Ctrl-C too: the caller decides what to raise
            return err
        return None

    def _keep(self) -> None:
        """The partial recording, if it holds anything, under :meth:`incomplete_path`."""
        try:
            if self.messages:
                kept = self.incomplete_path()
                os.replace(self._part, kept)
                self.incomplete = kept
        except OSError:  # nowhere to keep it: the error that brought us here is raised
            pass
        finally:
            self._part.unlink(missing_ok=True)

    def incomplete_path(self) -> Path:
        """Where a failed replay's recording goes: beside the path, ``NAME.incomplete`` and
        the path's suffix (``.mcap`` for a bare path), else ``NAME.incomplete-2.mcap``, … :
        an earlier failed replay's is never replaced."""
        return outfiles.incomplete_path(self.path, ".mcap")
