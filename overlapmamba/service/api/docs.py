"""The API's documentation page, ``/docs`` (Swagger UI), served from this process: FastAPI's
own pages load their scripts from a CDN, so on a robot fleet's network with no way out (a
warehouse, a mine, a ship) they stayed blank. The script and style come from the
``fastapi-offline`` package's copies of swagger-ui-dist (its static files only), under
``/docs/assets/``; the page names nothing outside this origin. ReDoc's page is not served:
its bundle fetches its logo from its makers' CDN, and Swagger UI shows the same API."""

from __future__ import annotations

from importlib import resources

from fastapi import APIRouter, Request, Response
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse

from overlapmamba.service.errors import NotFound

router = APIRouter(include_in_schema=False)

ASSETS = {  # the only files served, and their types
    "swagger-ui-bundle.js": "text/javascript",
    "swagger-ui.css": "text/css",
    "favicon.png": "image/png",
}
TITLE = "OverlapMamba place recognition"
# The page's own inline start-up script and style, the bundle from this origin; nothing
# may frame it.
DOCS_HEADERS = {
    "Content-Security-Policy": (
        "default-src 'none'; script-src 'self' 'unsafe-inline'; "
        "style-src 'self' 'unsafe-inline'; img-src 'self' data:; connect-src 'self'; "
        "font-src 'self' data:; frame-ancestors 'none'; "
        "base-uri 'none'; form-action 'none'"
    ),
    "X-Frame-Options": "DENY",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
}


def _at(request: Request, path: str) -> str:
    """``path`` under the prefix a proxy serves this app at (``--root-path``), as FastAPI's
    own page does."""
    return str(request.scope.get("root_path", "")).rstrip("/") + path


def _page(page: HTMLResponse) -> HTMLResponse:
    page.headers.update(DOCS_HEADERS)
    return page


@router.get("/docs")
async def swagger_ui(request: Request) -> HTMLResponse:
    return _page(
        get_swagger_ui_html(
            openapi_url=_at(request, request.app.openapi_url),
            title=f"{TITLE} – API",
            swagger_js_url=_at(request, "/docs/assets/swagger-ui-bundle.js"),
            swagger_css_url=_at(request, "/docs/assets/swagger-ui.css"),
            swagger_favicon_url=_at(request, "/docs/assets/favicon.png"),
        )
    )


@router.get("/docs/assets/{name}")
async def asset(name: str) -> Response:
    if name not in ASSETS:
        raise NotFound(
            f"no documentation asset {name!r}; there are {', '.join(sorted(ASSETS))}",
            code="route_not_found",
        )
    data = resources.files("fastapi_offline").joinpath("static", name).read_bytes()
    # the same bytes until the package is upgraded: a day in a browser's cache
    headers = {"Cache-Control": "public, max-age=86400", "X-Content-Type-Options": "nosniff"}
    return Response(data, media_type=ASSETS[name], headers=headers)
