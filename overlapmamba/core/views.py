"""Sub-column views: a descriptor that a continuous turn of the sensor cannot move.

The network is exactly invariant to whole-column rolls of its range image (its ring is
circular), but a real turn is rarely a whole number of columns: each point then lands in a
column by the fraction of the turn left over, pixels change owner, and the descriptor moves.
On real KITTI 00 the shipped network's cosine to a turned copy fell to 0.99690.

A model with ``views`` = V > 1 describes a scan by V range images, view j projected as if the
sensor had turned by j / V of a column (the column coordinate shifted by j / V, wrapping
around the ring), and takes the normalised mean of the V descriptors. A turn by any angle is
then, up to whole-column rolls, a shift of that comb of sub-column phases, which the mean
nearly does not see. Measured with the shipped weights on KITTI 00's 101 scans, ten yaw
seeds (`overlapmamba eval-real --seed S`; README, Training and evaluation → Measured,
*Sub-column views*), the minimum cosine under a random turn is 0.99541–0.99741 with one
view, 0.99896–0.99930 with V = 2 (one turned scan of 1,010 below 0.999, a quarter column
off the comb) and 0.99939–0.99966 with V = 3, which the shipped model has. Averaging the V
images into one instead (one pass of the network) did not work (0.9976–0.9985 with two):
the network never saw blurred ranges.

The yaw features are view 0's: those of the plain projection, whose columns are the
sensor's, so yaw estimates keep their meaning.

The count is the model's (``EncoderMetadata.views``, part of its model id), never a setting
of a consumer: descriptors of different counts must not share a map.

**Aligned columns** (``column_phase = "aligned"``, also the model's and part of its id): one
pass a scan and no views. Where a scan's columns start is taken from the scan itself: the
mean bearing of its returns (each point's unit direction in the horizontal plane, weighted by
its horizontal share, summed in float64) is put at the centre of a column by shifting every
column coordinate by the same fraction of a column (:func:`scan_offset`, within ±½). A turn
of the sensor turns that bearing with the points, so the turned scan's image is the plain
one rolled by whole columns, which the network does not see: the cosine to a turned copy is
1 up to float rounding at column edges. Two scans of a place from different poses are
sampled at offsets that differ arbitrarily, as they are in the sensor's columns (the towns'
revisits differ in heading by more than a column: ``benchmarks/revisit_phase.py``); with
these weights the alignment still costs the descriptor alone some loop closure
(``benchmarks/column_phase.py``, on ``val``), for a reason not measured. The yaw features of
an aligned image are shifted back by the offset (:func:`unshift_features`, an exact circular
shift of their spectra) so that their columns are the sensor's and yaw estimates keep their
meaning.
"""

from __future__ import annotations

import numpy as np

from overlapmamba.core.points import PointCloud
from overlapmamba.core.projection import pixel_coordinates, rasterize
from overlapmamba.core.sensors import SensorProfile

MAX_VIEWS = 8
COLUMN_PHASES = ("sensor", "aligned")  # where a scan's columns start (the module notes)


def check_views(views: int) -> int:
    whole = isinstance(views, int | np.integer) and not isinstance(views, bool)
    if not (whole and 1 <= views <= MAX_VIEWS):
        raise ValueError(f"views must be a whole number from 1 to {MAX_VIEWS}; got {views!r}")
    return int(views)


def view_turns(views: int, profile: SensorProfile) -> np.ndarray:
    """The sensor turn of each view in degrees: j / views of a column, j = 0 … views − 1."""
    return np.arange(check_views(views)) * (360.0 / profile.width) / views


def check_column_phase(phase: str) -> str:
    if phase not in COLUMN_PHASES:
        raise ValueError(f"column_phase must be one of {', '.join(COLUMN_PHASES)}; got {phase!r}")
    return phase


def scan_offset(
    x: np.ndarray, y: np.ndarray, depth: np.ndarray, width: int, harmonic: int = 1
) -> float:
    """Columns to add to every column coordinate of a scan (kept points' ``x``, ``y`` and
    range ``depth``) so that its mean bearing falls at the centre of a column: in (−½, ½].
    Turn-equivariant: the scan turned by any angle gets the offset that makes its image the
    plain one rolled by whole columns. 0 for a scan without points.

    ``harmonic`` k > 1 takes the direction of the bearings' k-th circular moment instead
    (defined modulo 360°/k, which must be whole columns): what ``benchmarks/column_phase.py``
    compares; aligned files use the mean bearing (k = 1)."""
    if len(x) == 0:
        return 0.0
    if harmonic < 1 or width % harmonic:
        raise ValueError(
            f"harmonic must be a whole divisor of the {width} columns (360°/k whole columns); "
            f"got {harmonic}"
        )
    inv = 1.0 / np.maximum(np.asarray(depth, np.float64), 1e-9)
    if harmonic == 1:  # float64 sums: a turned copy must find the same bearing
        sx = np.einsum("i,i->", x, inv, dtype=np.float64)
        sy = np.einsum("i,i->", y, inv, dtype=np.float64)
        bearing = np.arctan2(float(sy), float(sx))
    else:  # unit bearings to the k-th power, weighted by their horizontal share like k = 1
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        level = np.maximum(np.hypot(x, y), 1e-9)
        moment = (((x + 1j * y) / level) ** harmonic * (level * inv)).sum()
        bearing = np.angle(moment) / harmonic
    # the projection's column coordinate of that bearing (overlapmamba.core.projection)
    u = 0.5 * (1.0 - bearing / np.pi) * width
    return float(0.5 - (u - np.floor(u)))


def unshift_features(features: np.ndarray, offsets: np.ndarray | float) -> np.ndarray:
    """Yaw features (B, C, W) (or (C, W)) of images projected with column offsets
    ``offsets`` (B,) → float32 features whose columns are the sensor's: each map shifted
    back by its offset, a circular shift of its spectrum (exact for whole columns; in
    between, band-limited: an even width's Nyquist bin keeps only its real part). Where
    every offset is 0 (a file with the sensor's columns) the features are returned as they
    are, as float32."""
    if not np.any(np.asarray(offsets)):
        return np.asarray(features, np.float32)
    f = np.asarray(features, np.float64)
    single = f.ndim == 2
    f = f[None] if single else f
    off = np.broadcast_to(np.asarray(offsets, np.float64), (len(f),))
    W = f.shape[-1]
    k = np.arange(W // 2 + 1)
    phase = np.exp(2j * np.pi * np.outer(off, k) / W)[:, None, :]
    out = np.fft.irfft(np.fft.rfft(f, axis=-1) * phase, n=W, axis=-1).astype(np.float32)
    return out[0] if single else out


def project_views(
    points: PointCloud | np.ndarray,
    profile: SensorProfile,
    views: int,
    *,
    aligned: bool = False,
) -> np.ndarray:
    """(views, H, W) float32 range images; view 0 is exactly :func:`project`'s image. View j
    is the image of the sensor turned by j / views of a column: the column coordinate of
    every point grows by j / views and wraps around the ring. ``aligned``: every view's
    columns also start where the scan's mean bearing puts them (:func:`project_views_offset`)."""
    return project_views_offset(points, profile, views, aligned=aligned)[0]


def project_views_offset(
    points: PointCloud | np.ndarray,
    profile: SensorProfile,
    views: int,
    *,
    aligned: bool = False,
) -> tuple[np.ndarray, float]:
    """:func:`project_views` and the column offset it added (:func:`scan_offset`; 0 unless
    ``aligned``), which the yaw features are shifted back by (:func:`unshift_features`)."""
    views = check_views(views)
    pc = pixel_coordinates(points, profile)
    out = np.empty((views, profile.height, profile.width), np.float32)
    u = pc.azimuth_column
    offset = 0.0
    if aligned:
        offset = scan_offset(pc.x, pc.y, pc.depth, profile.width)
        u = u + np.float32(offset)
        col = np.floor(u).astype(np.int32) % profile.width
    else:
        col = pc.col
    out[0] = rasterize(pc.row, col, pc.depth, profile)
    for j in range(1, views):
        col = np.floor(u + np.float32(j / views)).astype(np.int32) % profile.width
        out[j] = rasterize(pc.row, col, pc.depth, profile)
    return out, offset


def combine_views(
    descriptors: np.ndarray, yaw_features: np.ndarray, views: int
) -> tuple[np.ndarray, np.ndarray]:
    """The encoder's outputs for B scans × ``views`` images, scan-major ((B·V, D) and
    (B·V, C, W)), → one descriptor per scan, the unit-norm mean of its views' (B, D), and
    view 0's yaw features (B, C, W)."""
    views = check_views(views)
    n = len(descriptors)
    if n % views or len(yaw_features) != n:
        raise ValueError(
            f"{n} descriptors and {len(yaw_features)} yaw features are not whole scans of "
            f"{views} views each"
        )
    if views == 1:
        return descriptors, yaw_features
    mean = descriptors.reshape(n // views, views, -1).mean(1)
    norm = np.linalg.norm(mean, axis=1, keepdims=True)
    desc = (mean / np.maximum(norm, np.float32(1e-12))).astype(np.float32)
    return desc, yaw_features[::views]
