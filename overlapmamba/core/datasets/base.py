"""What every sequence reader provides."""

from __future__ import annotations

import hashlib
import os
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from overlapmamba.core.errors import DatasetError
from overlapmamba.core.io import read_points, read_xyzi
from overlapmamba.core.points import PointCloud
from overlapmamba.core.sensors.mount import Mount

_NUMBER = re.compile(r"(\d+)")


def scan_order(path: Path) -> tuple[int, str]:
    """Sort key of scan files: by the first number in the name (``2.bin`` before
    ``10.bin``, as ``000002.bin`` before ``000010.bin``), then by name."""
    m = _NUMBER.search(path.stem)
    return (int(m.group(1)) if m else -1, path.name)


@dataclass(frozen=True)
class Sequence:
    """A recorded drive: scan files and one LiDAR-frame pose (scan → world) per scan.

    scan_paths: N files, in time order
    poses:      (N, 4, 4) float64, LiDAR frame
    sensor:     name of the sensor profile the data was recorded with, if known
    mount:      where that sensor sat, when known and not the reference (level,
                :data:`~overlapmamba.core.sensors.mount.REFERENCE_HEIGHT` above the road)
    """

    root: Path
    scan_paths: tuple[Path, ...]
    poses: np.ndarray
    sensor: str | None = None
    mount: Mount | None = None

    def __post_init__(self) -> None:
        if len(self.scan_paths) != len(self.poses):
            raise DatasetError(
                f"{self.root}: {len(self.scan_paths)} scans but {len(self.poses)} poses; "
                "a sequence needs exactly one pose per scan",
                scans=len(self.scan_paths),
                poses=len(self.poses),
            )
        if not self.scan_paths:
            raise DatasetError(f"{self.root}: the sequence holds no scans")

    @property
    def name(self) -> str:
        return self.root.name

    def __len__(self) -> int:
        return len(self.scan_paths)

    def points(self, i: int) -> PointCloud:
        return read_points(self.scan_paths[i])

    def xyzi(self, i: int) -> np.ndarray:
        """Scan ``i`` as (N, 4) float32 ``xyzi``, as a service takes it (:func:`read_xyzi`)."""
        return read_xyzi(self.scan_paths[i])

    def __iter__(self) -> Iterator[PointCloud]:
        for i in range(len(self)):
            yield self.points(i)

    def update_digest(self, h: hashlib._Hash) -> None:
        """Feed what identifies the recording (poses, scan names and sizes) into a hash, cheaply:
        no scan is read. Caches keyed by it go stale when a scan or pose changes."""
        h.update(np.ascontiguousarray(self.poses).tobytes())
        for p in self.scan_paths:
            h.update(f"{p.name}:{p.stat().st_size}".encode())

    def content_digest(self) -> str:
        """A digest of the scans' bytes, sampled: each scan's first and last 4 KiB (8 KiB a
        scan read). :meth:`update_digest` reads no scan, so a scan rewritten in place at its
        size (de-skewed, filtered, simulated again) keeps its caches' keys; a cache that
        records this digest beside its key sees the rewrite and is made again."""
        h = hashlib.sha256()
        for p in self.scan_paths:
            with open(p, "rb") as f:
                h.update(f.read(4096))
                size = f.seek(0, os.SEEK_END)
                f.seek(max(0, size - 4096))
                h.update(f.read(4096))
        return h.hexdigest()[:16]

    def positions(self) -> np.ndarray:
        """(N, 3) scan positions in the world frame."""
        return self.poses[:, :3, 3]
