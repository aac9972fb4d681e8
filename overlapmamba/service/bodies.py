"""HTTP request bodies → bytes, with every size limit checked before the memory is spent.

read_body(request, limits)        Content-Length and the streamed size against
                                  max_body_bytes (413), then Content-Encoding
                                  (gzip | zstd | identity) bounded by max_decoded_bytes
parse_json(body, Model, what)     a JSON body as ``Model``, or 422 naming the fields wrong
read_scan(request, limits, fields)
                                  the same size checks → a
                                  :class:`~overlapmamba.service.scans.ScanBody`,
                                  still encoded: its decompression belongs to the scan's
                                  decode stage (:func:`overlapmamba.service.scans.decode_scan`)
"""

from __future__ import annotations

import json
from typing import TypeVar

from fastapi import Request
from pydantic import BaseModel, ValidationError

from overlapmamba.core.sensors.mount import Mount
from overlapmamba.service.errors import BadRequest, PayloadTooLarge, Unprocessable
from overlapmamba.service.scans import ScanBody, decompress
from overlapmamba.service.settings import LimitSettings
from overlapmamba.service.threads import in_thread


async def read_body(request: Request, limits: LimitSettings) -> bytes:
    """The decoded request body. 413 as soon as a limit is crossed, before reading the rest."""
    body = await _read_raw(request, limits)
    encoding = request.headers.get("content-encoding")
    if encoding is None or encoding.strip().lower() == "identity":
        return body
    return await in_thread(decompress, body, encoding, limits.max_decoded_bytes)


async def read_scan(
    request: Request,
    limits: LimitSettings,
    fields: str | None,
    sensor: str | None = None,
    mount: str | None = None,
) -> ScanBody:
    """The scan body as sent (size-checked, not yet decompressed or decoded), with the sensor
    the request names and where it sits."""
    declared = parse_mount(mount)
    return ScanBody(
        await _read_raw(request, limits),
        request.headers.get("content-type"),
        fields,
        request.headers.get("content-encoding"),
        sensor=sensor,
        mount=declared,
    )


M = TypeVar("M", bound=BaseModel)


def parse_json(body: bytes, model: type[M], what: str) -> M:
    """``body`` as ``model``; else 422 ``invalid_request`` naming the first fields wrong
    (``what``: the body's name, "map settings")."""
    try:
        return model.model_validate_json(body)
    except ValidationError as err:
        errors = json.loads(err.json(include_url=False, include_input=False))
        where = "; ".join(".".join(str(p) for p in e["loc"]) + f": {e['msg']}" for e in errors[:3])
        raise Unprocessable(
            f"invalid {what}: {where}", code="invalid_request", errors=errors
        ) from None


def parse_mount(text: str | None) -> Mount | None:
    """The ``mount`` parameter (``HEIGHT[,PITCH[,ROLL]]``), or a 400 naming what is allowed."""
    if text is None:
        return None
    try:
        return Mount.parse(text)
    except (ValueError, ValidationError) as err:
        reason = err.errors()[0]["msg"] if isinstance(err, ValidationError) else str(err)
        raise BadRequest(
            f"mount {text!r} is not allowed ({reason}); give HEIGHT[,PITCH[,ROLL]]: a height "
            "above the ground in (0, 10] m, pitch and roll within ±45°",
            code="bad_mount",
        ) from None


async def _read_raw(request: Request, limits: LimitSettings) -> bytes:
    length = request.headers.get("content-length")
    if length is not None:
        try:
            declared = int(length)
        except ValueError:
            raise BadRequest(f"Content-Length {length!r} is not an integer") from None
        if declared > limits.max_body_bytes:
            raise PayloadTooLarge(
                f"body is {declared} bytes; allowed: at most {limits.max_body_bytes}",
                bytes=declared,
                max_body_bytes=limits.max_body_bytes,
            )
    chunks: list[bytes] = []
    size = 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limits.max_body_bytes:
            raise PayloadTooLarge(
                f"body exceeds {limits.max_body_bytes} bytes", max_body_bytes=limits.max_body_bytes
            )
        chunks.append(chunk)
    return b"".join(chunks)
