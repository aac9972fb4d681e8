"""One exception tree for the clients.

ClientError
 ├── TransportError          the request did not get an answer
 │    ├── ConnectError        could not connect
 │    └── Timeout             no answer in time (see ``Timeouts``)
 ├── ResponseError           a 2xx answer that is not this API's (a proxy's or another
 │                           service's page, a body cut short): what came is named
 └── APIError                the service answered with an error; ``status``, ``code``,
      │                      ``message`` and ``detail`` are the server's
      ├── BadRequestError     4xx not listed below
      ├── AuthError           401, 403
      ├── NotFoundError       404
      ├── ConflictError       409
      ├── PayloadTooLargeError 413
      ├── OverloadedError     429, 503 — ``retry_after`` seconds, from Retry-After
      └── ServerError         5xx other than 503
"""

from __future__ import annotations

from typing import Any


class ClientError(Exception):
    pass


class TransportError(ClientError):
    pass


class ConnectError(TransportError):
    pass


class Timeout(TransportError):
    pass


class ResponseError(ClientError):
    """A success status whose body is not what this API answers."""


class APIError(ClientError):
    def __init__(
        self,
        status: int,
        code: str,
        message: str,
        detail: dict[str, Any] | None = None,
        *,
        retry_after: float | None = None,
    ) -> None:
        super().__init__(f"{status} {code}: {message}")
        self.status = status
        self.code = code
        self.message = message
        self.detail = detail or {}
        self.retry_after = retry_after


class BadRequestError(APIError):
    pass


class AuthError(APIError):
    pass


class NotFoundError(APIError):
    pass


class ConflictError(APIError):
    pass


class PayloadTooLargeError(APIError):
    pass


class OverloadedError(APIError):
    pass


class ServerError(APIError):
    pass


def error_for(status: int) -> type[APIError]:
    if status in (429, 503):
        return OverloadedError
    if status >= 500:
        return ServerError
    return {
        401: AuthError,
        403: AuthError,
        404: NotFoundError,
        409: ConflictError,
        413: PayloadTooLargeError,
    }.get(status, BadRequestError)
