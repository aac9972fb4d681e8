"""One exception tree for the service; each error knows its HTTP status.

    ServiceError                         500 unless a subclass says otherwise
     ├── BadRequest                      400  malformed parameters, pose strings, JSON
     │    └── UnsupportedMediaType       415  a content type or encoding we do not read
     ├── Unauthorized                    401  no API key, or an unknown one
     ├── Forbidden                       403  a key whose role (or map list) does not allow it
     ├── NotFound                        404  unknown map or keyframe
     ├── Conflict                        409  same keyframe id, different content; model mismatch
     ├── PayloadTooLarge                 413  body or decompressed body over the limit
     ├── Unprocessable                   422  well-formed input with invalid values
     ├── Overloaded                      503  the encode queue is full (with Retry-After)
     ├── NotReady                        503  the model or the map indexes are still loading
     ├── Unavailable                     503  a map whose files could not be opened
     └── Timeout                         504  the request ran past its deadline

Shared-core errors (:mod:`overlapmamba.core.errors`) are mapped in :mod:`overlapmamba.service.app`:
undecodable bodies → 400, non-finite points and point counts → 422 (too many points → 413). Every
response body is ``{"error": {"code", "message", "detail"}}``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from overlapmamba.core.errors import LidarCoreError, PointCountError


class ServiceError(Exception):
    status = 500
    code = "internal_error"

    def __init__(self, message: str, *, code: str | None = None, **detail: Any) -> None:
        super().__init__(message)
        self.message = message
        if code is not None:
            self.code = code
        self.detail: dict[str, Any] = detail
        self.headers: dict[str, str] = {}


class BadRequest(ServiceError):
    status = 400
    code = "bad_request"


class UnsupportedMediaType(BadRequest):
    status = 415
    code = "unsupported_media_type"


class Unauthorized(ServiceError):
    status = 401
    code = "unauthorized"


class Forbidden(ServiceError):
    status = 403
    code = "forbidden"


class NotFound(ServiceError):
    status = 404
    code = "not_found"


class Conflict(ServiceError):
    status = 409
    code = "conflict"


class PayloadTooLarge(ServiceError):
    status = 413
    code = "payload_too_large"


class Unprocessable(ServiceError):
    status = 422
    code = "unprocessable"


def invalid_request(errors: Sequence[Any]) -> Unprocessable:
    """Pydantic's errors of a request's parameters or body as the 422 ``invalid_request``:
    the first three named in the message, all of them in ``errors``."""
    found = [{"loc": list(e["loc"]), "msg": e["msg"], "type": e["type"]} for e in errors]
    where = ", ".join(".".join(str(p) for p in e["loc"]) + f": {e['msg']}" for e in found[:3])
    return Unprocessable(f"invalid request: {where}", code="invalid_request", errors=found)


class Overloaded(ServiceError):
    status = 503
    code = "overloaded"

    def __init__(self, message: str, *, retry_after_s: int = 1, **detail: Any) -> None:
        super().__init__(message, retry_after_s=retry_after_s, **detail)
        self.headers["Retry-After"] = str(retry_after_s)


class NotReady(ServiceError):
    status = 503
    code = "not_ready"

    def __init__(self, message: str, **detail: Any) -> None:
        super().__init__(message, **detail)
        self.headers["Retry-After"] = "1"


class Unavailable(ServiceError):
    """503: a part the answer needs is down, full or busy. Every 503 says when to come back
    (Retry-After), so a client backs off by the server's word, not its own guess."""

    status = 503
    code = "unavailable"

    def __init__(self, message: str, *, retry_after_s: int = 1, **detail: Any) -> None:
        super().__init__(message, **detail)
        self.headers["Retry-After"] = str(retry_after_s)


class Timeout(ServiceError):
    status = 504
    code = "timeout"


def error_body(code: str, message: str, detail: dict[str, Any] | None = None) -> dict[str, Any]:
    return {"error": {"code": code, "message": message, "detail": detail or {}}}


def lidar_status(err: LidarCoreError) -> int:
    """The HTTP status of a scan the core library refused: 413 too many points, 422 values
    out of range, else 400 (over HTTP and in the stream's error frames)."""
    if isinstance(err, PointCountError) and err.detail.get("points", 0) > err.detail.get(
        "max_points", float("inf")
    ):
        return 413
    if err.code == "decoded_too_large":
        return 413
    return 422 if err.code in ("non_finite_points", "point_count_out_of_range") else 400
