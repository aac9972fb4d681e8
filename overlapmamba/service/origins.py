"""Which web pages may write to the service or open a stream.

A browser sends a WebSocket, or a "simple" POST (a ``text/plain`` body, which the JSON routes
parse), for any site's page with no preflight, carrying that page's ``Origin``. Without keys
(a keyless service answers only on loopback unless ``--insecure``), any site a user visits
could so insert keyframes into, or observe into, a service on that user's machine, also by
DNS rebinding (a site's own name made to resolve to 127.0.0.1: its Origin then matches the
Host it sends). With keys nothing here is needed: a browser cannot present a key on a
WebSocket, and a key header on a write makes it preflighted, which another site fails (the
service sends no CORS headers); Basic is taken for reads only (:mod:`.auth`).

So on a keyless service a browser's write or stream (it has an ``Origin``) passes when its
origin is listed in ``auth.allowed_origins``, or is the service's own page (the Origin's host
and port those of the ``Host`` the browser sent, default ports filled in) under a loopback
name or an IP address. Programs (robots, the clients, curl) send no Origin and always pass.
"""

from __future__ import annotations

import ipaddress
from urllib.parse import urlsplit

from overlapmamba.service.errors import Forbidden

_DEFAULT_PORTS = {"http": 80, "https": 443}


def site(origin: str) -> tuple[str, str, int] | None:
    """``scheme://host[:port]`` as (scheme, host, port), lowercased, the scheme's default
    port filled in; None where it is no such origin (``null``, a path, another scheme)."""
    try:
        parts = urlsplit(origin.strip())
        scheme, host = parts.scheme.lower(), (parts.hostname or "").lower()
        port = parts.port or _DEFAULT_PORTS.get(scheme)
    except ValueError:
        return None
    if scheme not in _DEFAULT_PORTS or not host or port is None or parts.path not in ("", "/"):
        return None
    return scheme, host, port


def _named_here(host: str) -> bool:
    """A loopback name or an IP address: no other site's page can be served under it."""
    if host == "localhost" or host.endswith(".localhost"):
        return True
    try:
        ipaddress.ip_address(host.strip("[]"))
    except ValueError:
        return False
    return True


def foreign_origin(origin: str | None, host: str, allowed: list[str], keyless: bool) -> bool:
    """Whether a request (a write or a stream's handshake) is a web page's that may not
    make it: see the module's docstring."""
    if origin is None or not keyless:
        return False
    page = site(origin)
    if page is None:  # "null" (a file:// page, a sandboxed frame) or unreadable
        return True
    if page in {site(a) for a in allowed}:
        return False
    served = site(f"{page[0]}://{host}")  # the Host the browser sent, under its scheme
    return served is None or served[1:] != page[1:] or not _named_here(page[1])


def cross_origin(origin: str) -> Forbidden:
    return Forbidden(
        f"a write or stream from a web page ({origin[:100]}) is refused on a service without "
        "keys; allowed: programs (no Origin), this service's own pages under a loopback name "
        "or an IP address, and the origins in auth.allowed_origins",
        code="cross_origin",
    )
