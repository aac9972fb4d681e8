"""Assembles the FastAPI app: lifespan (model, maps, batcher), routers, error mapping,
and one ASGI middleware for body limits, request timeouts and request metrics."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from fastapi.responses import JSONResponse
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from lidar_core.errors import LidarCoreError, PointCountError
from service.api import descriptors, keyframes, maps, queries, system
from service.auth import Authenticator
from service.backup import data_dir_lock
from service.core import PlaceService
from service.encoder import Encoder
from service.errors import PayloadTooLarge, ServiceError, error_body
from service.maps import MapRegistry
from service.schemas import DescriptorQueryIn, KeyframeBatchIn
from service.settings import Settings

log = logging.getLogger("overlapmamba.service")

DESCRIPTION = """
LiDAR place recognition with OverlapMamba. Send a scan, get a 256-d descriptor; keep maps of
keyframes; ask which places a scan matches and whether it closes a loop.

* Scans are binary bodies (`application/octet-stream` float32 xyzi|xyz, `application/x-npy`,
  `application/x-pcd`), optionally `Content-Encoding: gzip|zstd` — never JSON lists.
* Errors are `{"error": {"code", "message", "detail"}}`.
* With API keys configured, send `Authorization: Bearer <key>` or `X-API-Key: <key>`.
"""


def _error(
    status: int, code: str, message: str, detail: Any = None, headers: Any = None
) -> JSONResponse:
    return JSONResponse(error_body(code, message, detail), status_code=status, headers=headers)


def _lidar_status(err: LidarCoreError) -> int:
    if isinstance(err, PointCountError) and err.detail.get("points", 0) > err.detail.get(
        "max_points", float("inf")
    ):
        return 413
    return 422 if err.code in ("non_finite_points", "point_count_out_of_range") else 400


class GuardMiddleware:
    """Per HTTP request: refuse bodies over the limit while they stream in (413), cancel a
    request that runs past its timeout (504), and count requests by route and status."""

    def __init__(self, app: ASGIApp, max_body_bytes: int, timeout_s: float) -> None:
        self.app = app
        self.max_body = max_body_bytes
        self.timeout_s = timeout_s

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        received = 0
        started = False
        status = 500
        for name, value in scope.get("headers", []):
            if name == b"content-length" and value.isdigit() and int(value) > self.max_body:
                resp = _error(
                    413,
                    "payload_too_large",
                    f"body is {int(value)} bytes; allowed: at most {self.max_body}",
                    {"max_body_bytes": self.max_body},
                )
                await resp(scope, receive, send)
                return

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_body:
                    raise PayloadTooLarge(
                        f"body exceeds {self.max_body} bytes", max_body_bytes=self.max_body
                    )
            return message

        async def tracking_send(message: Message) -> None:
            nonlocal started, status
            if message["type"] == "http.response.start":
                started = True
                status = message["status"]
            await send(message)

        try:
            async with asyncio.timeout(self.timeout_s):
                await self.app(scope, limited_receive, tracking_send)
        except TimeoutError:
            if not started:
                status = 504
                resp = _error(504, "timeout", f"request ran past its {self.timeout_s} s timeout")
                await resp(scope, receive, send)
        finally:
            svc = getattr(scope["app"].state, "service", None) if "app" in scope else None
            route = scope.get("route")
            if svc is not None:
                svc.stats.request(getattr(route, "path", "unmatched"), status)


async def _load_maps(app: FastAPI, svc: PlaceService) -> None:
    app.state.stage = "loading maps"
    registry = svc.registry
    try:
        await run_in_threadpool(registry.load_all)
    except Exception as err:
        log.exception("loading the maps failed")
        app.state.stage = f"failed: {type(err).__name__}: {err}"
        return
    for m in registry.maps.values():
        svc.stats.p_keyframes.labels(m.map_id).set(m.index.ntotal)
        if m.model_id != svc.model_id:
            log.warning(
                "map %s was built with model %s, not %s: its queries and inserts will be "
                "refused (409)",
                m.map_id,
                m.model_id,
                svc.model_id,
            )
    app.state.ready = True
    app.state.stage = "ready"
    log.info("ready: %d maps under %s", len(registry.maps), svc.settings.data_dir)


def create_app(settings: Settings, *, encoder: Encoder | None = None) -> FastAPI:
    """The app. The model loads in the lifespan unless an ``encoder`` is handed in (tests)."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        with data_dir_lock(settings.data_dir):  # one service per data folder
            app.state.stage = "loading model"
            enc = encoder
            if enc is None:
                threads = settings.batching.intra_op_threads
                enc = await run_in_threadpool(
                    lambda: Encoder(settings.model, intra_op_threads=threads)
                )
            log.info(
                "model %s (%s, %s weights) loaded in %.2f s from %s",
                enc.model_id,
                enc.meta.profile.name,
                enc.meta.weights,
                enc.load_s,
                enc.path,
            )
            registry = MapRegistry(
                settings.data_dir, settings.index, model_id=enc.model_id, dim=enc.dim
            )
            svc = PlaceService(settings, enc, registry)
            await svc.batcher.start()
            app.state.service = svc
            # Maps load after start-up: /healthz answers meanwhile (a liveness probe must
            # not kill a process replaying a large map); /readyz says 503 until done.
            loader = asyncio.create_task(_load_maps(app, svc))
            try:
                yield
            finally:
                app.state.ready = False
                if not loader.done():
                    loader.cancel()
                with contextlib.suppress(BaseException):
                    await loader
                await svc.batcher.stop()
                await run_in_threadpool(registry.close)

    app = FastAPI(
        title="OverlapMamba place recognition",
        version="1",
        description=DESCRIPTION,
        lifespan=lifespan,
    )
    app.state.ready = False
    app.state.stage = "starting"
    app.state.service = None
    app.state.settings = settings
    app.state.auth = Authenticator(settings.auth)

    @app.exception_handler(ServiceError)
    async def service_error(request: Request, err: ServiceError) -> JSONResponse:
        headers = dict(err.headers)
        if err.status == 401 and request.url.path == "/dashboard":
            headers["WWW-Authenticate"] = 'Basic realm="overlapmamba"'
        return _error(err.status, err.code, err.message, err.detail, headers)

    @app.exception_handler(LidarCoreError)
    async def lidar_error(_: Request, err: LidarCoreError) -> JSONResponse:
        return _error(_lidar_status(err), err.code, err.message, err.detail)

    @app.exception_handler(RequestValidationError)
    async def validation_error(_: Request, err: RequestValidationError) -> JSONResponse:
        errors = [{"loc": list(e["loc"]), "msg": e["msg"], "type": e["type"]} for e in err.errors()]
        where = ", ".join(".".join(str(p) for p in e["loc"]) + f": {e['msg']}" for e in errors[:3])
        return _error(422, "invalid_request", f"invalid request: {where}", {"errors": errors})

    @app.exception_handler(StarletteHTTPException)
    async def http_error(_: Request, err: StarletteHTTPException) -> JSONResponse:
        code = {404: "route_not_found", 405: "method_not_allowed"}.get(
            err.status_code, "http_error"
        )
        return _error(err.status_code, code, str(err.detail), None, getattr(err, "headers", None))

    @app.exception_handler(Exception)
    async def internal_error(_: Request, err: Exception) -> JSONResponse:
        log.exception("unhandled error")
        return _error(500, "internal_error", f"internal error: {type(err).__name__}")

    for r in (system.router, descriptors.router, maps.router, keyframes.router, queries.router):
        app.include_router(r)

    def openapi() -> dict[str, Any]:
        """FastAPI's schema, plus the request models of routes that parse their own bodies
        (scan-or-JSON queries; batches read after the key check)."""
        if app.openapi_schema is None:
            schema = get_openapi(
                title=app.title, version=app.version, description=app.description, routes=app.routes
            )
            comps = schema.setdefault("components", {}).setdefault("schemas", {})
            for model in (DescriptorQueryIn, KeyframeBatchIn):
                js = model.model_json_schema(ref_template="#/components/schemas/{model}")
                for name, sub in js.pop("$defs", {}).items():
                    comps.setdefault(name, sub)
                comps.setdefault(model.__name__, js)
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
    app.add_middleware(
        GuardMiddleware,
        max_body_bytes=settings.limits.max_body_bytes,
        timeout_s=settings.limits.request_timeout_s,
    )
    return app
