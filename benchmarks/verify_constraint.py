"""How well a verified closure's geometry pins its translation, on the validation town's
true loops and on a road cut that slides along itself (``verify.min_constraint``).

GICP's fitness counts matched points, so where the scene repeats along one direction (a
corridor, a road cut, a tunnel) a pose slid along it fits as well as the right one: a
review registered a query 15 m along a straight cut from its keyframe and got fitness 0.95
at a translation 15 m off, verified, past the ambiguity check (which turns the seed, never
moves it). The registration's ``constraint`` (:func:`overlapmamba.service.registration.
constraint`: the smallest over the largest eigenvalue of the translation block of GICP's
final Hessian) says how firmly the geometry pins each direction.

This registers every query of the validation town with a ground-truth loop (its best loop,
overlap above 0.3) against that keyframe, seeded with the true relative yaw, judges it with
the service's fitness and rmse thresholds, and records the constraint of those verified with
the right pose (within 1 m and 2°); then a straight road cut (ground and a terraced rock face
along x, the keyframe 15 m farther along), registered the same way. It reports the
constraint's distribution on the town's right closures, the road cut's, and the largest
floor that keeps every right closure of the town: half the town's least (``suggested``).
Select on val only. Writes reports/model/verify-constraint.json.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from reports_kit import REPORTS, write_report

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.overlap import loop_ground_truth
from overlapmamba.core.poses import pose_error, yaw_deg
from overlapmamba.core.sensors import get_profile
from overlapmamba.service.registration import keyframe_geometry, prepare, register
from overlapmamba.service.settings import VerifySettings
from overlapmamba.service.verify import judge, params_of


def road_cut(sensor_x: float, rng: np.random.Generator, n: int = 120_000) -> np.ndarray:
    """A straight road cut along x seen from ``sensor_x``: ground at z = −1.7 m from y = −6
    to 3, a rock face terraced at y = 3, 5 and 7 m up to 7 m, 50 m each way, 2 cm noise."""
    x = rng.uniform(sensor_x - 50, sensor_x + 50, n)
    k = rng.integers(0, 4, n)
    y = np.select([k == 0, k == 1, k == 2], [3.0, 5.0, 7.0], rng.uniform(-6, 3, n))
    z = np.select(
        [k == 0, k == 1, k == 2],
        [rng.uniform(-1.7, 1, n), rng.uniform(1, 4, n), rng.uniform(4, 7, n)],
        -1.7,
    )
    return (np.stack([x - sensor_x, y, z], 1) + rng.normal(0, 0.02, (n, 3))).astype(np.float32)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--town", type=Path, default=Path("data/synth/val"))
    ap.add_argument("--json", type=Path, default=REPORTS / "model" / "verify-constraint.json")
    args = ap.parse_args()

    v = VerifySettings()
    p = params_of(v)
    seq = open_sequence(args.town)
    profile = get_profile(seq.sensor or "kitti-hdl64")
    queries, refs, _ = loop_ground_truth(seq, profile, progress=False).best_loops()
    right, wrong, refused = [], [], 0
    for q, r in zip(queries.tolist(), refs.tolist(), strict=True):
        truth = np.linalg.inv(seq.poses[r]) @ seq.poses[q]  # T_keyframe←query
        blob = keyframe_geometry(prepare(seq.points(r).xyz, p), p)
        reg = register(prepare(seq.points(q).xyz, p), blob, float(yaw_deg(np.linalg.inv(truth))), p)
        verdict = judge(reg, v)
        if not verdict.verified or reg.constraint is None:
            refused += 1
            continue
        t_err, yaw_err = pose_error(reg.relative_pose, truth)
        (right if t_err <= 1.0 and yaw_err <= 2.0 else wrong).append(reg.constraint)

    rng = np.random.default_rng(0)
    cut = register(
        prepare(road_cut(0.0, rng), p),
        keyframe_geometry(prepare(road_cut(15.0, rng), p), p),
        0.0,
        p,
    )
    cut_verdict = judge(cut, v)
    assert cut.relative_pose is not None
    c = np.array(right)
    least = float(c.min()) if c.size else None
    record = {
        "benchmark": "verify_constraint",
        "town": str(args.town),
        "loops": len(queries),
        "verified_right": len(right),
        "verified_wrong": len(wrong),
        "not_verified": refused,
        "constraint_right": {
            "min": least,
            "p1": float(np.percentile(c, 1)) if c.size else None,
            "p5": float(np.percentile(c, 5)) if c.size else None,
            "median": float(np.median(c)) if c.size else None,
        },
        "constraint_wrong": sorted(wrong),
        "road_cut": {
            "constraint": cut.constraint,
            "verified_without_the_floor": cut_verdict.verified,
            "translation_error_m": float(np.linalg.norm(cut.relative_pose[:3, 3] - [-15.0, 0, 0])),
        },
        "suggested_min_constraint": None if least is None else least / 2,
    }
    print(
        f"{args.town}: {len(right)} right closures verified (constraint least {least}, "
        f"median {record['constraint_right']['median']}), {len(wrong)} wrong; the road cut: "
        f"constraint {cut.constraint:.4f}, verified {cut_verdict.verified}, "
        f"{record['road_cut']['translation_error_m']:.1f} m off"
    )
    write_report(args.json, record)


if __name__ == "__main__":
    main()
