"""Which beam of a sensor a return is on, and which beam each row of a model's image shows
(the range-image inputs of :mod:`overlapmamba.core.sensors.input`).

A return's beam is the nearest elevation of its sensor's table (:func:`beam_of`). A model row
shows the beam nearest its own elevation within half a beam gap (:func:`row_beams`,
:func:`nearest_beams`), or, in ``rows`` mode, the beams stretched over the rows.
``elevation-lerp`` makes the model's own sensor's beams from another sensor's
(:class:`LerpPlan`, :func:`lerp_rows`). :func:`beams_near` finds the beams of one sensor that
see what another's would, and :func:`on_beams` keeps a scan's returns on them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from overlapmamba.core.sensors.catalogue import Sensor, sensor_of_profile
from overlapmamba.core.sensors.profile import SensorProfile

# a beam of one sensor sees what another's would when their elevations lie this close (°)
COMMON_TOLERANCE_DEG = 0.5
# ``elevation-lerp``: two beams' returns are one surface, and the rows between them take a
# range interpolated between theirs, when they stand at one height within LERP_LEVEL (m) or
# at one horizontal distance within the share LERP_EDGE of the nearer; else an edge, and
# the rows keep their nearest beam
LERP_LEVEL = 0.2
LERP_EDGE = 0.1


def beam_of(elevation_deg: np.ndarray, sensor: Sensor) -> np.ndarray:
    """(N,) elevations in degrees → (N,) int32 index of the nearest beam (0: the highest;
    exactly halfway between two: the lower)."""
    asc = np.asarray(sensor.elevations_deg, np.float64)[::-1]
    mids = (asc[1:] + asc[:-1]) / 2
    nearest_asc = np.searchsorted(mids, np.asarray(elevation_deg, np.float64))
    return (len(asc) - 1 - nearest_asc).astype(np.int32)


def row_beams(model: SensorProfile, sensor: Sensor, mode: str) -> np.ndarray:
    """(H,) int64: the beam each model row shows, −1 for a row left empty: in ``rows`` mode
    the sensor's beams stretched over the rows, else each row's nearest beam within reach
    (:func:`nearest_beams`)."""
    H = model.height
    if mode == "rows":
        return np.minimum((np.arange(H) + 0.5) * sensor.beams / H, sensor.beams - 1).astype(
            np.int64
        )
    pitch = (model.fov_up_deg - model.fov_down_deg) / H
    return nearest_beams(model.fov_up_deg - (np.arange(H) + 0.5) * pitch, sensor, pitch)


def nearest_beams(elevation_deg: np.ndarray, sensor: Sensor, pitch: float) -> np.ndarray:
    """(N,) int64: the beam of ``sensor`` nearest each elevation, where it lies within half
    the beam's gap to its neighbour on that side (or half ``pitch``); −1 elsewhere."""
    el = np.asarray(sensor.elevations_deg, np.float64)
    b = beam_of(elevation_deg, sensor).astype(np.int64)
    gaps = -np.diff(el) if sensor.beams > 1 else np.array([pitch])
    above = np.concatenate([gaps[:1], gaps])  # gap to the beam above (the top: the one below)
    below = np.concatenate([gaps, gaps[-1:]])
    off = elevation_deg - el[b]
    reach = np.maximum(np.where(off > 0, above[b], below[b]) / 2, pitch / 2)
    return np.where(np.abs(off) <= reach + 1e-9, b, -1)


@dataclass(frozen=True)
class LerpPlan:
    """How ``elevation-lerp`` makes the model's own sensor's beams (V of them) from another
    sensor's: per own beam, the sensor's beams above (``a``) and below (``b``) it and the
    share ``t`` of the way from one to the other in the sine of the elevation (−1, −1 where
    it lies outside them), the nearest beam within reach (``nearest``, −1: none) and the
    model row the beam lands in (``row``)."""

    a: np.ndarray
    b: np.ndarray
    t: np.ndarray
    nearest: np.ndarray
    row: np.ndarray

    @classmethod
    def of(cls, model: SensorProfile, sensor: Sensor) -> LerpPlan:
        own = np.asarray(sensor_of_profile(model).elevations_deg, np.float64)
        el = np.asarray(sensor.elevations_deg, np.float64)  # highest first
        pitch = (model.fov_up_deg - model.fov_down_deg) / model.height
        above = np.searchsorted(-el, -own, side="right") - 1  # the last beam at or above
        inside = (above >= 0) & (above < len(el) - 1)
        a = np.where(inside, above, -1).astype(np.int64)
        b = np.where(inside, above + 1, -1).astype(np.int64)
        # the share in sin(elevation): 1/range is linear in it along a flat ground
        sa, sb = (np.sin(np.radians(el[np.clip(i, 0, None)])) for i in (a, b))
        t = np.where(inside, (sa - np.sin(np.radians(own))) / np.where(inside, sa - sb, 1.0), 0.0)
        # the row as the model's own projection puts a return at that elevation
        row = np.clip(np.floor((model.fov_up_deg - own) / pitch), 0, model.height - 1)
        row = row.astype(np.int64)
        return cls(a, b, t.astype(np.float32), nearest_beams(own, sensor, pitch), row)


def lerp_rows(
    ring: np.ndarray,
    plan: LerpPlan,
    elevations_deg: np.ndarray | tuple[float, ...],
    height: int,
    empty: float,
) -> np.ndarray:
    """(B, W) one view's range per beam of a sensor (``empty`` where none) → (height, W) the
    model's image of the own beams ``plan`` makes from them. An own beam between two of the
    sensor's takes a range interpolated between theirs (1/range linear in the sine of the
    elevation: exact on a flat ground) when the two returns are one surface: at one height
    within :data:`LERP_LEVEL` (a ground) or at one horizontal distance within
    :data:`LERP_EDGE` of it (a wall). Else (an edge, where interpolating would put a return
    in the gap, or a beam without a return) it takes its nearest beam, as ``elevation``."""
    W = ring.shape[1]
    emp = np.float32(empty)
    vals = np.full((len(plan.row), W), emp, np.float32)
    has = plan.nearest >= 0
    vals[has] = ring[plan.nearest[has]]
    own = np.flatnonzero(plan.a >= 0)
    ra, rb = ring[plan.a[own]], ring[plan.b[own]]
    el = np.radians(np.asarray(elevations_deg, np.float64)).astype(np.float32)
    sa, sb = np.sin(el[plan.a[own]])[:, None], np.sin(el[plan.b[own]])[:, None]
    ca, cb = np.cos(el[plan.a[own]])[:, None], np.cos(el[plan.b[own]])[:, None]
    level = np.abs(ra * sa - rb * sb) <= np.float32(LERP_LEVEL)
    da, db = ra * ca, rb * cb
    wall = np.abs(da - db) <= np.float32(LERP_EDGE) * np.minimum(da, db)
    valid = (ra != emp) & (rb != emp) & (level | wall)
    w = plan.t[own, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        lerp = np.float32(1.0) / ((np.float32(1.0) - w) / ra + w / rb)
    vals[own] = np.where(valid, lerp, vals[own])
    out = np.full((height, W), np.inf, np.float32)
    vals[vals == emp] = np.inf
    for v in np.flatnonzero(plan.row >= 0):  # the nearest return where beams share a row
        np.minimum(out[plan.row[v]], vals[v], out=out[plan.row[v]])
    out[np.isinf(out)] = emp
    return out


def beams_near(sensor: Sensor, other: Sensor) -> np.ndarray:
    """Indices of ``sensor``'s beams nearest each of ``other``'s elevations, where one lies
    within :data:`COMMON_TOLERANCE_DEG` (sorted, highest first): the beams of ``sensor`` that
    see what ``other``'s would."""
    el = np.asarray(sensor.elevations_deg, np.float64)
    keep = {
        int(np.argmin(np.abs(el - e)))
        for e in other.elevations_deg
        if np.abs(el - e).min() <= COMMON_TOLERANCE_DEG
    }
    return np.array(sorted(keep), np.int64)


def on_beams(xyz: np.ndarray, sensor: Sensor, beams: np.ndarray) -> np.ndarray:
    """(M, 3) the points of ``xyz`` (N, ≥3), in the sensor's own frame, that lie on
    ``beams`` of ``sensor`` (a point's beam: the nearest elevation of its table)."""
    xyz = np.asarray(xyz)[:, :3]
    r = np.linalg.norm(xyz, axis=1)
    el = np.degrees(np.arcsin(np.clip(xyz[:, 2] / np.maximum(r, 1e-9), -1.0, 1.0)))
    return xyz[np.isin(beam_of(el, sensor), beams)]
