"""What the sync and async clients share: configuration, request building, response parsing
and the retry rules. The two clients only differ in how they send (``_sync``, ``_async``)."""

from __future__ import annotations

import dataclasses
import json
import math
import random
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import quote

import httpx
import numpy as np
from pydantic import ValidationError

from overlapmamba.client._exceptions import (
    APIError,
    ClientError,
    ConnectError,
    NotFoundError,
    ResponseError,
    Timeout,
    TransportError,
    error_for,
)
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


@dataclass(frozen=True)
class Retry:
    """Exponential backoff with jitter, for idempotent calls only (every call of these
    clients is: reads, PUT/DELETE, and inserts keyed by ``keyframe_id``). A server's
    ``Retry-After`` is honoured when it asks for longer, up to ``max_retry_after_s``: an
    answer asking for more (a proxy's hour, or ``inf``) is raised to the caller at once,
    rather than holding a robot's call that long."""

    attempts: int = 4  # total tries, including the first
    backoff_s: float = 0.25  # wait before the 2nd try; doubles each time
    max_backoff_s: float = 8.0
    jitter: float = 0.5  # ± this fraction of the wait, at random
    statuses: tuple[int, ...] = (429, 502, 503, 504)
    max_retry_after_s: float = 30.0

    def __post_init__(self) -> None:
        if self.attempts < 1:
            raise ValueError(
                f"Retry.attempts must be at least 1 (the first try); got {self.attempts}"
            )
        waits = {"backoff_s": self.backoff_s, "max_backoff_s": self.max_backoff_s}
        waits |= {"max_retry_after_s": self.max_retry_after_s}
        if bad := [f"{k}={v}" for k, v in waits.items() if not 0 <= v < math.inf]:
            raise ValueError(f"Retry waits must be finite seconds ≥ 0; got {', '.join(bad)}")
        if not 0 <= self.jitter <= 1:
            raise ValueError(f"Retry.jitter must lie in [0, 1]; got {self.jitter}")

    def delay(self, attempt: int, retry_after: float | None, rng: random.Random) -> float:
        base = min(self.max_backoff_s, self.backoff_s * 2 ** (attempt - 1))
        wait = base * (1 + self.jitter * (2 * rng.random() - 1))
        return max(wait, retry_after or 0.0)


NO_RETRY = Retry(attempts=1)


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


def _retry_after(resp: httpx.Response) -> float | None:
    value = resp.headers.get("retry-after")
    try:
        seconds = float(value) if value is not None else None
    except ValueError:
        return None
    return None if seconds is None or math.isnan(seconds) else max(seconds, 0.0)


def raise_for(resp: httpx.Response) -> None:
    """Raise the answer's error; a redirect (3xx: httpx does not follow one, e.g. a proxy
    sending http to https) is an error too, naming where it points."""
    if 300 <= resp.status_code < 400:
        where = resp.headers.get("location", "nowhere given")
        raise error_for(resp.status_code)(
            resp.status_code,
            "redirect",
            f"the server redirects to {where}: point the client at that URL",
            {"location": where},
        )
    if resp.status_code < 400:
        return
    try:
        err = resp.json()["error"]
        code, message, detail = err["code"], err["message"], err.get("detail") or {}
    except (ValueError, KeyError, TypeError):
        code, message, detail = "http_error", resp.text[:500] or resp.reason_phrase, {}
    raise error_for(resp.status_code)(
        resp.status_code, code, message, detail, retry_after=_retry_after(resp)
    )


def transport_error(err: httpx.TransportError) -> TransportError:
    if isinstance(err, httpx.TimeoutException):
        return Timeout(f"no answer in time: {err!r}")
    if isinstance(err, httpx.ConnectError):
        return ConnectError(f"cannot connect: {err}")
    return TransportError(f"transport failed: {err!r}")


def read_answer(call: Call, resp: httpx.Response) -> Any:
    """``call.parse(resp)``; a 2xx body that is not this API's answer (an HTML page from a
    proxy, ``{}``, a body cut short) raises :class:`ResponseError` naming what came."""
    try:
        return call.parse(resp)
    except (ValueError, KeyError, TypeError, IndexError, AttributeError) as err:
        raise not_this_api(call, resp, err) from err


def not_this_api(call: Call, resp: httpx.Response | None, err: Exception) -> ResponseError:
    where = f"{call.method} {call.path}"
    if resp is None:  # the body could not even be decoded (a bad content-encoding)
        return ResponseError(f"{where}: the answer's body could not be decoded: {err}")
    kind = resp.headers.get("content-type", "no content-type")
    head = resp.content[:200].decode("utf-8", "replace")
    return ResponseError(
        f"{where} answered {resp.status_code} ({kind}) with a body that is not this API's "
        f"answer ({type(err).__name__}: {err}); expected the service's JSON. Is the URL the "
        f"place-recognition service's? The body began: {head!r}"
    )


def may_have_applied(err: ClientError) -> bool:
    """Whether the request that failed so may have been carried out all the same: its answer
    was lost (connected, then no answer), or the server failed after taking it (5xx but
    503, which refuses before any work)."""
    if isinstance(err, TransportError):  # these never sent the request
        never_sent = (
            httpx.ConnectError,
            httpx.ConnectTimeout,
            httpx.PoolTimeout,
            httpx.UnsupportedProtocol,
        )
        return not isinstance(err.__cause__, never_sent)
    return isinstance(err, APIError) and err.status >= 500 and err.status != 503


def mark_retried(answer: Any, maybe_applied: bool) -> Any:
    """An insert's or an observation's answer to a retry after a try that may have been
    carried out (its answer lost): ``retried`` set, so "existing" is read as what it may be,
    that earlier try's own insert."""
    if maybe_applied and isinstance(answer, Keyframe | ObserveResult | BatchInsertResult):
        return dataclasses.replace(answer, retried=True)
    return answer


def deleted_before(call: Call, err: ClientError, maybe_applied: bool) -> bool:
    """A DELETE retried after a try that may have been carried out answers 404: that
    earlier try deleted it, and the deletion the caller asked for has happened."""
    return call.method == "DELETE" and maybe_applied and isinstance(err, NotFoundError)


def retryable(err: Exception, retry: Retry) -> bool:
    if isinstance(err, TransportError):
        return True
    if not (isinstance(err, APIError) and err.status in retry.statuses):
        return False
    return err.retry_after is None or err.retry_after <= retry.max_retry_after_s


def _filters(**values: Any) -> dict[str, Any]:
    return {k: v for k, v in values.items() if v is not None}


def _pose(pose: Any) -> str | None:
    if pose is None:
        return None
    values = [float(v) for v in np.asarray(pose, dtype=float).ravel()]
    if len(values) != 7:
        raise ValueError(f"pose must be 7 numbers x,y,z,qx,qy,qz,qw; got {len(values)}")
    return ",".join(repr(v) for v in values)


def _m(map_id: str) -> str:
    return quote(map_id, safe="")


def _json(resp: httpx.Response) -> Any:
    return resp.json()


class Calls:
    """Builds every call of the API; the clients run them."""

    def __init__(self, compress: bool, sensor: str | None = None, mount: str | None = None) -> None:
        self.compress = compress
        self.sensor = sensor  # the client's sensor: every scan call names it unless told
        self.mount = mount  # where it sits (HEIGHT[,PITCH[,ROLL]]): every scan call names it

    def _sensor(self, sensor: str | None) -> dict[str, str]:
        chosen = sensor or self.sensor
        params = {} if chosen is None else {"sensor": chosen}
        return params if self.mount is None else {**params, "mount": self.mount}

    def health(self) -> Call:
        return Call("GET", "/readyz", _json)

    def sensors(self) -> Call:
        return Call("GET", "/v1/sensors", _json)

    def describe(self, scan: Scan, sensor: str | None = None) -> Call:
        body, headers = encode(scan, compress=self.compress)

        def parse(r: httpx.Response) -> Descriptor:
            d = r.json()
            return Descriptor(
                np.asarray(d["descriptor"], np.float32), d["model_id"], d["timings_ms"]
            )

        params: dict[str, Any] = self._sensor(sensor)
        return Call("POST", "/v1/descriptors", parse, params=params, content=body, headers=headers)

    def describe_batch(self, scans: list[Scan], sensor: str | None = None) -> Call:
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

        params: dict[str, Any] = self._sensor(sensor)
        return Call(
            "POST", "/v1/descriptors:batch", parse, params=params, content=content, headers=headers
        )

    def create_map(
        self,
        map_id: str,
        index: str | None,
        keep_geometry: bool | None,
        sensor: str | None = None,
        mount: str | tuple[float, ...] | None = None,
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
    ) -> Call:
        body, headers = encode(scan, compress=self.compress)
        params = _filters(
            keyframe_id=keyframe_id,
            timestamp=timestamp,
            robot_id=robot_id,
            session_id=session_id,
            pose=_pose(pose),
            **self._sensor(sensor),
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
            f"/v1/maps/{_m(map_id)}/keyframes/{quote(keyframe_id, safe='')}",
            lambda r: Keyframe.from_json(r.json()),
        )

    def delete_keyframe(self, map_id: str, keyframe_id: str) -> Call:
        path = f"/v1/maps/{_m(map_id)}/keyframes/{quote(keyframe_id, safe='')}"
        return Call("DELETE", path, lambda r: None)

    def query(
        self,
        map_id: str,
        scan: Scan | None,
        descriptor: Any,
        k: int,
        filters: dict[str, Any],
        sensor: str | None = None,
    ) -> Call:
        if (scan is None) == (descriptor is None):
            raise ValueError("query needs exactly one of scan= or descriptor=")
        filters = renamed(filters, "query", stacklevel=5)  # max_distance: deprecated
        params = _filters(k=k, **filters, **(self._sensor(sensor) if scan is not None else {}))
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
            **self._sensor(sensor),
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


def check_mount(mount: str | tuple[float, ...] | None) -> str | None:
    """A client's ``mount``: ``"HEIGHT[,PITCH[,ROLL]]"`` or a tuple of those numbers (metres,
    degrees), checked here so a robot learns of a typo at start, not at its first scan."""
    if mount is None:
        return None
    text = mount if isinstance(mount, str) else ",".join(repr(float(x)) for x in mount)
    try:
        Mount.parse(text)
    except ValidationError as err:
        first = err.errors()[0]
        raise ValueError(f"mount {text!r}: {first['loc'][0]} {first['msg'].lower()}") from None
    return text
