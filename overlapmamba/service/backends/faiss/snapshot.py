"""A map's FAISS snapshot: the serialized index and the store seq it contains.

    index.snap   OMSNAP01 | uint32 header length | JSON {seq, kind, dim, crc32} | FAISS bytes

Written atomically (temporary file, fsync, rename, fsync of the folder). The index is
derived from the store, so a missing or damaged snapshot costs a rebuild, never data: the
header's CRC-32 of the FAISS bytes finds one damaged on disk (snapshots written before it
was recorded are read without it).
"""

from __future__ import annotations

import json
import logging
import os
import struct
import zlib
from pathlib import Path

from overlapmamba.service.backends.faiss.index import VectorIndex
from overlapmamba.service.backends.faiss.sqlfile import fsync_dir
from overlapmamba.service.settings import IndexSettings

log = logging.getLogger("overlapmamba.service")
SNAPSHOT_MAGIC = b"OMSNAP01"
SNAPSHOT_NAME = "index.snap"


def write_snapshot(path: Path, payload: bytes, seq: int, kind: str, dim: int) -> Path:
    # the payload's CRC-32: a bit flipped on disk is a rebuild, not a keyframe lost to search
    crc = zlib.crc32(payload)
    header = json.dumps({"seq": seq, "kind": kind, "dim": dim, "crc32": crc}).encode()
    tmp = path.with_suffix(".snap.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(SNAPSHOT_MAGIC + struct.pack("<I", len(header)) + header + payload)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:  # a full disk: a half-written copy as large as the index must go
        tmp.unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)
    return path


def read_snapshot(path: Path, dim: int, settings: IndexSettings) -> tuple[VectorIndex | None, int]:
    """(index, seq), or (None, 0) when there is no usable snapshot — the index is derived,
    so a missing or damaged snapshot costs a rebuild, never data."""
    if not path.exists():
        return None, 0
    try:
        data = path.read_bytes()
        if data[:8] != SNAPSHOT_MAGIC:
            raise ValueError("bad magic")
        (n,) = struct.unpack("<I", data[8:12])
        header = json.loads(data[12 : 12 + n])
        payload = memoryview(data)[12 + n :]
        if "crc32" in header and zlib.crc32(payload) != header["crc32"]:  # older: none
            raise ValueError("its payload's CRC-32 does not match its header's")
        index = VectorIndex.deserialize(data[12 + n :], header["kind"], nprobe=settings.ivf_nprobe)
        if index.dim != dim:
            raise ValueError(f"dimension {index.dim}, map has {dim}")
        return index, int(header["seq"])
    except Exception as err:  # anything wrong with a derived file means: rebuild it
        log.warning("snapshot %s is unusable (%s); rebuilding the index from the store", path, err)
        return None, 0
