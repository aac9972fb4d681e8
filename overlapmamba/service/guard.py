"""The ASGI middleware every request and stream goes through: a request id (logs,
``X-Request-ID``), bodies refused past ``limits.max_body_bytes`` while they stream in (413),
a request cancelled past its timeout (504) with its deadline carried to the work it queued
(:data:`~overlapmamba.service.threads.request_deadline`), requests counted by route and
status, and one access line each (a stream's when it ends, with its close code)."""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any

from fastapi.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from overlapmamba.service.errors import PayloadTooLarge, error_body
from overlapmamba.service.logs import new_request_id, request_id
from overlapmamba.service.origins import cross_origin, foreign_origin
from overlapmamba.service.threads import request_deadline

access = logging.getLogger("overlapmamba.access")


def error_response(
    status: int, code: str, message: str, detail: Any = None, headers: Any = None
) -> JSONResponse:
    """The service's JSON error, ``{"error": {"code", "message", "detail"}}``."""
    return JSONResponse(error_body(code, message, detail), status_code=status, headers=headers)


class GuardMiddleware:
    """Per HTTP request: give it a request id (logs, ``X-Request-ID``), refuse bodies over the
    limit while they stream in (413), cancel a request that runs past its timeout (504),
    count requests by route and status, and write one access log line."""

    def __init__(
        self,
        app: ASGIApp,
        max_body_bytes: int,
        timeout_s: float,
        allowed_origins: list[str] | None = None,
        keyless: bool = False,
    ) -> None:
        self.app = app
        self.max_body = max_body_bytes
        self.timeout_s = timeout_s
        self.allowed_origins = allowed_origins or []
        self.keyless = keyless  # overlapmamba.service.origins: only a keyless service checks

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        headers = dict(scope.get("headers", []))
        given = headers.get(b"x-request-id", b"").decode("latin-1")
        rid = new_request_id(given)
        token = request_id.set(rid)
        t0 = time.perf_counter()
        status = 500
        closed: dict[str, int] = {}  # a WebSocket's close code, once either side sent one
        try:
            if scope["type"] == "websocket":
                status = await self._websocket(scope, receive, send, closed)
            else:
                status = await self._http(scope, receive, send, rid)
        finally:
            client = scope.get("client")
            path = _printable(scope.get("path"))
            extra: dict[str, Any] = {"close_code": closed["code"]} if closed else {}
            access.log(
                logging.DEBUG if scope.get("path") in _PROBES else logging.INFO,
                "%s %s %s%s",
                scope.get("method", "WS"),
                path,
                status,
                f" (closed {closed['code']})" if closed else "",
                extra={
                    "method": scope.get("method", "WEBSOCKET"),
                    "path": path,
                    "status": status,
                    "duration_ms": round((time.perf_counter() - t0) * 1e3, 2),
                    "client": client[0] if client else None,
                    **extra,
                },
            )
            request_id.reset(token)

    async def _websocket(
        self, scope: Scope, receive: Receive, send: Send, closed: dict[str, int]
    ) -> int:
        """Run a WebSocket; its status for the log: 101 once accepted, the denial's status
        where the handshake was answered as a route (401, 404, …), 403 for a close before
        the accept (what uvicorn sends the client), 500 if the handler raised first."""
        status = 500

        async def tracking_receive() -> Message:
            message = await receive()
            if message["type"] == "websocket.disconnect":
                closed.setdefault("code", int(message.get("code", 1005)))
            return message

        async def tracking_send(message: Message) -> None:
            nonlocal status
            kind = message["type"]
            if kind == "websocket.accept":
                status = 101
            elif kind == "websocket.http.response.start":
                status = int(message["status"])
            elif kind == "websocket.close":
                status = 403 if status == 500 else status
                closed.setdefault("code", int(message.get("code", 1000)))
            await send(message)

        await self.app(scope, tracking_receive, tracking_send)
        return status

    def _too_large(self, message: str, rid: str) -> JSONResponse:
        detail = {"max_body_bytes": self.max_body}
        return error_response(413, "payload_too_large", message, detail, {"x-request-id": rid})

    async def _http(self, scope: Scope, receive: Receive, send: Send, rid: str) -> int:
        received = 0
        started = False
        status = 500
        if scope.get("method") not in ("GET", "HEAD", "OPTIONS"):  # a write: whose page?
            headers = dict(scope.get("headers", []))
            origin = headers.get(b"origin")
            host = headers.get(b"host", b"").decode("latin-1")
            given = None if origin is None else origin.decode("latin-1")
            if foreign_origin(given, host, self.allowed_origins, self.keyless):
                err = cross_origin(str(given))
                await error_response(
                    err.status, err.code, err.message, err.detail, {"x-request-id": rid}
                )(scope, receive, send)
                _count(scope, err.status, BEFORE_ROUTING)
                return err.status
        for name, value in scope.get("headers", []):
            if name == b"content-length" and value.isdigit() and int(value) > self.max_body:
                why = f"body is {int(value)} bytes; allowed: at most {self.max_body}"
                await self._too_large(why, rid)(scope, receive, send)
                _count(scope, 413, BEFORE_ROUTING)
                return 413

        over = False  # the body crossed the limit while it streamed in
        replaced = False  # ... and the app's own answer to that is dropped for a 413

        async def limited_receive() -> Message:
            nonlocal received, over
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_body:
                    over = True
                    raise PayloadTooLarge(
                        f"body exceeds {self.max_body} bytes", max_body_bytes=self.max_body
                    )
            return message

        async def tracking_send(message: Message) -> None:
            nonlocal started, status, replaced
            if replaced:
                return
            if over and message["type"] == "http.response.start" and message["status"] != 413:
                # FastAPI answers an error raised while it parses a JSON body with a 400
                # ("error parsing the body"): answer what happened instead
                started, status, replaced = True, 413, True
                why = f"body exceeds {self.max_body} bytes"
                await self._too_large(why, rid)(scope, receive, send)
                return
            if message["type"] == "http.response.start":
                started = True
                status = message["status"]
                message = {**message, "headers": [*message.get("headers", []), _rid(rid)]}
            await send(message)

        t0 = time.monotonic()
        deadline = request_deadline.set(t0 + self.timeout_s)
        try:
            async with asyncio.timeout(self.timeout_s):
                await self.app(scope, limited_receive, tracking_send)
        except TimeoutError:
            # the route's own stage times were cancelled with it: without its total, the
            # slowest requests would be missing from every latency figure
            _timed_out(scope, (time.monotonic() - t0) * 1e3)
            if not started:
                status = 504
                resp = error_response(
                    504,
                    "timeout",
                    f"request ran past its {self.timeout_s} s timeout",
                    headers={"x-request-id": rid},
                )
                await resp(scope, receive, send)
        finally:
            request_deadline.reset(deadline)
            _count(scope, status)
        return status


# the routes that record their stage times (overlapmamba.service.places: a scan described,
# queried, observed or inserted): a snapshot or a map's settings that ran out of time are
# not a scan's latency
TIMED_ROUTES = frozenset(
    {
        "/v1/descriptors",
        "/v1/descriptors:batch",
        "/v1/maps/{map_id}/query",
        "/v1/maps/{map_id}/observe",
        "/v1/maps/{map_id}/keyframes",
    }
)


def _timed_out(scope: Scope, ms: float) -> None:
    """A request cut at its timeout: its total time in the latency statistics (the
    service's, and its map's where the route names one that is still there)."""
    app = scope.get("app")
    svc = getattr(app.state, "service", None) if app is not None else None
    route = getattr(scope.get("route"), "path", None)
    if svc is None or route not in TIMED_ROUTES:  # the routes whose stage times are kept
        return
    map_id = scope.get("path_params", {}).get("map_id")
    if map_id is not None and map_id not in svc.stats.by_map:
        map_id = None  # a map this service has not counted (or that is gone): not made
    svc.stats.timings({"total": ms}, map_id)


def _count(scope: Scope, status: int, route: str | None = None) -> None:
    """One answered request on ``overlapmamba_requests_total``, by route and status."""
    app = scope.get("app")
    svc = getattr(app.state, "service", None) if app is not None else None
    if svc is not None:
        svc.stats.request(route or getattr(scope.get("route"), "path", "unmatched"), status)


BEFORE_ROUTING = "(before routing)"  # the route label of a request refused by its headers
_PROBES = {"/healthz", "/readyz", "/metrics"}  # polled every few seconds: debug level


def _printable(path: str | None) -> str:
    """A decoded path may hold control characters (%0A): escape them for text logs."""
    if not path:
        return ""
    return path if path.isprintable() else path.encode("unicode_escape").decode("ascii")


def _rid(rid: str) -> tuple[bytes, bytes]:
    return (b"x-request-id", rid.encode())
