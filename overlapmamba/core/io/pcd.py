"""PCD scans (ascii, binary, binary_compressed) through pypcd4.

pypcd4 trusts the header; we check it first — declared point count, the fields we need, and
for ``binary_compressed`` the declared uncompressed size — so a hostile header cannot make
it allocate gigabytes (a decompression bomb) or silently return fewer points than declared.
"""

from __future__ import annotations

import io
import struct
import warnings

import numpy as np
from pypcd4 import PointCloud as PcdCloud
from pypcd4.pypcd4 import MetaData

from overlapmamba.core.errors import DataTooLargeError, DecodeError
from overlapmamba.core.points import DEFAULT_LIMITS, PointCloud, PointLimits, validate

INTENSITY_FIELDS = ("intensity", "i")
DATA_ENCODINGS = ("ascii", "binary", "binary_compressed")
# The PCD v0.7 header has at most 10 entries (VERSION … DATA); pypcd4 stops reading at 10.
_MAX_HEADER_ENTRIES = 10
_MAX_HEADER_BYTES = 4096
# the whole header, blank and comment lines included (read line by line in Python)
_MAX_HEADER_TOTAL = 64 << 10
# a point's fields: pypcd4 makes one numpy field per element of a COUNT, in a Python loop
_MAX_ELEMENTS = 256
_MAX_RECORD_BYTES = 4096
# ascii rows past POINTS that may still be blank (a trailing newline or two)
_ASCII_SPARE_LINES = 16


def _read_header(buf: io.BytesIO, source: str) -> tuple[MetaData, list[str], int]:
    """Parse the header ourselves; return it, its cleaned lines and the data offset.

    pypcd4 is later handed exactly these lines, so it cannot read the header differently.
    """
    lines: list[str] = []
    while True:
        raw = buf.readline(_MAX_HEADER_BYTES + 1)
        if not raw:
            raise DecodeError(f"{source}: PCD header ends without a DATA line")
        if len(raw) > _MAX_HEADER_BYTES:
            raise DecodeError(f"{source}: PCD header line longer than {_MAX_HEADER_BYTES} bytes")
        if buf.tell() > _MAX_HEADER_TOTAL:
            raise DecodeError(
                f"{source}: PCD header runs past {_MAX_HEADER_TOTAL} bytes (blank and comment "
                "lines included) without a DATA line"
            )
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError as err:
            raise DecodeError(f"{source}: PCD header is not ASCII text") from err
        if not line or line.startswith("#"):
            continue
        lines.append(line)
        if line.startswith("DATA"):
            break
        if len(lines) >= _MAX_HEADER_ENTRIES:
            raise DecodeError(
                f"{source}: PCD header has no DATA line in its first {_MAX_HEADER_ENTRIES} "
                "entries (VERSION, FIELDS, SIZE, TYPE, COUNT, WIDTH, HEIGHT, VIEWPOINT, POINTS, "
                "DATA)"
            )
    encoding = lines[-1].split()[1:]
    if encoding not in ([e] for e in DATA_ENCODINGS):
        raise DecodeError(
            f"{source}: PCD 'DATA {' '.join(encoding)}' is not supported; allowed: "
            f"{', '.join(DATA_ENCODINGS)}",
            allowed=list(DATA_ENCODINGS),
        )
    try:
        meta = MetaData.parse_header(lines)
    except Exception as err:  # pydantic.ValidationError, ValueError on junk numbers
        raise DecodeError(f"{source}: malformed PCD header: {_short(err)}") from err
    n = len(meta.fields)
    if not (len(meta.size) == len(meta.type) == len(meta.count) == n):
        raise DecodeError(
            f"{source}: PCD header lists {n} FIELDS but {len(meta.size)} SIZE, "
            f"{len(meta.type)} TYPE and {len(meta.count)} COUNT entries"
        )
    if meta.points != meta.width * meta.height:
        raise DecodeError(
            f"{source}: PCD header declares POINTS {meta.points} but WIDTH×HEIGHT is "
            f"{meta.width * meta.height}"
        )
    return meta, lines, buf.tell()


def _short(err: Exception) -> str:
    return str(err).splitlines()[0][:200]


def decode_pcd(
    data: bytes | bytearray | memoryview,
    *,
    limits: PointLimits = DEFAULT_LIMITS,
    source: str = "scan",
) -> PointCloud:
    buf = io.BytesIO(data)
    meta, lines, offset = _read_header(buf, source)
    missing = [f for f in ("x", "y", "z") if f not in meta.fields]
    if missing:
        raise DecodeError(
            f"{source}: PCD has fields {list(meta.fields)}; required: x, y, z "
            f"(optional intensity); missing {missing}"
        )
    for name, size, typ, count in zip(meta.fields, meta.size, meta.type, meta.count, strict=True):
        if name in ("x", "y", "z") and (typ != "F" or count != 1):
            raise DecodeError(
                f"{source}: PCD field {name} is TYPE {typ} COUNT {count}; allowed: F with COUNT 1"
            )
        if name in INTENSITY_FIELDS and count != 1:
            raise DecodeError(f"{source}: PCD field {name} has COUNT {count}; allowed: 1")
        if (typ == "F" and size not in (4, 8)) or (typ in "UI" and size not in (1, 2, 4, 8)):
            raise DecodeError(f"{source}: PCD field {name} has unsupported SIZE {size}")
    limits.check_count(meta.points, source=source)
    elements = sum(meta.count)
    declared = sum(size * count for size, count in zip(meta.size, meta.count, strict=True))
    if elements > _MAX_ELEMENTS or declared > _MAX_RECORD_BYTES:
        raise DecodeError(
            f"{source}: PCD point has {elements} values in {declared} bytes (COUNT "
            f"{' '.join(map(str, meta.count))}); allowed: at most {_MAX_ELEMENTS} values and "
            f"{_MAX_RECORD_BYTES} bytes a point"
        )
    try:
        record = meta.build_dtype().itemsize
    except Exception as err:
        raise DecodeError(f"{source}: PCD field types are invalid: {_short(err)}") from err
    body = len(data) - offset
    encoding = meta.data.value
    # Short data is a cut body; a whole point or more past POINTS means POINTS (or
    # WIDTH × HEIGHT) is wrong, and reading the first POINTS would lose the rest unseen.
    if encoding == "binary" and not meta.points * record <= body < (meta.points + 1) * record:
        raise DecodeError(
            f"{source}: PCD declares {meta.points} points ({meta.points * record} bytes) "
            f"but holds {body} bytes of data"
            + ("; is POINTS right?" if body > meta.points * record else "")
        )
    if encoding == "binary_compressed" and meta.points * record > limits.max_bytes:
        raise DataTooLargeError(
            f"{source}: binary_compressed PCD declares {meta.points} points of {record} bytes "
            f"({meta.points * record} bytes once inflated); allowed: at most "
            f"{limits.max_bytes} bytes",
            max_bytes=limits.max_bytes,
        )
    if encoding == "ascii":  # every row is parsed: count them first (in C), not after
        rows = bytes(memoryview(data)[offset:]).count(b"\n")
        if rows > meta.points + _ASCII_SPARE_LINES:
            raise DecodeError(
                f"{source}: ascii PCD declares {meta.points} points but its data holds {rows} lines"
            )
    if encoding == "binary_compressed":
        if body < 8:
            raise DecodeError(f"{source}: binary_compressed PCD lacks its size header")
        compressed, uncompressed = struct.unpack("<II", bytes(data[offset : offset + 8]))
        if uncompressed != meta.points * record or compressed > body - 8:
            raise DecodeError(
                f"{source}: binary_compressed PCD sizes are inconsistent (compressed "
                f"{compressed}, uncompressed {uncompressed}, expected uncompressed "
                f"{meta.points * record}, {body - 8} bytes present)"
            )
    try:
        clean = "\n".join(lines).encode() + b"\n" + bytes(memoryview(data)[offset:])
        with warnings.catch_warnings():
            # e.g. loadtxt's "input contained no data": the count check below reports it.
            warnings.simplefilter("ignore")
            pc = PcdCloud.from_fileobj(io.BytesIO(clean))  # type: ignore[arg-type]
        arr = np.atleast_1d(pc.pc_data)
    except Exception as err:  # lzf, numpy and pypcd4 raise a variety of types
        raise DecodeError(f"{source}: PCD data cannot be decoded: {_short(err)}") from err
    if arr.shape[0] != meta.points:
        raise DecodeError(
            f"{source}: PCD declares {meta.points} points but its data holds {arr.shape[0]}"
        )
    # float64 fields beyond float32's range become inf here; validate() reports them.
    with np.errstate(over="ignore"):
        xyz = np.stack([arr["x"], arr["y"], arr["z"]], axis=1).astype(np.float32)
        field = next((f for f in INTENSITY_FIELDS if f in meta.fields), None)
        intensity = None if field is None else np.asarray(arr[field], dtype=np.float32)
    if meta.height > 1:  # organised (a driver's image of rows): NaN points are missing returns
        keep = ~np.isnan(xyz).any(axis=1)
        if not keep.all():
            xyz = xyz[keep]
            intensity = None if intensity is None else intensity[keep]
    return validate(xyz, intensity, limits=limits, source=source)
