"""Request bodies → bytes → points, with every limit checked before the memory is spent.

    read_body(request, limits)        Content-Length and the streamed size against
                                      max_body_bytes (413), then Content-Encoding
                                      (gzip | zstd | identity) bounded by max_decoded_bytes
    read_scan(request, limits, fields)
                                      the same size checks → a ScanBody, still encoded: its
                                      decompression belongs to the scan's decode stage
    decode_scan(scan, limits)         Content-Encoding undone, then application/octet-stream
                                      (X-Point-Fields xyzi | xyz), application/x-npy,
                                      application/x-pcd, application/x-ros2-pointcloud2
                                      → PointCloud

A decompression bomb is stopped at max_decoded_bytes + 1 bytes of output: the decoders are
asked for at most that much, never for "everything".
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import zstandard
from fastapi import Request
from starlette.concurrency import run_in_threadpool

from lidar_core.io import FIELD_LAYOUTS, decode
from lidar_core.points import PointCloud, PointLimits
from service.errors import BadRequest, PayloadTooLarge, UnsupportedMediaType
from service.settings import LimitSettings

SCAN_TYPES = {
    "application/octet-stream": "raw",
    "application/x-npy": "npy",
    "application/x-pcd": "pcd",
    # a CDR-serialized sensor_msgs/msg/PointCloud2, the bytes a ROS 2 node receives
    "application/x-ros2-pointcloud2": "pointcloud2",
}
ENCODINGS = ("identity", "gzip", "zstd")


@dataclass(frozen=True)
class ScanBody:
    """One scan as it came over the wire: bytes in a media type, maybe compressed."""

    data: bytes
    content_type: str | None
    fields: str | None = None  # X-Point-Fields for raw float32 bodies
    encoding: str | None = None  # Content-Encoding, undone by decode_scan
    source: str = "scan"  # how errors name it ("scan 3" in a batch)


async def read_body(request: Request, limits: LimitSettings) -> bytes:
    """The decoded request body. 413 as soon as a limit is crossed, before reading the rest."""
    body = await _read_raw(request, limits)
    encoding = request.headers.get("content-encoding")
    if encoding is None or encoding.strip().lower() == "identity":
        return body
    return await run_in_threadpool(decompress, body, encoding, limits.max_decoded_bytes)


async def read_scan(request: Request, limits: LimitSettings, fields: str | None) -> ScanBody:
    """The scan body as sent (size-checked, not yet decompressed or decoded)."""
    return ScanBody(
        await _read_raw(request, limits),
        request.headers.get("content-type"),
        fields,
        request.headers.get("content-encoding"),
    )


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


def decompress(body: bytes, encoding: str | None, max_bytes: int) -> bytes:
    enc = (encoding or "identity").strip().lower()
    if enc == "identity":
        return body
    if enc == "gzip":
        d = zlib.decompressobj(16 + zlib.MAX_WBITS)
        try:
            out = d.decompress(body, max_bytes + 1)
        except zlib.error as err:
            raise BadRequest(f"gzip body does not decompress: {err}") from None
        if len(out) > max_bytes or d.unconsumed_tail:
            raise _bomb(max_bytes)
        if not d.eof:
            raise BadRequest("gzip body is truncated")
        if d.unused_data:
            raise BadRequest("gzip body has data after its end; allowed: one gzip member")
        return out
    if enc == "zstd":
        try:
            declared = zstandard.frame_content_size(body)
        except zstandard.ZstdError as err:
            raise BadRequest(f"zstd body does not decompress: {err}") from None
        if declared > max_bytes:  # the header says so: refuse before allocating anything
            raise _bomb(max_bytes)
        if declared < 0 and _zstd_exceeds(body, max_bytes):  # a streamed frame: no size
            raise _bomb(max_bytes)
        try:
            # One frame, nothing after it; an unknown size is capped at max_bytes.
            return zstandard.ZstdDecompressor().decompress(
                body, max_output_size=max_bytes, allow_extra_data=False
            )
        except zstandard.ZstdError as err:
            why = "truncated, or larger than the limit" if "full frame" in str(err) else err
            raise BadRequest(
                f"zstd body does not decompress ({why}); allowed: one zstd frame of at most "
                f"{max_bytes} bytes",
                max_decoded_bytes=max_bytes,
            ) from None
    raise UnsupportedMediaType(
        f"Content-Encoding {encoding!r} is not supported; allowed: {', '.join(ENCODINGS)}",
        allowed=list(ENCODINGS),
    )


def _zstd_exceeds(body: bytes, max_bytes: int) -> bool:
    """Whether a frame of undeclared size decompresses to more than max_bytes: counted in
    1 MB pieces, never held whole. (Truncation and garbage are left to the strict pass.)"""
    total = 0
    try:
        with zstandard.ZstdDecompressor().stream_reader(body, read_across_frames=False) as r:
            while piece := r.read(1 << 20):
                total += len(piece)
                if total > max_bytes:
                    return True
    except zstandard.ZstdError:
        return False
    return False


def _bomb(max_bytes: int) -> PayloadTooLarge:
    return PayloadTooLarge(
        f"body decompresses to more than {max_bytes} bytes", max_decoded_bytes=max_bytes
    )


def scan_format(content_type: str | None) -> str:
    media = (content_type or "").split(";")[0].strip().lower()
    if media not in SCAN_TYPES:
        raise UnsupportedMediaType(
            f"content type {media or '(none)'!r} is not a scan format; allowed: "
            f"{', '.join(SCAN_TYPES)} (never a JSON list of floats)",
            allowed=list(SCAN_TYPES),
        )
    return SCAN_TYPES[media]


def decode_scan(scan: ScanBody, limits: LimitSettings) -> PointCloud:
    """Blocking: run it off the event loop."""
    fmt = scan_format(scan.content_type)
    layout = (scan.fields or "xyzi").strip().lower()
    if fmt == "raw" and layout not in FIELD_LAYOUTS:
        raise BadRequest(
            f"X-Point-Fields {scan.fields!r} is not supported; allowed: {', '.join(FIELD_LAYOUTS)}",
            allowed=list(FIELD_LAYOUTS),
        )
    body = decompress(scan.data, scan.encoding, limits.max_decoded_bytes)
    point_limits = PointLimits(min_points=limits.min_points, max_points=limits.max_points)
    return decode(body, fmt, fields=layout, limits=point_limits, source=scan.source)
