"""Checks on real scans that have no loops (``../shared/data``: KITTI 00 frames 0–100, the
nuScenes HDL-32E scene): ``overlapmamba eval-real``.

- **yaw invariance**: every scan turned about z by a random, continuous angle;
- **odd → even retrieval**: the odd frames, turned, against the even frames, with Scan
  Context on the same queries;
- **yaw estimate** from the yaw features;
- **thinned beams** (``--beams 32,16``): the queries keep every second or fourth ring of the
  HDL-64E (rings found by elevation, :func:`overlapmamba.core.sensors.beams.beam_of`), the database
  stays whole: what a fleet's 32- or 16-beam sensor gives against a map of full scans.

Scans enter the model as their sensor's (:mod:`overlapmamba.core.sensors.input`): the sequence's
own sensor (KITTI's HDL-64E unless told otherwise), into the model's profile.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from overlapmamba.core.datasets.base import Sequence
from overlapmamba.core.errors import DatasetError
from overlapmamba.core.metrics import nearest, squared_distances
from overlapmamba.core.poses import rotation_z, transform_points, yaw_deg
from overlapmamba.core.rerank import OFF, Rerank, rerank_ranked
from overlapmamba.core.scancontext import ScanContextParams, scan_context
from overlapmamba.core.scancontext import retrieve as sc_retrieve
from overlapmamba.core.sensors import Sensor, SensorProfile
from overlapmamba.core.sensors.beams import beam_of
from overlapmamba.core.sensors.input import SensorInput
from overlapmamba.core.yaw import estimate_yaw
from overlapmamba.train.checkpoint import (
    Network,
    aligned_of,
    input_of,
    sensor_input_of,
    views_of,
)
from overlapmamba.train.evaluate import describe


@dataclass(frozen=True)
class RealTurns:
    """Range images of real scans and of the same scans turned about z by ``theta`` (degrees,
    uniform in ±180°: continuous, not whole columns), projected once; with sub-column views,
    each scan's views (:mod:`overlapmamba.core.views`)."""

    plain: np.ndarray  # (N, H, W) float32, or (N, V, H, W)
    turned: np.ndarray  # the same shape
    theta: np.ndarray  # (N,) degrees
    positions: np.ndarray  # (N, 3) from the poses
    input: str  # how the scans entered the model: native, elevation or rows
    plain_offsets: np.ndarray | None = None  # (N,) column offsets, aligned columns only
    turned_offsets: np.ndarray | None = None


def turned_points(xyz: np.ndarray, theta: float) -> np.ndarray:
    """Points ``xyz`` (N, 3) as the sensor sees them after it turned by ``theta`` degrees
    about z: they turn by −θ, and every one is re-binned when projected, as a real turn."""
    return transform_points(xyz, rotation_z(-theta))


def turned_image(xyz: np.ndarray, theta: float, profile: SensorProfile) -> np.ndarray:
    """The range image of points ``xyz`` (N, 3) after the sensor turned by ``theta`` degrees
    about z (:func:`turned_points`)."""
    from overlapmamba.core.projection import project

    return project(turned_points(xyz, theta), profile)


def turns(n: int, seed: int) -> np.ndarray:
    """(n,) random continuous turns in degrees, one per scan, from ``seed``."""
    return np.random.default_rng(seed).uniform(-180.0, 180.0, n)


def real_turns(
    seq: Sequence,
    sensor: SensorInput,
    seed: int = 0,
    views: int = 1,
    aligned: bool = False,
    stride: int = 1,
) -> RealTurns:
    """Every ``stride``-th scan of ``seq`` (all by default) and its turned copy, as
    ``sensor`` puts them into the model's input; ``views`` > 1: each scan's sub-column views,
    (N, views, H, W); ``aligned``: each scan's columns at its mean bearing
    (:mod:`overlapmamba.core.views`), with the offsets."""
    if stride < 1:
        raise ValueError(f"stride must be ≥ 1 (every stride-th scan); got {stride}")
    index = np.arange(0, len(seq), stride)
    theta = turns(len(index), seed)
    plain, turned = [], []
    for i, k in enumerate(index):
        xyz = seq.points(int(k)).xyz
        plain.append(sensor.project_offset(xyz, views, aligned=aligned))
        turned.append(sensor.project_offset(turned_points(xyz, theta[i]), views, aligned=aligned))

    def stack(projected: list[tuple[np.ndarray, float]]) -> np.ndarray:
        return np.stack([img if views > 1 else img[0] for img, _ in projected])

    def offsets(projected: list[tuple[np.ndarray, float]]) -> np.ndarray | None:
        return np.array([o for _, o in projected]) if aligned else None

    return RealTurns(
        stack(plain),
        stack(turned),
        theta,
        seq.positions()[index],
        sensor.kind,
        offsets(plain),
        offsets(turned),
    )


def turn_check(model: Network, turns: RealTurns | None, device: str) -> dict[str, Any] | None:
    """An epoch's check on real scans (``real``): :func:`invariance` of the model's
    descriptors of ``turns``; None when the check is off."""
    if turns is None:
        return None
    desc, _ = describe(model, turns.plain, device=device)
    desc_t, _ = describe(model, turns.turned, device=device)
    return invariance(desc, desc_t, turns.positions)


def invariance(desc: np.ndarray, desc_t: np.ndarray, positions: np.ndarray) -> dict[str, Any]:
    """How far a turned copy moves, against how far scans 1 m apart (0.8–1.2 m) and any two
    different scans are: squared distances between descriptors, medians."""
    n = len(desc)
    cos = (desc * desc_t).sum(1)
    d_turn = float(np.median(((desc - desc_t) ** 2).sum(1)))
    d_all = squared_distances(desc, desc)
    d_other = float(np.median(d_all[~np.eye(n, dtype=bool)]))
    apart = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
    step = np.triu((apart >= 0.8) & (apart <= 1.2), 1)
    d_step = float(np.median(d_all[step])) if step.any() else math.nan

    def ratio(a: float, b: float) -> float:  # a collapsed model has zero distances
        return a / b if b > 0 else math.nan

    return {
        "cosine_min": float(cos.min()),
        "cosine_mean": float(cos.mean()),
        "turned_over_other_distance": ratio(d_turn, d_other),
        "turned_distance_median": d_turn,
        "one_metre_step_distance_median": d_step,
        "one_metre_step_pairs": int(step.sum()),
        "turned_over_one_metre_step": ratio(d_turn, d_step),
    }


def _stats(x: np.ndarray) -> dict[str, float]:
    if len(x) == 0:
        return {"median": math.nan, "p90": math.nan, "max": math.nan}
    return {
        "median": float(np.median(x)),
        "p90": float(np.percentile(x, 90)),
        "max": float(x.max()),
    }


def _hits(
    pos: np.ndarray, queries: np.ndarray, database: np.ndarray, ranked: np.ndarray, radius: float
) -> np.ndarray:
    """(Q, N) bool: the n-th answer (database index) lies within ``radius`` of its query."""
    found = database[ranked]
    return np.linalg.norm(pos[found] - pos[queries][:, None], axis=-1) < radius


def eval_real(
    model: Network,
    profile: SensorProfile,
    seq: Sequence,
    *,
    seed: int = 0,
    hit_radius: float = 3.0,
    rerank: Rerank = OFF,
    beams: tuple[int, ...] = (),
) -> dict[str, Any]:
    """Real scans (the module notes): invariance under a random continuous turn, odd → even
    retrieval of the turned odd frames (Recall@1/@5 within ``hit_radius``, Scan Context
    beside; with ``rerank`` on, the two-stage answers too), the yaw estimate, and for each
    count in ``beams`` the same retrieval with thinned queries (:func:`thinned`)."""
    if len(seq) < 2:  # odd → even retrieval needs one of each
        raise DatasetError(
            f"{seq.root}: eval-real needs at least 2 scans (odd frames query the even); "
            f"it has {len(seq)}"
        )
    inp = input_of(model, profile, seq)
    t = real_turns(seq, inp, seed, views_of(model), aligned_of(model))
    theta, pos, n = t.theta, t.positions, len(seq)
    desc, feats = describe(model, t.plain, offsets=t.plain_offsets)
    desc_t, feats_t = describe(model, t.turned, offsets=t.turned_offsets)
    inv = invariance(desc, desc_t, pos)
    yaw_copy = np.array([estimate_yaw(feats[i], feats_t[i])[0][0] for i in range(n)])
    err_copy = np.abs((yaw_copy - theta + 180.0) % 360.0 - 180.0)

    odd, even = np.arange(1, n, 2), np.arange(0, n, 2)
    k = min(5, len(even))
    # one search for both stages: the second re-ranks the first rerank.shortlist of it
    ranked, dist = nearest(desc_t[odd], desc[even], k=min(max(k, rerank.shortlist), len(even)))
    close = _hits(pos, odd, even, ranked[:, :k], hit_radius)
    staged: dict[str, Any] = {}
    if rerank.on:  # the service's two stages: the nearest re-ranked by their yaw features
        r2, _ = rerank_ranked(
            feats_t[odd], feats[even], ranked, dist, rerank, (desc_t[odd], desc[even])
        )
        near2 = _hits(pos, odd, even, r2[:, :k], hit_radius)
        staged = {
            "reranked": {
                **asdict(rerank),
                "recall@1": float(near2[:, 0].mean()),
                "recall@5": float(near2.any(1).mean()),
            }
        }
    # The turned query's pose: its sensor frame is turned by +θ about z.
    q_poses = seq.poses[odd] @ np.stack([rotation_z(x) for x in theta[odd]])
    top1 = even[ranked[:, 0]]
    truth = yaw_deg(np.linalg.inv(q_poses) @ seq.poses[top1])  # T_query←retrieved
    est = np.array(
        [estimate_yaw(feats_t[i], feats[j])[0][0] for i, j in zip(odd, top1, strict=True)]
    )
    err_ret = np.abs((est - truth + 180.0) % 360.0 - 180.0)[close[:, 0]]
    out: dict[str, Any] = {
        "scans": n,
        "sensor": inp.sensor.name,
        "input": inp.kind,
        "yaw_invariance": inv,
        "retrieval_odd_to_even": {
            "queries": len(odd),
            "database": len(even),
            "hit_radius_m": hit_radius,
            "recall@1": float(close[:, 0].mean()),
            "recall@5": float(close.any(1).mean()),
            **staged,
            "scan_context": _scan_context_odd_to_even(seq, theta, odd, even, k, hit_radius),
        },
        "yaw_error_deg": {
            "vs_turned_copy": _stats(err_copy),
            "vs_retrieved_frame": _stats(err_ret),
        },
    }
    if beams:
        full = (desc, feats)
        out["thinned"] = {
            str(b): thinned(model, profile, seq, inp.sensor, b, full, theta, hit_radius, rerank)
            for b in beams
        }
    return out


def thinned_sensor(sensor: Sensor, beams: int) -> Sensor:
    """``sensor`` with every (B / ``beams``)-th beam: what a sensor of that many rings over
    the same field of view looks like."""
    if beams < 1 or sensor.beams % beams:
        raise ValueError(
            f"{sensor.name} has {sensor.beams} beams: it thins to a whole divisor of that, not "
            f"{beams}"
        )
    step = sensor.beams // beams
    return sensor.model_copy(
        update={
            "name": f"{sensor.name}-{beams}",
            "title": f"{sensor.title}, every {step}th ring",
            "elevations_deg": sensor.elevations_deg[::step],
            "projection": None,
        }
    )


def thin_points(xyz: np.ndarray, sensor: Sensor, beams: int) -> np.ndarray:
    """The points of every (B / ``beams``)-th ring of ``sensor`` (rings found by elevation)."""
    step = sensor.beams // beams
    r = np.linalg.norm(xyz[:, :3], axis=1)
    ring = beam_of(np.degrees(np.arcsin(xyz[:, 2] / np.maximum(r, 1e-9))), sensor)
    return xyz[ring % step == 0]


def thinned(
    model: Network,
    profile: SensorProfile,
    seq: Sequence,
    sensor: Sensor,
    beams: int,
    full: tuple[np.ndarray, np.ndarray],
    theta: np.ndarray,
    hit_radius: float,
    rerank: Rerank,
) -> dict[str, Any]:
    """Queries of ``beams`` rings against whole scans. The odd frames, turned by ``theta``
    and thinned, query the even frames' descriptors ``full`` (descriptors, yaw features);
    each frame thinned but not turned is compared with its whole self (cosine). Twice: the
    thinned scans declared as the sensor they now are (the model's input for a sensor of
    that table, as the service projects a scan that names its sensor), and undeclared
    (projected as the model's own sensor, as a scan that names none would be)."""
    desc, feats = full
    pos, n = seq.positions(), len(seq)
    odd, even = np.arange(1, n, 2), np.arange(0, n, 2)
    k = min(5, len(even))
    mode = sensor_input_of(model)
    declared = SensorInput(profile, thinned_sensor(sensor, beams), mode)
    out: dict[str, Any] = {"beams": beams, "points_kept": 0.0}
    kept = []
    views, aligned = views_of(model), aligned_of(model)
    for label, inp in (("declared", declared), ("undeclared", SensorInput.own(profile, mode))):
        plain, turned, t_off = [], [], []
        for i in range(n):
            xyz = seq.points(i).xyz
            thin = thin_points(xyz, sensor, beams)
            if label == "declared":
                kept.append(len(thin) / max(len(xyz), 1))
            img = inp.project(thin, views, aligned=aligned)
            plain.append(img if views > 1 else img[0])
            if i % 2:
                t_img, off = inp.project_offset(
                    turned_points(thin, theta[i]), views, aligned=aligned
                )
                turned.append(t_img if views > 1 else t_img[0])
                t_off.append(off)
        d_thin, _ = describe(model, np.stack(plain))
        d_q, f_q = describe(model, np.stack(turned), offsets=np.array(t_off))
        cos = (d_thin * desc).sum(1)
        ranked, dist = nearest(d_q, desc[even], k=min(max(k, rerank.shortlist), len(even)))
        close = _hits(pos, odd, even, ranked[:, :k], hit_radius)
        row: dict[str, Any] = {
            "input": inp.kind,
            "cosine_to_full": {"median": float(np.median(cos)), "min": float(cos.min())},
            "recall@1": float(close[:, 0].mean()),
            "recall@5": float(close.any(1).mean()),
        }
        if rerank.on:
            r2, _ = rerank_ranked(f_q, feats[even], ranked, dist, rerank, (d_q, desc[even]))
            near2 = _hits(pos, odd, even, r2[:, :k], hit_radius)
            row["reranked"] = {
                "recall@1": float(near2[:, 0].mean()),
                "recall@5": float(near2.any(1).mean()),
            }
        out[label] = row
    out["points_kept"] = float(np.mean(kept))
    return out


def _scan_context_odd_to_even(
    seq: Sequence, theta: np.ndarray, odd: np.ndarray, even: np.ndarray, k: int, radius: float
) -> dict[str, float]:
    """Scan Context on :func:`eval_real`'s odd → even protocol: the same turned queries
    (odd frames turned by ``theta``), the same database, the same hit radius."""
    p = ScanContextParams()
    db = [scan_context(seq.points(int(i)).xyz, p) for i in even]
    qs = [scan_context(turned_points(seq.points(int(i)).xyz, theta[i]), p) for i in odd]
    contexts = np.stack(db + qs)
    queries = len(even) + np.arange(len(odd))
    ranked, _ = sc_retrieve(contexts, queries, np.full(len(odd), len(even)), k, p.candidates)
    pos = seq.positions()
    found = np.where(ranked >= 0, even[np.clip(ranked, 0, None)], -1)
    close = (np.linalg.norm(pos[found] - pos[odd][:, None], axis=-1) < radius) & (found >= 0)
    return {"recall@1": float(close[:, 0].mean()), "recall@5": float(close.any(1).mean())}
