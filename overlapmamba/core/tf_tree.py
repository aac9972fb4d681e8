"""A transform tree as ROS tf keeps one: frames joined by parent → child transforms, each
either static or a time series, looked up between any two connected frames at given times.

    tree = TransformTree()
    tree.add("odom", "base_link", stamp_ns, T)              # from /tf
    tree.add("base_link", "velodyne", 0, M, static=True)    # from /tf_static
    poses = tree.lookup("odom", "velodyne", scan_stamps_ns, max_gap_s=0.1)

``lookup(target, source, …)`` returns T_target←source (maps ``source``-frame points into
``target``; for a sensor frame, its pose in ``target``) at each time: the chain up to the
two frames' common ancestor is composed, each time-varying link interpolated between the
samples around the time (translation linearly, rotation along the great arc). Unlike tf2,
a time up to ``max_gap_s`` past either end of a link's samples takes the end sample, and a
time whose nearest sample is farther than ``max_gap_s`` is refused, naming the link. A frame
has one parent: tf2 lets a frame change parents over time (a tracker that moves a person's
frame from ``odom`` to ``map``); here the first parent is kept, and a lookup whose chain
passes through such a frame is refused, naming both parents. Other lookups are answered.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from overlapmamba.core.errors import DatasetError
from overlapmamba.core.poses import from_quaternion, quaternion

CHUNK = 4096  # samples a block: appends never copy what is held, and a block is 416 kB


@dataclass
class _Link:
    """One parent → child link: a static transform, or its samples in blocks of arrays (a
    timestamp and the top 3×4 of the transform: 104 bytes a sample, where a list of 4×4
    arrays took ≈ 300; an hour of a robot's /tf at 100 Hz on a dozen links is 4 million
    samples: benchmarks/tf_memory.py)."""

    parent: str
    static: np.ndarray | None = None
    n: int = 0
    _t: list[np.ndarray] = field(default_factory=list)
    _T: list[np.ndarray] = field(default_factory=list)

    def append(self, stamp_ns: int, T: np.ndarray) -> None:
        i = self.n % CHUNK
        if i == 0:
            self._t.append(np.empty(CHUNK, np.int64))
            self._T.append(np.empty((CHUNK, 3, 4)))
        self._t[-1][i] = stamp_ns
        self._T[-1][i] = T[:3]
        self.n += 1

    def samples(self) -> tuple[np.ndarray, np.ndarray]:
        """The samples in time order: (n,) int64 stamps and their (n, 3, 4) transforms'
        top rows (sorted only where they arrived out of order)."""
        t = np.concatenate(self._t)[: self.n]
        T = np.concatenate(self._T)[: self.n]
        if (np.diff(t) < 0).any():
            order = np.argsort(t, kind="stable")
            t, T = t[order], T[order]
        return t, T


class TransformTree:
    def __init__(self) -> None:
        self._links: dict[str, _Link] = {}  # child frame -> its link to its parent
        # child frame -> the parents it was sent with after its first (tf2's re-parenting)
        self._reparented: dict[str, list[str]] = {}

    def add(
        self, parent: str, child: str, stamp_ns: int, transform: np.ndarray, *, static: bool = False
    ) -> None:
        """T_parent←child at ``stamp_ns`` (any time, when ``static``). A frame has one
        parent: a transform from another is noted, not kept, and refuses only the lookups
        through that frame. A static link that is sent again is replaced (as /tf_static
        latches)."""
        if not parent or not child or parent == child:
            raise DatasetError(f"transform {parent!r} → {child!r}: frames must be named and differ")
        T = np.asarray(transform, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise DatasetError(f"transform {parent!r} → {child!r} is not a finite 4×4 matrix")
        if T[3].tolist() != [0.0, 0.0, 0.0, 1.0]:
            raise DatasetError(
                f"transform {parent!r} → {child!r} is not rigid: its last row is {T[3].tolist()}, "
                "allowed: [0, 0, 0, 1]"
            )
        link = self._links.get(child)
        if link is None:
            link = self._links[child] = _Link(parent)
        if link.parent != parent:
            others = self._reparented.setdefault(child, [])
            if parent not in others:
                others.append(parent)
            return
        if static:
            link.static = T
        else:
            link.append(int(stamp_ns), T)

    @property
    def frames(self) -> list[str]:
        return sorted({*self._links, *(link.parent for link in self._links.values())})

    def lookup(
        self,
        target: str,
        source: str,
        stamps_ns: np.ndarray,
        *,
        max_gap_s: float = 0.1,
        gaps: str = "raise",
    ) -> np.ndarray:
        """(N, 4, 4) T_target←source at each of ``stamps_ns`` (N,). Raises DatasetError
        naming an unknown frame, frames in different trees, or a link without a sample
        within ``max_gap_s`` of a time; with ``gaps="nan"`` such a time's transform is NaN
        instead (a raise still when no time has one)."""
        if gaps not in ("raise", "nan"):
            raise ValueError(f"gaps must be 'raise' or 'nan', got {gaps!r}")
        stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        for frame in (target, source):
            if frame not in self.frames:
                # reached, perhaps, only as a second parent: of a frame on the other's chain
                # first (the one this lookup would pass through)
                other = source if frame == target else target
                near = self._chain(other) if other in self.frames else []
                children = [c for c, others in self._reparented.items() if frame in others]
                children.sort(key=lambda c: c not in near)
                if children:
                    raise self._two_parents(children[0], source, target)
                raise DatasetError(
                    f"frame {frame!r} is in no transform; frames: "
                    f"{', '.join(self.frames) or 'none'}",
                    frames=self.frames,
                )
        up_source, up_target = self._chain(source), self._chain(target)
        common = next((f for f in up_target if f in up_source), None)
        if common is None:
            for frame in up_source + up_target:  # joined, perhaps, by a second parent
                if frame in self._reparented:
                    raise self._two_parents(frame, source, target)
            raise DatasetError(
                f"frames {target!r} and {source!r} are not connected (their roots are "
                f"{up_target[-1]!r} and {up_source[-1]!r})"
            )
        for frame in up_source[: up_source.index(common)] + up_target[: up_target.index(common)]:
            if frame in self._reparented:
                raise self._two_parents(frame, source, target)
        nan = gaps == "nan"
        root_source = self._compose(up_source[: up_source.index(common)], stamps, max_gap_s, nan)
        root_target = self._compose(up_target[: up_target.index(common)], stamps, max_gap_s, nan)
        missing = np.isnan(root_source).any(axis=(1, 2)) | np.isnan(root_target).any(axis=(1, 2))
        out: np.ndarray = np.full((len(stamps), 4, 4), np.nan)
        out[~missing] = np.linalg.inv(root_target[~missing]) @ root_source[~missing]
        if len(stamps) and missing.all():  # no time has one: say which link lacks it
            self._compose(up_source[: up_source.index(common)], stamps, max_gap_s, False)
            self._compose(up_target[: up_target.index(common)], stamps, max_gap_s, False)
        return out

    def _two_parents(self, frame: str, source: str, target: str) -> DatasetError:
        parents = [self._links[frame].parent, *self._reparented[frame]]
        return DatasetError(
            f"frame {frame!r} has two parents, {parents[0]!r} and {parents[1]!r}, and lies "
            f"between {source!r} and {target!r}; a transform tree allows one parent a frame",
            frame=frame,
            parents=parents,
        )

    def _chain(self, frame: str) -> list[str]:
        """The frame, its parent, …, its root."""
        chain = [frame]
        while chain[-1] in self._links:
            parent = self._links[chain[-1]].parent
            if parent in chain:
                raise DatasetError(f"the transforms form a cycle: {' → '.join([*chain, parent])}")
            chain.append(parent)
        return chain

    def _compose(
        self, frames: list[str], stamps: np.ndarray, max_gap_s: float, nan: bool
    ) -> np.ndarray:
        """T_ancestor←frames[0] for a chain of child frames below the ancestor."""
        out = np.tile(np.eye(4), (len(stamps), 1, 1))
        for child in frames:
            out = self._at(child, stamps, max_gap_s, nan) @ out
        return out

    def _at(self, child: str, stamps: np.ndarray, max_gap_s: float, nan: bool) -> np.ndarray:
        link = self._links[child]
        if link.static is not None and not link.n:
            return np.broadcast_to(link.static, (len(stamps), 4, 4))
        if link.static is not None:
            raise DatasetError(f"link {link.parent!r} → {child!r} is both static and timed")
        t, top = link.samples()
        after = np.searchsorted(t, stamps, side="right")  # the first sample later
        lo = np.clip(after - 1, 0, None)  # before the first sample: the first
        hi = np.clip(after, None, len(t) - 1)  # past the last: the last
        gap = np.minimum(np.abs(t[lo] - stamps), np.abs(t[hi] - stamps)) / 1e9
        if len(stamps) and gap.max() > max_gap_s and (not nan or (gap > max_gap_s).all()):
            i = int(gap.argmax())
            raise DatasetError(
                f"no transform {link.parent!r} → {child!r} within {max_gap_s} s of time "
                f"{stamps[i] / 1e9:.3f} s (nearest {gap[i]:.3f} s away; it has "
                f"{t[0] / 1e9:.3f}–{t[-1] / 1e9:.3f} s)"
            )
        span = (t[hi] - t[lo]).astype(np.float64)
        a = np.divide(stamps - t[lo], span, out=np.zeros(len(stamps)), where=span > 0)
        out = interpolate(_full(top[lo]), _full(top[hi]), a)
        out[gap > max_gap_s] = np.nan  # only with ``nan``: else raised above
        return out


def _full(top: np.ndarray) -> np.ndarray:
    """(N, 4, 4) rigid transforms from their top (N, 3, 4) rows."""
    out = np.zeros((len(top), 4, 4))
    out[:, :3] = top
    out[:, 3, 3] = 1.0
    return out


def interpolate(T0: np.ndarray, T1: np.ndarray, a: np.ndarray) -> np.ndarray:
    """(N, 4, 4) transforms a of the way from T0 to T1 (N, 4, 4): translation linearly,
    rotation by spherical linear interpolation of the quaternions. At a = 0 (a sample's own
    time) T0 itself."""
    a = np.asarray(a, dtype=np.float64)
    out = np.array(T0, dtype=np.float64)
    mid = a > 0
    if mid.any():
        out[mid] = _slerp(out[mid], np.asarray(T1, dtype=np.float64)[mid], a[mid])
    return out


def _slerp(T0: np.ndarray, T1: np.ndarray, a: np.ndarray) -> np.ndarray:
    q0 = np.array([quaternion(m[:3, :3]) for m in T0])
    q1 = np.array([quaternion(m[:3, :3]) for m in T1])
    dot = np.sum(q0 * q1, axis=1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)  # the shorter arc
    theta = np.arccos(np.clip(np.abs(dot), -1.0, 1.0))
    sin = np.sin(theta)
    small = sin < 1e-9
    w0 = np.where(small, 1 - a, np.sin((1 - a) * theta) / np.where(small, 1, sin))
    w1 = np.where(small, a, np.sin(a * theta) / np.where(small, 1, sin))
    q = w0[:, None] * q0 + w1[:, None] * q1
    xyz = (1 - a)[:, None] * T0[:, :3, 3] + a[:, None] * T1[:, :3, 3]
    return np.stack([from_quaternion(p, r) for p, r in zip(xyz, q, strict=True)])
