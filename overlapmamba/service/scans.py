"""A scan as it came over the wire (:class:`ScanBody`) → points, with every limit checked
before the memory is spent. No HTTP here: :mod:`overlapmamba.service.bodies` reads request bodies
into these, the scan pipeline decodes them.

    decompress(body, encoding, max)   Content-Encoding (gzip | zstd | identity), bounded
    scan_format(content_type)         the codec a media type names
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

from overlapmamba.core.io import FIELD_LAYOUTS, decode
from overlapmamba.core.points import PointCloud, PointLimits
from overlapmamba.core.sensors.mount import Mount
from overlapmamba.service.errors import BadRequest, PayloadTooLarge, UnsupportedMediaType
from overlapmamba.service.settings import LimitSettings

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
    sensor: str | None = None  # the sensor it names (overlapmamba.service.sensors); None: its map's
    mount: Mount | None = None  # where that sensor sits (the `mount` parameter); None: as is


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
    point_limits = PointLimits(
        min_points=limits.min_points,
        max_points=limits.max_points,
        max_bytes=limits.max_decoded_bytes,
    )
    return decode(body, fmt, fields=layout, limits=point_limits, source=scan.source)
