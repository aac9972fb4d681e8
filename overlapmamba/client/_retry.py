"""How the clients read an answer and when they try a call again: the retry settings, a
server's error as an exception, what a lost answer may have done, and which failures are
worth another try."""

from __future__ import annotations

import dataclasses
import email.utils
import math
import random
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

import httpx

from overlapmamba.client._base import Call
from overlapmamba.client._exceptions import (
    APIError,
    ClientError,
    ConnectError,
    NotFoundError,
    ResponseError,
    Timeout,
    TransportError,
    error_for,
)
from overlapmamba.client._models import BatchInsertResult, Keyframe, ObserveResult


@dataclass(frozen=True)
class Retry:
    """Exponential backoff with jitter, for idempotent calls only (every call of these
    clients is: reads, PUT/DELETE, and inserts keyed by ``keyframe_id``). A server's
    ``Retry-After`` is honoured when it asks for longer, up to ``max_retry_after_s``: an
    answer asking for more (a proxy's hour, or ``inf``) is raised to the caller at once,
    rather than holding a robot's call that long."""

    attempts: int = 4  # total tries, including the first
    backoff_s: float = 0.25  # wait before the 2nd try; doubles each time
    max_backoff_s: float = 8.0
    jitter: float = 0.5  # ± this fraction of the wait, at random
    statuses: tuple[int, ...] = (429, 502, 503, 504)
    max_retry_after_s: float = 30.0

    def __post_init__(self) -> None:
        if self.attempts < 1:
            raise ValueError(
                f"Retry.attempts must be at least 1 (the first try); got {self.attempts}"
            )
        waits = {"backoff_s": self.backoff_s, "max_backoff_s": self.max_backoff_s}
        waits |= {"max_retry_after_s": self.max_retry_after_s}
        if bad := [f"{k}={v}" for k, v in waits.items() if not 0 <= v < math.inf]:
            raise ValueError(f"Retry waits must be finite seconds ≥ 0; got {', '.join(bad)}")
        if not 0 <= self.jitter <= 1:
            raise ValueError(f"Retry.jitter must lie in [0, 1]; got {self.jitter}")

    def delay(self, attempt: int, retry_after: float | None, rng: random.Random) -> float:
        base = min(self.max_backoff_s, self.backoff_s * 2 ** (attempt - 1))
        wait = base * (1 + self.jitter * (2 * rng.random() - 1))
        return max(wait, retry_after or 0.0)


NO_RETRY = Retry(attempts=1)


def _retry_after(resp: httpx.Response) -> float | None:
    """Retry-After in seconds: a number, or an HTTP date (as proxies send it)."""
    value = resp.headers.get("retry-after")
    if value is None:
        return None
    try:
        seconds = float(value)
    except ValueError:
        try:
            when = email.utils.parsedate_to_datetime(value)
        except (TypeError, ValueError, IndexError):
            return None
        if when.tzinfo is None:
            when = when.replace(tzinfo=UTC)
        seconds = (when - datetime.now(UTC)).total_seconds()
    return None if math.isnan(seconds) else max(seconds, 0.0)


# 503s that waiting will not mend: they wait on an operator (storage_full: a full disk;
# start_failed: a service that must be restarted), so they are raised at once
NOT_RETRIED = frozenset({"storage_full", "start_failed"})


def raise_for(resp: httpx.Response) -> None:
    """Raise the answer's error; a redirect (3xx: httpx does not follow one, e.g. a proxy
    sending http to https) is an error too, naming where it points."""
    if 300 <= resp.status_code < 400:
        where = resp.headers.get("location", "nowhere given")
        raise error_for(resp.status_code)(
            resp.status_code,
            "redirect",
            f"the server redirects to {where}: point the client at that URL",
            {"location": where},
        )
    if resp.status_code < 400:
        return
    try:
        err = resp.json()["error"]
        code, message, detail = err["code"], err["message"], err.get("detail") or {}
    except (ValueError, KeyError, TypeError):  # a proxy's page, or not this service at all
        kind = resp.headers.get("content-type", "no content-type")
        head = resp.content[:200].decode("utf-8", "replace")
        message = (
            f"{resp.reason_phrase or 'error'}, without the service's JSON error ({kind}): is "
            "the URL the place-recognition service's, or did a proxy in front of it answer?"
            + (f" The body began: {head!r}" if head else "")
        )
        code, detail = "http_error", {}
    raise error_for(resp.status_code)(
        resp.status_code, code, message, detail, retry_after=_retry_after(resp)
    )


def answered(call: Call, resp: httpx.Response) -> bool:
    """Whether ``resp`` is the call's answer, an error status the call reads as one (the
    readiness's 503 with its status and stage) included; else :func:`raise_for` raises it.
    Such a status with the API's error body, or with none (a proxy's), is an error still."""
    if resp.status_code not in call.answers:
        return False
    try:
        body = resp.json()
    except ValueError:
        return False
    return isinstance(body, dict) and "status" in body and "error" not in body


def transport_error(err: httpx.TransportError) -> TransportError:
    if isinstance(err, httpx.TimeoutException):
        return Timeout(f"no answer in time: {err!r}")
    if isinstance(err, httpx.ConnectError):
        return ConnectError(f"cannot connect: {err}")
    return TransportError(f"transport failed: {err!r}")


def read_answer(call: Call, resp: httpx.Response) -> Any:
    """``call.parse(resp)``; a 2xx body that is not this API's answer (an HTML page from a
    proxy, ``{}``, a body cut short) raises :class:`ResponseError` naming what came."""
    try:
        return call.parse(resp)
    except (ValueError, KeyError, TypeError, IndexError, AttributeError) as err:
        raise not_this_api(call, resp, err) from err


def not_this_api(call: Call, resp: httpx.Response | None, err: Exception) -> ResponseError:
    where = f"{call.method} {call.path}"
    if resp is None:  # the body could not even be decoded (a bad content-encoding)
        return ResponseError(f"{where}: the answer's body could not be decoded: {err}")
    kind = resp.headers.get("content-type", "no content-type")
    head = resp.content[:200].decode("utf-8", "replace")
    return ResponseError(
        f"{where} answered {resp.status_code} ({kind}) with a body that is not this API's "
        f"answer ({type(err).__name__}: {err}); expected the service's JSON. Is the URL the "
        f"place-recognition service's? The body began: {head!r}"
    )


def may_have_applied(err: ClientError) -> bool:
    """Whether the request that failed so may have been carried out all the same: its answer
    was lost (connected, then no answer), or the server failed after taking it (5xx but
    503, which refuses before any work)."""
    if isinstance(err, TransportError):  # these never sent the request
        never_sent = (
            httpx.ConnectError,
            httpx.ConnectTimeout,
            httpx.PoolTimeout,
            httpx.UnsupportedProtocol,
        )
        return not isinstance(err.__cause__, never_sent)
    return isinstance(err, APIError) and err.status >= 500 and err.status != 503


def mark_retried(answer: Any, maybe_applied: bool) -> Any:
    """An insert's or an observation's answer to a retry after a try that may have been
    carried out (its answer lost): ``retried`` set, so "existing" is read as what it may be,
    that earlier try's own insert."""
    if maybe_applied and isinstance(answer, Keyframe | ObserveResult | BatchInsertResult):
        return dataclasses.replace(answer, retried=True)
    return answer


def deleted_before(call: Call, err: ClientError, maybe_applied: bool) -> bool:
    """A DELETE retried after a try that may have been carried out answers 404: that
    earlier try deleted it, and the deletion the caller asked for has happened."""
    return call.method == "DELETE" and maybe_applied and isinstance(err, NotFoundError)


def retryable(err: Exception, retry: Retry) -> bool:
    if isinstance(err, TransportError):  # but a URL or a header that can never be sent
        return not isinstance(err.__cause__, httpx.UnsupportedProtocol | httpx.LocalProtocolError)
    if not (isinstance(err, APIError) and err.status in retry.statuses):
        return False
    if err.code in NOT_RETRIED:
        return False
    return err.retry_after is None or err.retry_after <= retry.max_retry_after_s
