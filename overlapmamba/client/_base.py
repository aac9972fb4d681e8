"""What the sync and async clients share: configuration and request building (how answers are
read and calls retried: ``_retry``). The two clients only differ in how they send (``_sync``,
``_async``)."""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import quote

import httpx
import numpy as np
from pydantic import ValidationError

from overlapmamba.client._models import (
    BatchInsertResult,
    Descriptor,
    Keyframe,
    MapInfo,
    ObserveResult,
    QueryResult,
)
from overlapmamba.client._scans import Scan, encode
from overlapmamba.core.renamed import renamed
from overlapmamba.core.sensors.mount import Mount


@dataclass(frozen=True)
class Timeouts:
    """Seconds; one object for both clients (``httpx.Timeout`` underneath)."""

    connect: float = 5.0
    read: float = 60.0
    write: float = 60.0
    pool: float = 5.0

    def httpx(self) -> httpx.Timeout:
        return httpx.Timeout(connect=self.connect, read=self.read, write=self.write, pool=self.pool)


@dataclass
class Call:
    """One request and how to read its answer."""

    method: str
    path: str
    parse: Callable[[httpx.Response], Any]
    params: dict[str, Any] = field(default_factory=dict)
    content: bytes | None = None
    json: Any = None
    headers: dict[str, str] = field(default_factory=dict)
    idempotent: bool = True
    answers: tuple[int, ...] = ()  # error statuses whose body is the answer (readiness: 503)


# where a scan's sensor sits: "HEIGHT[,PITCH[,ROLL]]" or those numbers (check_mount)
MountArg = str | float | tuple[float, ...] | None

# what a query takes beside k and sensor (the server's query parameters)
QUERY_FILTERS = frozenset(
    {
        "exclude_session", "exclude_robot", "exclude_recent_s", "session_id", "robot_id",
        "timestamp", "time_from", "time_to", "max_match_distance", "max_distance", "verify",
    }
)  # fmt: skip


def _filters(**values: Any) -> dict[str, Any]:
    return {k: v for k, v in values.items() if v is not None}


def _pose(pose: Any) -> str | None:
    if pose is None:
        return None
    if isinstance(pose, str):  # the server's own form, "x,y,z,qx,qy,qz,qw"
        pose = pose.split(",")
    try:
        values = [float(v) for v in np.asarray(pose, dtype=float).ravel()]
    except ValueError:
        raise ValueError(f"pose must be 7 numbers x,y,z,qx,qy,qz,qw; got {pose!r}") from None
    if len(values) != 7:
        raise ValueError(f"pose must be 7 numbers x,y,z,qx,qy,qz,qw; got {len(values)}")
    return ",".join(repr(v) for v in values)


# the characters of the service's robot and session ids, after a letter or digit
NAME_CHARS = "A-Za-z0-9_.@-"
NAME = re.compile(f"[A-Za-z0-9][{NAME_CHARS}]{{0,99}}")


def _m(map_id: str, what: str = "map id") -> str:
    """An id as one segment of a path. ``.`` and ``..`` would be read as the path's own
    steps (``keyframes/..`` is the map: a DELETE of it, the map's), and an empty one as
    none: refused here, as the server refuses them."""
    if map_id in ("", ".", ".."):
        raise ValueError(
            f"{what} {map_id!r} is not an id; allowed: a letter or digit first, then letters, "
            "digits and _.:@+- (map ids: a-z, 0-9, _ and -)"
        )
    return quote(map_id, safe="")


def _json(resp: httpx.Response) -> Any:
    return resp.json()


class Calls:
    """Builds every call of the API; the clients run them."""

    def __init__(self, compress: bool, sensor: str | None = None, mount: str | None = None) -> None:
        self.compress = compress
        self.sensor = sensor  # the client's sensor: every scan call names it unless told
        self.mount = mount  # where it sits (HEIGHT[,PITCH[,ROLL]]): every scan call names it

    def _sensor(self, sensor: str | None, mount: MountArg = None) -> dict[str, str]:
        """A scan call's sensor and mount: the call's own, else the client's."""
        chosen = sensor or self.sensor
        where = check_mount(mount) or self.mount
        params = {} if chosen is None else {"sensor": chosen}
        return params if where is None else {**params, "mount": where}

    def health(self) -> Call:
        # 503 with {"status": "loading" | "failed" | "draining" | "stuck", "detail"}: an answer
        return Call("GET", "/readyz", _json, answers=(503,))

    def sensors(self) -> Call:
        return Call("GET", "/v1/sensors", _json)

    def describe(self, scan: Scan, sensor: str | None = None, mount: MountArg = None) -> Call:
        body, headers = encode(scan, compress=self.compress)

        def parse(r: httpx.Response) -> Descriptor:
            d = r.json()
            return Descriptor(
                np.asarray(d["descriptor"], np.float32), d["model_id"], d["timings_ms"]
            )

        params: dict[str, Any] = self._sensor(sensor, mount)
        return Call("POST", "/v1/descriptors", parse, params=params, content=body, headers=headers)

    def describe_batch(
        self, scans: list[Scan], sensor: str | None = None, mount: MountArg = None
    ) -> Call:
        parts = []
        fields = None
        for s in scans:
            body, headers = encode(s)
            if fields not in (None, headers["x-point-fields"]):
                raise ValueError("all scans of a batch need the same fields (xyz or xyzi)")
            fields = headers["x-point-fields"]
            parts.append(len(body).to_bytes(4, "little") + body)
        content = b"".join(parts)
        headers = {
            "content-type": "application/x-scan-batch; format=application/octet-stream",
            "x-point-fields": fields or "xyzi",
        }
        if self.compress:
            import zstandard

            content = zstandard.ZstdCompressor(level=3).compress(content)
            headers["content-encoding"] = "zstd"

        def parse(r: httpx.Response) -> list[Descriptor]:
            d = r.json()
            return [
                Descriptor(np.asarray(v, np.float32), d["model_id"], t)
                for v, t in zip(d["descriptors"], d["timings_ms"], strict=True)
            ]

        params: dict[str, Any] = self._sensor(sensor, mount)
        return Call(
            "POST", "/v1/descriptors:batch", parse, params=params, content=content, headers=headers
        )

    def create_map(
        self,
        map_id: str,
        index: str | None,
        keep_geometry: bool | None,
        sensor: str | None = None,
        mount: MountArg = None,
    ) -> Call:
        settings = {
            "index": index,
            "keep_geometry": keep_geometry,
            "sensor": sensor,
            "mount": check_mount(mount),
        }
        body = {k: v for k, v in settings.items() if v is not None} or None
        return Call(
            "PUT", f"/v1/maps/{_m(map_id)}", lambda r: MapInfo.from_json(r.json()), json=body
        )

    def list_maps(self) -> Call:
        return Call("GET", "/v1/maps", lambda r: [MapInfo.from_json(m) for m in r.json()["maps"]])

    def get_map(self, map_id: str) -> Call:
        return Call("GET", f"/v1/maps/{_m(map_id)}", lambda r: MapInfo.from_json(r.json()))

    def delete_map(self, map_id: str) -> Call:
        return Call("DELETE", f"/v1/maps/{_m(map_id)}", lambda r: None)

    def insert_keyframe(
        self,
        map_id: str,
        scan: Scan,
        keyframe_id: str,
        timestamp: float,
        robot_id: str,
        session_id: str,
        pose: Any,
        sensor: str | None = None,
        mount: MountArg = None,
    ) -> Call:
        body, headers = encode(scan, compress=self.compress)
        params = _filters(
            keyframe_id=keyframe_id,
            timestamp=timestamp,
            robot_id=robot_id,
            session_id=session_id,
            pose=_pose(pose),
            **self._sensor(sensor, mount),
        )
        return Call(
            "POST",
            f"/v1/maps/{_m(map_id)}/keyframes",
            lambda r: Keyframe.from_json(r.json()),
            params=params,
            content=body,
            headers=headers,
        )

    def insert_descriptors(
        self, map_id: str, model_id: str, keyframes: list[dict[str, Any]]
    ) -> Call:
        rows = []
        for k in keyframes:
            row = dict(k)
            row["descriptor"] = [float(v) for v in np.asarray(row["descriptor"]).ravel()]
            if row.get("yaw_features") is not None:
                row["yaw_features"] = np.asarray(row["yaw_features"], dtype=float).tolist()
            if row.get("pose") is not None:
                row["pose"] = [float(v) for v in np.asarray(row["pose"]).ravel()]
            if isinstance(row.get("timestamp"), np.generic):  # np.float32: not JSON
                row["timestamp"] = row["timestamp"].item()
            rows.append(row)

        def parse(r: httpx.Response) -> BatchInsertResult:
            d = r.json()
            return BatchInsertResult(
                d["inserted"], d["existing"], [Keyframe.from_json(k) for k in d["keyframes"]]
            )

        content = json.dumps({"model_id": model_id, "keyframes": rows}).encode()
        return Call(
            "POST",
            f"/v1/maps/{_m(map_id)}/keyframes:batch",
            parse,
            content=content,
            headers={"content-type": "application/json"},
        )

    def get_keyframe(self, map_id: str, keyframe_id: str) -> Call:
        return Call(
            "GET",
            f"/v1/maps/{_m(map_id)}/keyframes/{_m(keyframe_id, 'keyframe id')}",
            lambda r: Keyframe.from_json(r.json()),
        )

    def delete_keyframe(self, map_id: str, keyframe_id: str) -> Call:
        path = f"/v1/maps/{_m(map_id)}/keyframes/{_m(keyframe_id, 'keyframe id')}"
        return Call("DELETE", path, lambda r: None)

    def query(
        self,
        map_id: str,
        scan: Scan | None,
        descriptor: Any,
        k: int,
        filters: dict[str, Any],
        sensor: str | None = None,
        mount: MountArg = None,
    ) -> Call:
        if (scan is None) == (descriptor is None):
            raise ValueError("query needs exactly one of scan= or descriptor=")
        unknown = sorted(set(filters) - QUERY_FILTERS)
        if unknown:  # the server would ignore them: a filter misspelt would not filter
            raise TypeError(
                f"query() got unknown filter(s) {', '.join(unknown)}; allowed: "
                f"{', '.join(sorted(QUERY_FILTERS - {'max_distance'}))}"
            )
        filters = renamed(filters, "query", stacklevel=5)  # max_distance: deprecated
        scanned = self._sensor(sensor, mount) if scan is not None else {}
        params = _filters(k=k, **filters, **scanned)
        path = f"/v1/maps/{_m(map_id)}/query"
        parse = lambda r: QueryResult.from_json(r.json())  # noqa: E731
        if descriptor is not None:
            vec = [float(v) for v in np.asarray(descriptor).ravel()]
            return Call("POST", path, parse, params=params, json={"descriptor": vec})
        body, headers = encode(scan, compress=self.compress)  # type: ignore[arg-type]
        return Call("POST", path, parse, params=params, content=body, headers=headers)

    def observe(
        self,
        map_id: str,
        scan: Scan,
        robot_id: str,
        session_id: str,
        timestamp: float,
        pose: Any,
        insert: str,
        k: int,
        verify: bool = True,
        sensor: str | None = None,
        mount: MountArg = None,
    ) -> Call:
        body, headers = encode(scan, compress=self.compress)
        params = _filters(
            robot_id=robot_id,
            session_id=session_id,
            timestamp=timestamp,
            pose=_pose(pose),
            insert=insert,
            k=k,
            verify=verify,
            **self._sensor(sensor, mount),
        )
        return Call(
            "POST",
            f"/v1/maps/{_m(map_id)}/observe",
            lambda r: ObserveResult.from_json(r.json()),
            params=params,
            content=body,
            headers=headers,
        )

    def stats(self, map_id: str | None) -> Call:
        path = "/v1/stats" if map_id is None else f"/v1/maps/{_m(map_id)}/stats"
        return Call("GET", path, _json)


def check_mount(mount: str | float | tuple[float, ...] | None) -> str | None:
    """A client's ``mount``: ``"HEIGHT[,PITCH[,ROLL]]"``, a tuple of those numbers (metres,
    degrees) or a height alone, checked here so a robot learns of a typo at start, not at its
    first scan."""
    if mount is None:
        return None
    if isinstance(mount, int | float) and not isinstance(mount, bool):
        mount = (mount,)
    if not isinstance(mount, str | tuple | list):
        raise ValueError(
            f"mount {mount!r}: give HEIGHT[,PITCH[,ROLL]] as a string, a number or a tuple"
        )
    try:
        text = mount if isinstance(mount, str) else ",".join(repr(float(x)) for x in mount)
    except (TypeError, ValueError):
        raise ValueError(f"mount {mount!r}: give HEIGHT[,PITCH[,ROLL]] as numbers") from None
    try:
        Mount.parse(text)
    except ValidationError as err:
        first = err.errors()[0]
        raise ValueError(f"mount {text!r}: {first['loc'][0]} {first['msg'].lower()}") from None
    return text
