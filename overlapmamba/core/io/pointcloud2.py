"""ROS 2 ``sensor_msgs/msg/PointCloud2`` messages, CDR-serialized, as a ROS 2 node holds them
(``rclpy.serialization.serialize_message``, or the bytes a rosbag2 stores).

    encapsulation (4 bytes: CDR little or big endian)
    header    stamp (int32 sec, uint32 nanosec), frame_id (string)
    height, width                       uint32: an organised cloud has height > 1
    fields    sequence of PointField    name (string), offset (uint32), datatype (uint8),
                                        count (uint32)
    is_bigendian (bool), point_step, row_step (uint32)
    data      sequence<uint8>           height rows of row_step bytes, width points a row
    is_dense  (bool)

Every layout robots send decodes: x/y/z as float32 or float64, intensity (``intensity`` or
``i``, any numeric type) or none, a ``ring`` (any integer type: the beam a point came from,
kept beside the points so a named sensor can be checked against it), padding between fields
and at the end of a point or a row, organised or not, either byte order. Sizes are checked
against the bytes present before anything is allocated. A cloud that is not dense
(``is_dense`` false) may hold NaN (or infinite) points for missing returns: those are
dropped; a float64 coordinate past float32's range, or NaN in a cloud that says it is dense,
is an error. The fields the points are read from may each be declared once, in bytes of
their own.
Parsed here, without ROS: the message's layout is fixed (CDR, XCDR1 as ROS 2's default
middleware writes it), and a hand parser can name what is wrong with a malformed one.
"""

from __future__ import annotations

import struct
from dataclasses import replace
from typing import Any

import numpy as np

from overlapmamba.core.errors import DecodeError
from overlapmamba.core.points import DEFAULT_LIMITS, PointCloud, PointLimits, validate

# sensor_msgs/msg/PointField datatypes → numpy kinds (byte order added per message)
DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
INTEGERS = ("i1", "u1", "i2", "u2", "i4", "u4")
INTENSITY_FIELDS = ("intensity", "i")
MAX_FIELDS = 64  # real drivers send 4–12
MAX_NAME = 256


class _Reader:
    """CDR primitives: each aligned to its own size, counted from after the encapsulation."""

    def __init__(self, data: memoryview, little: bool, source: str) -> None:
        self.data, self.pos, self.source = data, 4, source
        self.order = "<" if little else ">"

    def _take(self, size: int, what: str, align: int = 1) -> memoryview:
        self.pos += (-(self.pos - 4)) % align  # a primitive starts at a multiple of its size
        end = self.pos + size
        if end > len(self.data):
            raise DecodeError(
                f"{self.source}: PointCloud2 message ends inside its {what} (byte {self.pos} "
                f"of {len(self.data)})",
                field=what,
            )
        out, self.pos = self.data[self.pos : end], end
        return out

    def u32(self, what: str) -> int:
        return int(struct.unpack(self.order + "I", self._take(4, what, 4))[0])

    def i32(self, what: str) -> int:
        return int(struct.unpack(self.order + "i", self._take(4, what, 4))[0])

    def u8(self, what: str) -> int:
        return int(self._take(1, what)[0])

    def string(self, what: str, limit: int) -> str:
        n = self.u32(what)
        if n > limit:
            raise DecodeError(
                f"{self.source}: PointCloud2 {what} is {n} bytes long; allowed: at most {limit}",
                field=what,
            )
        raw = bytes(self._take(n, what)) if n else b""
        text = raw[:-1] if raw.endswith(b"\0") else raw
        try:
            return text.decode("utf-8")
        except UnicodeDecodeError:
            raise DecodeError(
                f"{self.source}: PointCloud2 {what} is not UTF-8", field=what
            ) from None

    def octets(self, what: str) -> memoryview:
        n = self.u32(what)
        return self._take(n, what)


def decode_pointcloud2(
    data: bytes | bytearray | memoryview,
    *,
    limits: PointLimits = DEFAULT_LIMITS,
    source: str = "scan",
) -> PointCloud:
    buf = memoryview(data).cast("B")
    if len(buf) < 4 or buf[0] != 0 or buf[1] not in (0, 1):
        raise DecodeError(
            f"{source}: not a CDR-serialized PointCloud2: the encapsulation header is "
            f"{bytes(buf[:4]).hex() or '(missing)'}; allowed: 00 01 (CDR little endian) or "
            f"00 00 (big endian)",
            field="encapsulation",
        )
    r = _Reader(buf, little=buf[1] == 1, source=source)
    r.i32("header.stamp.sec")
    r.u32("header.stamp.nanosec")
    r.string("header.frame_id", MAX_NAME)
    height, width = r.u32("height"), r.u32("width")
    n_fields = r.u32("fields")
    if n_fields > MAX_FIELDS:
        raise DecodeError(
            f"{source}: PointCloud2 declares {n_fields} fields; allowed: at most {MAX_FIELDS}",
            field="fields",
        )
    fields: dict[str, tuple[int, int, int]] = {}
    for k in range(n_fields):
        name = r.string(f"fields[{k}].name", MAX_NAME)
        offset = r.u32(f"fields[{k}].offset")
        datatype = r.u8(f"fields[{k}].datatype")
        count = r.u32(f"fields[{k}].count")
        _add_field(fields, name, (offset, datatype, count), source)
    big = r.u8("is_bigendian")
    point_step, row_step = r.u32("point_step"), r.u32("row_step")
    payload = r.octets("data")
    dense = r.u8("is_dense")
    for name, value in (("is_bigendian", big), ("is_dense", dense)):
        if value > 1:
            raise DecodeError(
                f"{source}: PointCloud2 {name} is {value}; allowed: 0 or 1", field=name
            )
    return _points(
        payload, fields, height, width, point_step, row_step, bool(big), bool(dense), limits, source
    )


def decode_message(
    msg: Any, *, limits: PointLimits = DEFAULT_LIMITS, source: str = "scan"
) -> PointCloud:
    """A PointCloud2 already deserialized — any object with the message's attributes, as a
    bag reader returns it (ROS 1 or ROS 2) — checked and decoded as above."""
    fields: dict[str, tuple[int, int, int]] = {}
    for f in list(msg.fields)[:MAX_FIELDS]:
        _add_field(fields, str(f.name), (int(f.offset), int(f.datatype), int(f.count)), source)
    return _points(
        np.ascontiguousarray(msg.data, dtype=np.uint8).data,  # a view: no copy
        fields,
        int(msg.height),
        int(msg.width),
        int(msg.point_step),
        int(msg.row_step),
        bool(msg.is_bigendian),
        bool(msg.is_dense),
        limits,
        source,
    )


_READ = ("x", "y", "z", *INTENSITY_FIELDS, "ring")


def _add_field(
    fields: dict[str, tuple[int, int, int]], name: str, field: tuple[int, int, int], source: str
) -> None:
    """A field of the message; one that the points are read from may be declared once (a
    second ``x`` would leave which one is meant to chance). Others (padding) may repeat."""
    if name in fields:
        if name in _READ:
            raise DecodeError(
                f"{source}: PointCloud2 field {name} is declared twice; allowed: once",
                field=name,
            )
        return
    fields[name] = field


def _points(
    payload: memoryview,
    fields: dict[str, tuple[int, int, int]],
    height: int,
    width: int,
    point_step: int,
    row_step: int,
    big: bool,
    dense: bool,
    limits: PointLimits,
    source: str,
) -> PointCloud:
    missing = [f for f in ("x", "y", "z") if f not in fields]
    if missing:
        raise DecodeError(
            f"{source}: PointCloud2 has fields {list(fields)}; required: x, y, z (optional "
            f"intensity); missing {missing}",
            field="fields",
        )
    order = ">" if big else "<"
    names: list[str] = []
    formats: list[str] = []
    offsets: list[int] = []
    sizes: list[int] = []
    intensity = next((f for f in INTENSITY_FIELDS if f in fields), None)
    ring = "ring" if "ring" in fields else None
    for name in ("x", "y", "z", *([intensity] if intensity else []), *([ring] if ring else [])):
        offset, datatype, count = fields[name]
        kind = DATATYPES.get(datatype)
        allowed = (
            ("f4", "f8")
            if name in "xyz"
            else INTEGERS
            if name == "ring"
            else tuple(DATATYPES.values())
        )
        if kind not in allowed or count != 1:
            raise DecodeError(
                f"{source}: PointCloud2 field {name} has datatype {datatype} and count {count}; "
                f"allowed: count 1 and "
                + (
                    "FLOAT32 (7) or FLOAT64 (8)"
                    if name in "xyz"
                    else "an integer datatype (1–6)"
                    if name == "ring"
                    else "a numeric datatype (1–8)"
                ),
                field=name,
            )
        size = int(kind[1])
        if offset + size > point_step:
            raise DecodeError(
                f"{source}: PointCloud2 field {name} (offset {offset}, {size} bytes) does not "
                f"fit in point_step {point_step}",
                field=name,
            )
        for other, start, other_size in zip(names, offsets, sizes, strict=True):
            if offset < start + other_size and start < offset + size:
                raise DecodeError(
                    f"{source}: PointCloud2 fields {other} (offset {start}, {other_size} bytes) "
                    f"and {name} (offset {offset}, {size} bytes) overlap; allowed: each its "
                    "own bytes",
                    field=name,
                )
        names.append(name)
        formats.append(order + kind)
        offsets.append(offset)
        sizes.append(size)
    limits.check_count(height * width, source=source)
    if row_step < width * point_step:
        raise DecodeError(
            f"{source}: PointCloud2 row_step {row_step} is less than width × point_step "
            f"({width} × {point_step})",
            field="row_step",
        )
    if len(payload) != height * row_step:
        raise DecodeError(
            f"{source}: PointCloud2 data holds {len(payload)} bytes; height × row_step is "
            f"{height * row_step}",
            field="data",
        )
    dtype = np.dtype(
        {"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step}
    )
    rows = np.frombuffer(payload, np.uint8).reshape(height, row_step)[:, : width * point_step]
    arr = np.ascontiguousarray(rows).view(dtype).reshape(-1)
    with np.errstate(over="ignore", invalid="ignore"):
        wide = np.stack([arr["x"], arr["y"], arr["z"]], axis=1)
        xyz = wide.astype(np.float32)
        value = None if intensity is None else arr[intensity].astype(np.float32)
    rings = None if ring is None else arr[ring].astype(np.int64)
    if not dense:  # missing returns, NaN (or ±inf) as the driver wrote them; a float64 value
        # past float32's range is not a missing return: it stays, and validate() refuses it
        keep = np.isfinite(wide).all(axis=1)
        if not keep.all():
            xyz = xyz[keep]
            value = None if value is None else value[keep]
            rings = None if rings is None else rings[keep]
    cloud = validate(xyz, value, limits=limits, source=source)
    return cloud if rings is None else replace(cloud, ring=rings)
