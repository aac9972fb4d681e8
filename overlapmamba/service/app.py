"""Assembles the FastAPI app: lifespan (model, maps, scan pipeline), routers, error mapping,
and the ASGI middleware every request passes (:mod:`overlapmamba.service.guard`)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import signal
import threading
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from types import FrameType
from typing import Any

import uvicorn
from fastapi import FastAPI, Request, WebSocket
from fastapi.exceptions import RequestValidationError, WebSocketRequestValidationError
from fastapi.openapi.utils import get_openapi
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from overlapmamba.core.errors import LidarCoreError
from overlapmamba.service.api import descriptors, docs, keyframes, maps, queries, stream, system
from overlapmamba.service.auth import Authenticator
from overlapmamba.service.backends.factory import open_backend
from overlapmamba.service.backup import data_dir_lock
from overlapmamba.service.calibration import log_thresholds, resolve
from overlapmamba.service.encoder import Encoder
from overlapmamba.service.errors import (
    ServiceError,
    Unavailable,
    invalid_request,
    lidar_status,
)
from overlapmamba.service.guard import GuardMiddleware, error_response
from overlapmamba.service.logs import configure as configure_logs
from overlapmamba.service.places import PlaceService
from overlapmamba.service.schemas import DescriptorQueryIn, KeyframeBatchIn, MapSettingsIn
from overlapmamba.service.settings import Settings
from overlapmamba.service.threads import encoder_threads, in_thread

log = logging.getLogger("overlapmamba.service")

DESCRIPTION = """
LiDAR place recognition with OverlapMamba. Send a scan, get a 256-d descriptor; keep maps of
keyframes; ask which places a scan matches and whether it closes a loop.

* Scans are binary bodies (`application/octet-stream` float32 xyzi|xyz, `application/x-npy`,
  `application/x-pcd`, `application/x-ros2-pointcloud2`: a ROS 2 PointCloud2 message as
  CDR bytes), optionally `Content-Encoding: gzip|zstd` — never JSON lists.
* Errors are `{"error": {"code", "message", "detail"}}`.
* With API keys configured, send `Authorization: Bearer <key>` or `X-API-Key: <key>`.
"""


async def _load_maps(app: FastAPI, svc: PlaceService) -> None:
    app.state.stage = "loading maps"
    registry = svc.registry
    delay = 0.5
    while True:
        try:
            await in_thread(registry.load_all)
            break
        except Unavailable as err:  # Qdrant not up yet: a replica may start before it
            app.state.stage = f"waiting for the index: {err.message}"
            log.warning("%s; retrying in %.1f s", err.message, delay)
            await asyncio.sleep(delay)
            delay = min(10.0, 2 * delay)
        except Exception as err:
            log.exception("loading the maps failed")
            app.state.stage = f"failed: {type(err).__name__}: {err}"
            return
    try:
        loaded = await in_thread(
            lambda: [(m.map_id, m.model_id, m.count) for m in registry.snapshot_list()]
        )
    except Exception as err:  # e.g. Qdrant went away meanwhile: /readyz reports it
        log.warning("listing the maps failed: %s", err)
        loaded = []
    for map_id, model_id, count in loaded:
        svc.stats.p_keyframes.labels(map_id).set(count)
        if model_id != svc.model_id:
            log.warning(
                "map %s was built with model %s, not %s: its queries and inserts will be "
                "refused (409)",
                map_id,
                model_id,
                svc.model_id,
            )
    app.state.ready = True
    app.state.stage = "ready"
    log.info("ready: %d maps (%s)", len(loaded), registry.name)


def create_app(settings: Settings, *, encoder: Encoder | None = None) -> FastAPI:
    """The app. The model loads in the lifespan unless an ``encoder`` is handed in (tests)."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        # One service per data folder; with Qdrant the process keeps no state of its own.
        owns_data = settings.index.backend == "faiss"
        with data_dir_lock(settings.data_dir) if owns_data else contextlib.nullcontext():
            app.state.stage = "loading model"
            lanes, threads = encoder_threads(
                settings.batching.lanes, settings.batching.intra_op_threads
            )
            enc = encoder
            if enc is None:
                kernel = settings.scan_kernel
                enc = await in_thread(
                    lambda: Encoder(settings.model, intra_op_threads=threads, scan_kernel=kernel)
                )
            log.info(
                "model %s (%s, %s weights, %d view(s) a scan) loaded in %.2f s from %s; scan: %s",
                enc.model_id,
                enc.meta.profile.name,
                enc.meta.weights,
                enc.views,
                enc.load_s,
                enc.path,
                enc.scan_path,
            )
            log.info("encoder: %d lane(s), %d onnxruntime thread(s) each", lanes, enc.threads)
            # The model's own calibration, unless a setting overrides
            # (overlapmamba.service.calibration).
            serving, thresholds = resolve(settings, enc.meta)
            log_thresholds(enc.model_id, thresholds)
            app.state.settings = serving
            registry = open_backend(serving, model_id=enc.model_id, dim=enc.dim)
            svc = PlaceService(serving, enc, registry, thresholds)
            await svc.pipeline.start()
            log.info("registration: in %s", svc.pipeline.registrar.where)
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
                await svc.pipeline.stop()
                t0 = time.perf_counter()
                await in_thread(registry.close)
                log.info(
                    "stopped: %s maps closed in %.2f s",
                    registry.name,
                    time.perf_counter() - t0,
                )

    app = FastAPI(
        title="OverlapMamba place recognition",
        version="1",
        description=DESCRIPTION,
        lifespan=lifespan,
        docs_url=None,  # /docs and /redoc from this process, not a CDN: api/docs.py
        redoc_url=None,
    )
    app.state.ready = False
    app.state.draining = False
    app.state.stage = "starting"
    app.state.service = None
    app.state.settings = settings
    app.state.auth = Authenticator(settings.auth)

    @app.exception_handler(ServiceError)
    async def serviceerror_response(request: Request, err: ServiceError) -> JSONResponse:
        headers = dict(err.headers)
        if err.status == 401 and request.url.path == "/dashboard":
            headers["WWW-Authenticate"] = 'Basic realm="overlapmamba"'
        return error_response(err.status, err.code, err.message, err.detail, headers)

    @app.exception_handler(LidarCoreError)
    async def lidarerror_response(_: Request, err: LidarCoreError) -> JSONResponse:
        return error_response(lidar_status(err), err.code, err.message, err.detail)

    @app.exception_handler(RequestValidationError)
    async def validationerror_response(_: Request, err: RequestValidationError) -> JSONResponse:
        bad = invalid_request(err.errors())
        return error_response(bad.status, bad.code, bad.message, bad.detail)

    @app.exception_handler(WebSocketRequestValidationError)
    async def ws_validationerror(
        websocket: WebSocket, err: WebSocketRequestValidationError
    ) -> None:
        # a stream's handshake answered as an HTTP route's (FastAPI's own closed it: a bare
        # 403 to the robot, which could not tell a bad k from a refused key)
        await stream.refuse(websocket, invalid_request(err.errors()))

    @app.exception_handler(StarletteHTTPException)
    async def httperror_response(_: Request, err: StarletteHTTPException) -> JSONResponse:
        code = {404: "route_not_found", 405: "method_not_allowed"}.get(
            err.status_code, "http_error"
        )
        return error_response(
            err.status_code, code, str(err.detail), None, getattr(err, "headers", None)
        )

    @app.exception_handler(ClientDisconnect)
    async def client_gone(request: Request, _: ClientDisconnect) -> JSONResponse:
        # the client closed the connection before its body was in: no fault of ours (it
        # was a 500 with a traceback); nginx's 499, which no one will read
        log.info(
            "%s %s: the client went away before its body was read", request.method, request.url.path
        )
        return error_response(499, "client_closed_request", "the client closed the connection")

    @app.exception_handler(Exception)
    async def internalerror_response(_: Request, err: Exception) -> JSONResponse:
        log.exception("unhandled error")
        return error_response(500, "internal_error", f"internal error: {type(err).__name__}")

    routers = (system, docs, descriptors, maps, keyframes, queries, stream)
    for r in (module.router for module in routers):
        app.include_router(r)

    def openapi() -> dict[str, Any]:
        """FastAPI's schema, plus the request models of routes that parse their own bodies
        (scan-or-JSON queries; batches read after the key check)."""
        if app.openapi_schema is None:
            schema = get_openapi(
                title=app.title, version=app.version, description=app.description, routes=app.routes
            )
            comps = schema.setdefault("components", {}).setdefault("schemas", {})
            for model in (DescriptorQueryIn, KeyframeBatchIn, MapSettingsIn):
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
        allowed_origins=settings.auth.allowed_origins,
        keyless=not settings.auth.keys,
    )
    return app


class _DrainingServer(uvicorn.Server):
    """uvicorn, plus: on SIGTERM/SIGINT, /readyz turns 503 at once; the service goes on
    serving for ``delay_s`` (a load balancer's probes notice and stop sending), then uvicorn
    stops accepting and drains the requests in flight. A second signal skips the delay."""

    def __init__(self, config: uvicorn.Config, app: FastAPI, delay_s: float) -> None:
        super().__init__(config)
        self.app = app
        self.delay_s = delay_s
        self._delayed: threading.Timer | None = None

    def handle_exit(self, sig: int, frame: FrameType | None) -> None:
        if not self.app.state.draining:
            self.app.state.draining = True
            log.info(
                "signal %d: /readyz is 503; serving %.1f s more, then draining requests in "
                "flight (up to %s s) and snapshotting maps",
                sig,
                self.delay_s,
                self.config.timeout_graceful_shutdown,
            )
            if self.delay_s > 0:
                # uvicorn checks should_exit every 0.1 s; setting it later is thread-safe.
                self._delayed = threading.Timer(self.delay_s, self._drain, (sig, frame))
                self._delayed.daemon = True
                self._delayed.start()
                return
        elif self._delayed is not None:
            self._delayed.cancel()
        self._drain(sig, frame)

    def _drain(self, sig: int, frame: FrameType | None) -> None:
        if not self.should_exit:
            log.info("draining requests in flight")
        super().handle_exit(sig, frame)

    async def _serve(self, sockets: Any = None) -> None:
        await super()._serve(sockets)
        # uvicorn raises the signals it caught again once it has shut down, so a SIGTERM's
        # stop, drained and snapshotted, exited 143, as if killed: a supervisor or `docker
        # ps` could not tell it from a crash. The stop asked for is done: exit 0. (SIGINT
        # is still raised again: a Ctrl-C stops a shell script that ran serve.)
        self._captured_signals = [s for s in self._captured_signals if s != signal.SIGTERM]


def run(settings: Settings) -> None:
    """Serve until SIGTERM or SIGINT. Then: stop accepting, let requests in flight finish (up
    to the request timeout), stop the encoder, snapshot every map, exit 0 (after SIGINT, by
    SIGINT, as a shell expects of a Ctrl-C)."""
    configure_logs(settings.log_level, settings.log_format)
    if not settings.auth.keys and not settings.loopback:
        log.warning(
            "INSECURE: listening on %s with NO API KEYS — anyone who can reach this port can "
            "read and change every map",
            settings.host,
        )
    app = create_app(settings)
    config = uvicorn.Config(
        app,
        host=settings.host,
        port=settings.port,
        log_config=None,  # our handler (overlapmamba.service.logs), not uvicorn's
        access_log=False,  # GuardMiddleware writes the access lines, with request ids
        log_level=settings.log_level,
        timeout_graceful_shutdown=math.ceil(settings.limits.request_timeout_s),
        # a stream's scan frame may be as large as an HTTP body (uvicorn's own cap, 16 MiB,
        # closed the socket on a legal scan with 1009 and lost what was pending)
        ws_max_size=settings.limits.max_body_bytes + (64 << 10),
    )
    _DrainingServer(config, app, settings.shutdown_delay_s).run()
