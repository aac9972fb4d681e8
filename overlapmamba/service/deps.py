"""FastAPI dependencies as ``Annotated`` aliases: the service, and the caller's rights.

They are coroutines because none of them blocks (a dictionary lookup, one SHA-256 of the
key): FastAPI runs a plain ``def`` dependency in its thread pool, which cost every request
three thread hops to the pool and back before its route ran, on the same two cores that
decode and encode the scans."""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Annotated, Any

from fastapi import Depends, Request

from overlapmamba.service.auth import Action, Authenticator, Principal, presented_key
from overlapmamba.service.errors import NotReady, Unavailable
from overlapmamba.service.places import PlaceService


def start_failure(state: Any) -> str | None:
    """Why the start-up failed for good (loading the maps raised), or None: such a service
    will not become ready by waiting, and its probes and routes say so."""
    stage = str(getattr(state, "stage", ""))
    return stage if stage.startswith("failed") else None


def serving(state: Any) -> PlaceService:
    """The app's service once it is ready; else 503: ``not_ready`` while it starts,
    ``start_failed`` once its start-up failed for good."""
    svc: PlaceService | None = getattr(state, "service", None)
    if svc is not None and state.ready:
        return svc
    failed = start_failure(state)
    if failed is not None:
        raise Unavailable(  # not NotReady: it will not be ready, however long one waits
            f"the service's start-up {failed}; see its log, fix it and restart it",
            code="start_failed",
            retry_after_s=30,
        )
    stage = getattr(state, "stage", "starting")
    raise NotReady(f"the service is starting ({stage}): retry when /readyz says ready")


async def get_service(request: Request) -> PlaceService:
    return serving(request.app.state)


async def get_loaded_service(request: Request) -> PlaceService:
    """The app's service once its model is loaded, ready or not: ``/metrics`` answers while
    the maps replay (a scrape that failed would read as a dead process); else as ``serving``."""
    svc: PlaceService | None = getattr(request.app.state, "service", None)
    return svc if svc is not None else serving(request.app.state)


async def get_principal(request: Request) -> Principal:
    auth: Authenticator = request.app.state.auth
    return auth.identify(presented_key(request))


def require(action: Action) -> Callable[..., Awaitable[Principal]]:
    """A dependency that lets through only callers whose role allows ``action``
    (on the route's ``map_id`` where it has one: a robot key may list its maps)."""

    async def check(
        request: Request, who: Annotated[Principal, Depends(get_principal)]
    ) -> Principal:
        request.app.state.auth.authorize(who, action, request.path_params.get("map_id"))
        return who

    return check


ServiceDep = Annotated[PlaceService, Depends(get_service)]
LoadedServiceDep = Annotated[PlaceService, Depends(get_loaded_service)]
CanEncode = Annotated[Principal, Depends(require(Action.ENCODE))]
CanInsert = Annotated[Principal, Depends(require(Action.INSERT))]
CanWriteMaps = Annotated[Principal, Depends(require(Action.MAP_WRITE))]
CanReadMaps = Annotated[Principal, Depends(require(Action.MAP_READ))]
CanView = Annotated[Principal, Depends(require(Action.VIEW))]
