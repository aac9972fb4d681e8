"""Range images of a whole sequence, projected once and cached as one float16 ``.npy``.

Training reads every scan many times; decoding ≈120k points and projecting them costs more
than the network's forward pass on a batch. So each sequence is projected once, with
overlapmamba.core's projection (the service uses the same one), into
``$OVERLAPMAMBA_CACHE/range_images/<sequence>-<key>.npy`` and memory-mapped from then on.

The key hashes the sensor profile, the scans' sensor when it is not the profile's own
(:mod:`overlapmamba.core.sensors.input`), and the sequence's poses, scan names and sizes, so a
changed profile, sensor or recording never reuses a stale cache. float16 keeps ranges to ≤ 4 cm at
80 m (half a KITTI beam's range noise) at half the size: 4,000 HDL-64E scans are 460 MB.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from overlapmamba.core.cache import cache_root
from overlapmamba.core.datasets.base import Sequence
from overlapmamba.core.sensors import SensorProfile
from overlapmamba.core.sensors.input import SensorInput
from overlapmamba.core.views import check_views, project_views_offset

FORMAT = 1
ALIGNMENT = 1  # how aligned columns are taken (overlapmamba.core.views.scan_offset): bump on change


def cache_key(
    seq: Sequence,
    profile: SensorProfile,
    views: int = 1,
    sensor: SensorInput | None = None,
    aligned: bool = False,
) -> str:
    key: list[object] = [FORMAT, profile.model_dump()]
    if views != 1:  # one view keeps the keys (and caches) made before views existed
        key.append({"views": views})
    if aligned:  # the sensor's columns keep them too
        key.append({"column_phase": "aligned", "alignment": ALIGNMENT})
    if sensor is not None and sensor.key():  # a native sensor keeps them too
        key.append(sensor.key())
    h = hashlib.sha256(json.dumps(key, sort_keys=True).encode())
    seq.update_digest(h)
    return h.hexdigest()[:16]


def range_images(
    seq: Sequence,
    profile: SensorProfile,
    *,
    views: int = 1,
    sensor: SensorInput | None = None,
    progress: bool = True,
    aligned: bool = False,
) -> np.ndarray:
    """(N, H, W) float16 range images of every scan, memory-mapped read-only; with
    ``views`` > 1, (N, views, H, W): each scan's sub-column views (:mod:`overlapmamba.core.views`).
    ``sensor``: the scans' sensor into ``profile`` (:mod:`overlapmamba.core.sensors.input`; None:
    the profile's own sensor). ``aligned``: each scan's columns start at its mean bearing;
    the offsets are cached beside the images (:func:`range_offsets`)."""
    views = check_views(views)
    if sensor is not None and sensor.model != profile:
        raise ValueError(f"sensor input for {sensor.model.name}, not the profile {profile.name}")
    shape: tuple[int, ...] = (len(seq), profile.height, profile.width)
    if views > 1:
        shape = (shape[0], views, *shape[1:])
    path = _cache_path(seq, profile, views, sensor, aligned)
    # the key reads no scan: a rewrite in place keeps it (a recording's, a bag's, holds its
    # message times, and it has no content digest)
    digest = getattr(seq, "content_digest", None)
    content = digest() if digest is not None else ""
    recorded = _content_path(path)
    if path.is_file() and (not aligned or _offsets_path(path).is_file()):
        try:
            images = np.load(path, mmap_mode="r")
            # caches made before 2026-12-04 record no content: taken as before
            same = not recorded.is_file() or recorded.read_text().strip() == content
            if images.shape == shape and same:
                return images
        except (OSError, ValueError):
            pass  # torn or foreign file: rebuild it
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.stem}.tmp{os.getpid()}.npy")
    out = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.float16, shape=shape)
    offsets = np.zeros(len(seq), np.float64)
    for i in tqdm(range(len(seq)), desc=f"range images {seq.name}", disable=not progress):
        points = seq.points(i)
        images, offsets[i] = (
            project_views_offset(points, profile, views, aligned=aligned)
            if sensor is None
            else sensor.project_offset(points, views, aligned=aligned)
        )
        out[i] = images if views > 1 else images[0]
    out.flush()
    del out
    if aligned:  # first, so that images without their offsets are never found
        done = _offsets_path(path)
        part = done.with_name(f"{done.stem}.tmp{os.getpid()}.npy")
        np.save(part, offsets)
        os.replace(part, done)
    recorded.unlink(missing_ok=True)  # no stale record beside new images, even for a moment
    os.replace(tmp, path)  # atomic: a crash mid-way leaves no half-written cache behind
    if content:
        part = recorded.with_name(f"{recorded.name}.tmp{os.getpid()}")
        part.write_text(content + "\n")
        os.replace(part, recorded)
    return np.load(path, mmap_mode="r")


def _content_path(path: Path) -> Path:
    """Beside a cache: the content digest of the scans it was made from."""
    return path.with_name(f"{path.stem}.content")


def range_offsets(
    seq: Sequence,
    profile: SensorProfile,
    *,
    views: int = 1,
    sensor: SensorInput | None = None,
    progress: bool = True,
) -> np.ndarray:
    """(N,) the column offsets of :func:`range_images` with ``aligned`` (projected and cached
    with the images if not yet there)."""
    path = _cache_path(seq, profile, check_views(views), sensor, True)
    offsets = _load_offsets(path, len(seq))
    if offsets is None or not path.is_file():
        _offsets_path(path).unlink(missing_ok=True)  # torn or foreign: project again
        range_images(seq, profile, views=views, sensor=sensor, progress=progress, aligned=True)
        offsets = np.load(_offsets_path(path))
    return offsets


def _load_offsets(images: Path, n: int) -> np.ndarray | None:
    try:
        offsets = np.load(_offsets_path(images))
    except (OSError, ValueError):
        return None
    return offsets if offsets.shape == (n,) else None


def _cache_path(
    seq: Sequence, profile: SensorProfile, views: int, sensor: SensorInput | None, aligned: bool
) -> Path:
    key = cache_key(seq, profile, views, sensor, aligned)
    return cache_root() / "range_images" / f"{seq.name}-{key}.npy"


def _offsets_path(images: Path) -> Path:
    return images.with_name(f"{images.stem}.offsets.npy")
