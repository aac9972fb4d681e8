"""Optional API keys with one role each.

    robot    descriptors, query, observe, stream; keyframe inserts into its allowed maps
             (``maps``); with ``query_maps``, it queries only those and its ``maps``
    mapper   robot's rights on every map, plus keyframe batches, reads, deletes, map management
    viewer   stats, metrics, dashboard (read-only)
    admin    everything

Keys arrive as ``Authorization: Bearer <key>``, ``X-API-Key: <key>``, or HTTP Basic with the
key as password (so a browser can open ``/dashboard``). Only SHA-256 hashes are configured
(``overlapmamba hash-key``); the presented key's hash is compared with every configured hash
in constant time, and all of them are always compared, so timing says nothing about which
one nearly matched. With no keys configured, everyone is admin — and
:meth:`~overlapmamba.service.settings.Settings.check_binding` keeps such a service on loopback.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import secrets
from dataclasses import dataclass
from enum import StrEnum

from fastapi import Request

from overlapmamba.service.errors import Forbidden, Unauthorized
from overlapmamba.service.settings import ApiKey, AuthSettings


class Action(StrEnum):
    ENCODE = "encode"  # descriptors, query, observe, stream
    INSERT = "insert"  # keyframe insert with a scan (robots: allowed maps only)
    MAP_WRITE = "map_write"  # keyframe batches, deletes, snapshots, map create/delete
    MAP_READ = "map_read"  # map list/info, keyframe get
    VIEW = "view"  # stats, metrics, dashboard


ROLE_ACTIONS: dict[str, frozenset[Action]] = {
    "robot": frozenset({Action.ENCODE, Action.INSERT}),
    "mapper": frozenset({Action.ENCODE, Action.INSERT, Action.MAP_WRITE, Action.MAP_READ}),
    "viewer": frozenset({Action.VIEW}),
    "admin": frozenset(Action),
}


def hash_key(key: str) -> str:
    return hashlib.sha256(key.encode()).hexdigest()


def new_key() -> str:
    return "om_" + secrets.token_urlsafe(32)


@dataclass(frozen=True)
class Principal:
    name: str
    role: str
    maps: list[str] | None = None
    query_maps: list[str] | None = None

    def may_query(self, map_id: str) -> bool:
        """A robot key with ``query_maps`` queries only those maps and the ones it may insert
        into; any other key, any map."""
        if self.role != "robot" or self.query_maps is None:
            return True
        return map_id in self.query_maps or map_id in (self.maps or ())


ANONYMOUS_ADMIN = Principal(name="anonymous", role="admin")
_READS = ("GET", "HEAD")


def presented_key(request: Request) -> str | None:
    """The key a request presents: ``Authorization: Bearer``, ``X-API-Key``, or HTTP Basic's
    password. Basic is what a browser resends by itself once the dashboard's login was
    given, to any page's request to this address: it is taken only to read (GET, HEAD),
    never for a write or a stream, which another site's page could make that browser send
    (cross-site request forgery)."""
    header = request.headers.get("authorization", "")
    scheme, _, value = header.partition(" ")
    if scheme.lower() == "bearer" and value.strip():
        return value.strip()
    if scheme.lower() == "basic" and value.strip():
        if request.scope.get("type") != "http" or request.scope.get("method") not in _READS:
            auth = getattr(request.app.state, "auth", None)
            if auth is None or not auth.enabled:  # no keys: nothing is checked anyway
                return None
            raise Unauthorized(
                "HTTP Basic credentials are taken only to read (the dashboard's GETs); "
                "send the key as 'Authorization: Bearer <key>' or 'X-API-Key'",
                code="basic_not_allowed",
            )
        try:
            decoded = base64.b64decode(value.strip(), validate=True).decode()
        except ValueError:  # binascii.Error, UnicodeDecodeError and non-ASCII input
            return None
        _, _, password = decoded.partition(":")
        return password or None
    return request.headers.get("x-api-key") or None


class Authenticator:
    def __init__(self, settings: AuthSettings) -> None:
        self.keys: list[ApiKey] = list(settings.keys)

    @property
    def enabled(self) -> bool:
        return bool(self.keys)

    def identify(self, key: str | None) -> Principal:
        if not self.enabled:
            return ANONYMOUS_ADMIN
        if not key:
            raise Unauthorized(
                "an API key is required: send 'Authorization: Bearer <key>' or 'X-API-Key'",
                code="missing_api_key",
            )
        digest = hash_key(key).encode()
        found: ApiKey | None = None
        for k in self.keys:  # every hash is compared: no early exit
            if hmac.compare_digest(digest, k.sha256.encode()):
                found = k
        if found is None:
            raise Unauthorized("the API key is not valid", code="invalid_api_key")
        return Principal(
            name=found.name, role=found.role, maps=found.maps, query_maps=found.query_maps
        )

    def authorize(self, who: Principal, action: Action, map_id: str | None = None) -> None:
        if action not in ROLE_ACTIONS[who.role]:
            allowed = sorted(r for r, acts in ROLE_ACTIONS.items() if action in acts)
            raise Forbidden(
                f"key {who.name!r} has role {who.role!r}, which may not {action.value}; "
                f"allowed roles: {', '.join(allowed)}",
                code="wrong_role",
                role=who.role,
                allowed_roles=allowed,
            )
        if (
            action is Action.INSERT
            and who.role == "robot"
            and who.maps is not None
            and map_id not in who.maps
        ):
            raise Forbidden(
                f"key {who.name!r} may insert into maps {who.maps}, not {map_id!r}",
                code="map_not_allowed",
                allowed_maps=who.maps,
            )
        if action is Action.ENCODE and map_id is not None and not who.may_query(map_id):
            allowed = sorted({*(who.query_maps or ()), *(who.maps or ())})
            raise Forbidden(
                f"key {who.name!r} may query maps {allowed}, not {map_id!r}",
                code="map_not_allowed",
                allowed_maps=allowed,
            )
