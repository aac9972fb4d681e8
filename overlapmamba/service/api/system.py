"""Health, readiness, statistics, Prometheus metrics and the dashboard."""

from __future__ import annotations

import contextlib
from importlib import resources
from typing import Any

from fastapi import APIRouter, Request, Response
from fastapi.responses import HTMLResponse, JSONResponse, PlainTextResponse
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from overlapmamba.service.api.openapi import error_responses
from overlapmamba.service.auth import presented_key
from overlapmamba.service.backends.base import each_map
from overlapmamba.service.deps import CanView, LoadedServiceDep, ServiceDep, start_failure
from overlapmamba.service.errors import ServiceError
from overlapmamba.service.schemas import Health
from overlapmamba.service.threads import in_thread

router = APIRouter(tags=["system"])


@router.get(
    "/healthz",
    response_model=Health,
    responses={503: {"description": "the start-up failed: restart the process"}},
    summary="The process is alive",
)
async def healthz(request: Request) -> Response:
    """200 while the process can serve or is getting there; 503 once its start-up has
    failed for good (a liveness probe then restarts it, rather than wait on a process
    that will never be ready)."""
    failed = start_failure(request.app.state)
    if failed is not None:
        return _not_ready(request, "failed", failed)
    svc = getattr(request.app.state, "service", None)
    lanes = _stuck(svc, 2)
    if svc is not None and len(lanes) == svc.pipeline.batcher.lanes:  # it encodes nothing
        return _not_ready(request, "stuck", _stuck_text(lanes))
    return JSONResponse(Health(status="ok").model_dump())


def _shows_detail(request: Request) -> bool:
    """Whether a probe's answer may carry its detail. The probes answer anyone (a load
    balancer or kubelet has no key); with keys configured, what they say beyond the status
    (the data folder, the failed maps and why, the model and its thresholds) is for a
    caller that presents a valid key, of any role."""
    auth = getattr(request.app.state, "auth", None)
    if auth is None or not auth.enabled:
        return True
    try:
        auth.identify(presented_key(request))
    except ServiceError:
        return False
    return True


HIDDEN = {"hidden": "send an API key (any role) to read the detail"}


def _not_ready(request: Request, status: str, stage: str, *, retry: bool = False) -> JSONResponse:
    """A probe's 503: the status and its stage; Retry-After where waiting will help."""
    detail = {"stage": stage} if _shows_detail(request) else HIDDEN
    body = Health(status=status, detail=detail).model_dump()
    return JSONResponse(body, status_code=503, headers={"Retry-After": "1"} if retry else None)


def _stuck(svc: Any, timeouts: float) -> list[tuple[int, float]]:
    """The encoder lanes busy on one call for longer than ``timeouts`` request timeouts:
    every request waiting on them has been answered 504 long since."""
    if svc is None:
        return []
    return svc.pipeline.batcher.stuck(timeouts * svc.settings.limits.request_timeout_s)


def _stuck_text(lanes: list[tuple[int, float]]) -> str:
    each = ", ".join(f"lane {lane} for {s:.0f} s" for lane, s in lanes)
    return f"encoder calls have not returned ({each}): restart the process"


@router.get(
    "/readyz",
    response_model=Health,
    responses={503: {"description": "still loading the model or replaying map indexes"}},
    summary="Ready: the model and every map index are loaded and replayed",
)
async def readyz(request: Request) -> Response:
    state = request.app.state
    if getattr(state, "draining", False):
        return _not_ready(request, "draining", "shutting down")
    failed = start_failure(state)
    if failed is not None:  # waiting will not help: no Retry-After
        return _not_ready(request, "failed", failed)
    if not getattr(state, "ready", False):
        return _not_ready(request, "loading", state.stage, retry=True)
    svc = state.service
    lanes = _stuck(svc, 1)
    if lanes:
        return _not_ready(request, "stuck", _stuck_text(lanes))
    try:  # the Qdrant backend asks its server: unreachable means not ready
        where = await in_thread(svc.registry.describe)
    except ServiceError as err:
        return _not_ready(request, "unavailable", err.message, retry=True)
    if not _shows_detail(request):
        return JSONResponse(Health(status="ready", detail=HIDDEN).model_dump())
    return JSONResponse(
        Health(
            status="ready",
            detail={
                "model_id": svc.model_id,
                "views": svc.encoder.views,
                "scan": svc.encoder.scan_path,
                "lanes": svc.pipeline.batcher.lanes,  # encoder calls at once
                "threads_per_lane": svc.encoder.threads,
                # registration's child processes (0: in the server's threads), and how
                # many times one died and was started again
                "registration_processes": svc.pipeline.registrar.processes,
                "registration_restarts": svc.pipeline.registrar.restarts,
                "sensor": svc.sensors.model_sensor.name,
                "sensor_maps": {
                    name: {"how": m.how, "pairs": m.pairs, "data": m.data, "at": m.at}
                    for name, m in svc.encoder.meta.sensor_maps.items()
                },
                "thresholds": {k: t.public() for k, t in svc.thresholds.items()},
                **where,
                "failed_maps": sorted(svc.registry.failed),  # why: in the log
            },
        ).model_dump()
    )


@router.get("/v1/stats", responses=error_responses(401, 403), summary="Recognition statistics")
async def stats(svc: ServiceDep, _: CanView) -> dict[str, Any]:
    """Counts, loop closures and their acceptance rate, latency percentiles per stage (last
    2048 requests), per-robot last seen and counts, encoder batch sizes, map sizes, and the
    faiss backend's row cache (the keyframes searched last: bytes, rows, hits, misses)."""
    live = await _reconcile(svc)
    maps = {map_id: {"keyframes": n} for map_id, n in live.items()}
    return {
        **svc.stats.public(),
        "maps": maps,
        "encoder_queue": svc.pipeline.pending,
        "row_cache": svc.registry.row_cache_info(),
    }


async def _reconcile(svc: Any) -> dict[str, int]:
    """Every map's keyframe count, as the backend has it now, and the statistics brought
    in line with it (another replica's writes and deletions on a shared Qdrant)."""
    known = svc.stats.known_maps()
    live = await in_thread(lambda: each_map(svc.registry, lambda m: m.count))
    svc.stats.reconcile(known, live)
    return live


@router.get(
    "/metrics",
    summary="Prometheus metrics",
    response_class=PlainTextResponse,
    responses={
        200: {
            "description": "Prometheus text exposition format",
            "content": {CONTENT_TYPE_LATEST.split(";")[0]: {"schema": {"type": "string"}}},
        },
        **error_responses(401, 403),
    },
)
async def metrics(request: Request, svc: LoadedServiceDep, _: CanView) -> Response:
    """Answers from the moment the model is loaded, while the maps replay too:
    ``overlapmamba_ready`` is 1 once /readyz says ready, else 0 (loading, or failed)."""
    ready = getattr(request.app.state, "ready", False)
    svc.stats.p_ready.set(1 if ready else 0)
    if ready:  # (while the maps replay, those not yet loaded are not gone)
        with contextlib.suppress(ServiceError):  # the index away: the last values, not a 503
            await _reconcile(svc)
    svc.stats.p_queue.set(svc.pipeline.pending)
    return Response(generate_latest(svc.stats.registry), media_type=CONTENT_TYPE_LATEST)


@router.get("/dashboard", response_class=HTMLResponse, summary="Live dashboard (HTML)")
async def dashboard(_: CanView) -> HTMLResponse:
    """A self-contained page that polls /v1/stats and draws live charts. With API keys
    configured, the browser asks for one (HTTP Basic; the key is the password)."""
    page = resources.files("overlapmamba.service").joinpath("static/dashboard.html").read_text()
    return HTMLResponse(page, headers=DASHBOARD_HEADERS)


# The page is one file, its script and style inline, reading this origin only: nothing else
# may load into it, it may not be framed (clickjacking), and nothing caches it
DASHBOARD_HEADERS = {
    "Content-Security-Policy": (
        "default-src 'none'; script-src 'unsafe-inline'; style-src 'unsafe-inline'; "
        "connect-src 'self'; img-src data:; frame-ancestors 'none'; base-uri 'none'; "
        "form-action 'none'"
    ),
    "X-Frame-Options": "DENY",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}
