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
"""

from __future__ import annotations

import numpy as np

from overlapmamba.core.points import PointCloud
from overlapmamba.core.projection import pixel_coordinates, rasterize
from overlapmamba.core.sensors import SensorProfile

MAX_VIEWS = 8


def check_views(views: int) -> int:
    whole = isinstance(views, int | np.integer) and not isinstance(views, bool)
    if not (whole and 1 <= views <= MAX_VIEWS):
        raise ValueError(f"views must be a whole number from 1 to {MAX_VIEWS}; got {views!r}")
    return int(views)


def view_turns(views: int, profile: SensorProfile) -> np.ndarray:
    """The sensor turn of each view in degrees: j / views of a column, j = 0 … views − 1."""
    return np.arange(check_views(views)) * (360.0 / profile.width) / views


def project_views(
    points: PointCloud | np.ndarray, profile: SensorProfile, views: int
) -> np.ndarray:
    """(views, H, W) float32 range images; view 0 is exactly :func:`project`'s image. View j
    is the image of the sensor turned by j / views of a column: the column coordinate of
    every point grows by j / views and wraps around the ring."""
    views = check_views(views)
    pc = pixel_coordinates(points, profile)
    out = np.empty((views, profile.height, profile.width), np.float32)
    out[0] = rasterize(pc.row, pc.col, pc.depth, profile)
    if views > 1:
        u = pc.azimuth_column
        for j in range(1, views):
            col = np.floor(u + np.float32(j / views)).astype(np.int32) % profile.width
            out[j] = rasterize(pc.row, col, pc.depth, profile)
    return out


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
