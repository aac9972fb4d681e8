"""Memory of a bag's transform tree: bytes a /tf sample, held and at the lookup, the shipped
:class:`overlapmamba.core.tf_tree.TransformTree` against a list of 4×4 arrays a link (how it
held them up to 2026-12-04).

Replaying a bag whose poses come from /tf reads every transform of the drive into the tree
before the first scan is sent, every link's, not only the chain to the LiDAR (a robot's /tf
carries its wheels, arms and estimators too). This builds such a tree: ``--links`` timed
links at ``--rate-hz`` for ``--minutes``, a static sensor link, then looks up the sensor's
pose at 10 Hz (a scan's rate), measured with tracemalloc, one way after the other. It
reports bytes a sample held, the lookup's peak above that, the samples an hour of such a
/tf holds and what they would take, and that both ways give the same poses.
Writes reports/client/tf_memory.json.
"""

from __future__ import annotations

import argparse
import gc
import time
import tracemalloc
from pathlib import Path

import numpy as np
from reports_kit import REPORTS, write_report

from overlapmamba.core.poses import rotation_z
from overlapmamba.core.tf_tree import TransformTree, interpolate

S = 10**9


class ListTree:
    """The storage before: per link a list of stamps and a list of 4×4 arrays, stacked
    and sorted at each lookup; one link's lookup, interpolated as the tree does."""

    def __init__(self) -> None:
        self.links: dict[str, tuple[list[int], list[np.ndarray]]] = {}

    def add(self, child: str, stamp_ns: int, T: np.ndarray) -> None:
        stamps, transforms = self.links.setdefault(child, ([], []))
        stamps.append(int(stamp_ns))
        transforms.append(np.asarray(T, dtype=np.float64))

    def lookup(self, child: str, at: np.ndarray) -> np.ndarray:
        stamps, transforms = self.links[child]
        t = np.asarray(stamps, dtype=np.int64)
        order = np.argsort(t, kind="stable")
        t, T = t[order], np.stack(transforms)[order]
        after = np.searchsorted(t, at, side="right")
        lo, hi = np.clip(after - 1, 0, None), np.clip(after, None, len(t) - 1)
        span = (t[hi] - t[lo]).astype(np.float64)
        a = np.divide(at - t[lo], span, out=np.zeros(len(at)), where=span > 0)
        return interpolate(T[lo], T[hi], a)


def sample(i: int, link: int) -> np.ndarray:
    T = rotation_z(0.01 * i + link)
    T[:3, 3] = (0.02 * i, 0.01 * link, 0.001 * i)
    return T


def measure(way: str, links: int, samples: int, step_ns: int, at: np.ndarray) -> dict:
    gc.collect()
    tracemalloc.start()
    t0 = time.perf_counter()
    tree: TransformTree | ListTree = TransformTree() if way == "shipped" else ListTree()
    for i in range(samples):
        for link in range(links):
            parent = "odom" if link == 0 else "base"
            if isinstance(tree, TransformTree):
                tree.add(parent, f"l{link}", i * step_ns, sample(i, link))
            else:
                tree.add(f"l{link}", i * step_ns, sample(i, link))
    if isinstance(tree, TransformTree):
        tree.add("l0", "lidar", 0, np.eye(4), static=True)
    added = time.perf_counter() - t0
    held = tracemalloc.get_traced_memory()[0]
    tracemalloc.reset_peak()
    if isinstance(tree, TransformTree):
        poses = tree.lookup("odom", "lidar", at)
    else:
        poses = tree.lookup("l0", at)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    n = samples * links
    return {
        "samples": n,
        "held_bytes_per_sample": held / n,
        "lookup_peak_above_held_bytes_per_sample": (peak - held) / n,
        "add_s_under_tracemalloc": added,
        "poses": poses,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--links", type=int, default=12)
    ap.add_argument("--rate-hz", type=float, default=100.0)
    ap.add_argument("--minutes", type=float, default=5.0)
    ap.add_argument("--json", type=Path, default=REPORTS / "client" / "tf_memory.json")
    args = ap.parse_args()

    step_ns = int(S / args.rate_hz)
    samples = int(args.minutes * 60 * args.rate_hz)
    at = np.arange(0, samples * step_ns, S // 10) + step_ns // 3  # 10 Hz, between samples
    ways = {w: measure(w, args.links, samples, step_ns, at) for w in ("list", "shipped")}
    diff = float(np.abs(ways["list"].pop("poses") - ways["shipped"].pop("poses")).max())
    hour = int(3600 * args.rate_hz * args.links)
    record = {
        "benchmark": "tf_memory",
        "tf": {"links": args.links, "rate_hz": args.rate_hz, "minutes": args.minutes},
        "ways": ways,
        "held_ratio": ways["list"]["held_bytes_per_sample"]
        / ways["shipped"]["held_bytes_per_sample"],
        "an_hour": {
            "samples": hour,
            "held_mb": {w: hour * r["held_bytes_per_sample"] / 1e6 for w, r in ways.items()},
        },
        "max_abs_pose_difference": diff,
    }
    for way, r in ways.items():
        print(
            f"{way}: {r['held_bytes_per_sample']:.0f} B a sample held, "
            f"{r['lookup_peak_above_held_bytes_per_sample']:.0f} more at the lookup; "
            f"an hour ({hour:,} samples): {record['an_hour']['held_mb'][way]:.0f} MB"
        )
    print(f"poses differ by at most {diff:.1e}")
    write_report(args.json, record)


if __name__ == "__main__":
    main()
