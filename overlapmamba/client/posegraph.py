"""A replayed drive's pose graph, for a SLAM back end: g2o's text format (``VERTEX_SE3:QUAT``,
``EDGE_SE3:QUAT``), written for g2o or for GTSAM's ``readG2o`` (other readers of the format
may take its information in yet another convention).

Each observed scan is a vertex at the drive's pose, numbered by its frame; consecutive
observed scans are joined by an odometry edge (their relative pose from the drive, with a
diagonal information from the given standard deviations: a drive's poses carry none); each
verified loop closure is an edge from its keyframe's vertex to the query scan's, its
relative pose and information from the server's answer (``LoopClosure.covariance``,
``overlapmamba.core.posecov``). A keyframe this replay inserted is its scan's vertex; one of
another drive (another robot's, an earlier session's) is a vertex of its own, numbered
after the drive's frames, at the pose the map stores for it. A closure without a
covariance (a server or model without its calibration) or whose keyframe has no pose is
left out and counted. The first scan's vertex is fixed (``FIX``).

The information is written for the reader that will read the file (``READERS``). g2o's
``EDGE_SE3:QUAT`` error takes the rotation as the quaternion's vector part, half the
rotation vector, so ``g2o`` writes ``posecov.g2o_information`` (the rotation's rows and
columns doubled); GTSAM's ``readG2o`` (4.2 and later) reads the same block as over the
rotation vector (it only swaps the blocks into its own order), so ``gtsam`` writes the
inverse covariance as it is. Either file read by the other back end weighs it as if every
rotation σ were halved or doubled, correlations kept (``benchmarks/g2o_check.py`` measures
both). GTSAM before 4.2 swaps only the diagonal blocks in ``readG2o`` and transposes the
cross ones: with a correlated covariance, build the factors from
``posecov.swap_blocks(covariance)`` there instead.

``overlapmamba-client observe DRIVE --map M --g2o FILE [--g2o-for gtsam]`` writes one.
"""

from __future__ import annotations

import contextlib
import itertools
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from overlapmamba.core import outfiles, posecov
from overlapmamba.core.poses import from_quaternion, quaternion

Edge = tuple[int, int, np.ndarray, np.ndarray]  # from, to, 4×4 measurement, 6×6 information


def _se3(T: np.ndarray) -> str:
    t, q = T[:3, 3], quaternion(T[:3, :3])
    return " ".join(f"{x:.17g}" for x in (*t, *q))


def _upper(info: np.ndarray) -> str:
    """g2o's information: the upper triangle, row by row."""
    return " ".join(f"{info[i, j]:.17g}" for i in range(6) for j in range(i, 6))


def _pose(pose: np.ndarray | list[float] | None) -> np.ndarray:
    """4 × 4, from a 4 × 4 or x, y, z, qx, qy, qz, qw (as drives and keyframes give it)."""
    p = np.asarray(pose, dtype=np.float64)
    return from_quaternion(p[:3], p[3:]) if p.shape == (7,) else p


READERS = ("g2o", "gtsam")  # whose reading of EDGE_SE3:QUAT's information a file is for


def file_information(covariance: np.ndarray, reader: str = "g2o") -> np.ndarray:
    """The ``EDGE_SE3:QUAT`` information of an edge of this covariance (``posecov``'s δ:
    translation, then rotation vector), as ``reader`` reads it (module docstring)."""
    if reader == "g2o":
        return posecov.g2o_information(covariance)
    if reader == "gtsam":
        info = np.linalg.inv(np.asarray(covariance, dtype=np.float64))
        return 0.5 * (info + info.T)
    raise ValueError(f"a pose graph's reader is one of {', '.join(READERS)}; got {reader!r}")


def odometry_information(sigma_m: float, sigma_deg: float, reader: str = "g2o") -> np.ndarray:
    """The information of an odometry edge whose translation and rotation are known to
    ``sigma_m`` and ``sigma_deg`` on each axis (independent), as ``reader`` reads it."""
    if not (sigma_m > 0 and sigma_deg > 0):
        raise ValueError(
            f"odometry standard deviations must be > 0; got {sigma_m} m and {sigma_deg}°"
        )
    cov = np.diag([sigma_m**2] * 3 + [np.deg2rad(sigma_deg) ** 2] * 3)
    return file_information(cov, reader)


@dataclass
class PoseGraph:
    """What a replay adds, in order: :meth:`scan` for each observed scan, :meth:`closure`
    for each verified loop closure; :meth:`write` once at the end (:meth:`written_to`
    keeps what a failed replay made). A scan's vertex is its
    frame number; a keyframe of another drive (another robot's, an earlier session's) is a
    vertex of its own, numbered from ``others_from``, at the pose the map stores for it,
    joined to the drive only by its loop edges."""

    odometry: np.ndarray  # (6, 6) information of every odometry edge, for ``reader``
    others_from: int  # the first vertex number of another drive's keyframe (> every frame)
    reader: str = "g2o"  # whose reading the information is written for (READERS)
    vertices: dict[int, np.ndarray] = field(default_factory=dict)  # vertex → pose
    keyframes: dict[str, int] = field(default_factory=dict)  # keyframe id → its vertex
    scans: list[int] = field(default_factory=list)  # the drive's vertices, in order
    loops: list[Edge] = field(default_factory=list)
    left_out: dict[str, int] = field(default_factory=dict)  # why a closure is not an edge
    others: int = 0  # another drive's keyframes made vertices so far
    incomplete: Path | None = None  # where a failed replay's graph was kept (written_to)
    lost: str | None = None  # why a failed replay's graph could not be kept
    write_failed: bool = False  # the replay ended, writing the graph at its path did not

    def __post_init__(self) -> None:
        if self.reader not in READERS:
            raise ValueError(
                f"a pose graph's reader is one of {', '.join(READERS)}; got {self.reader!r}"
            )

    @classmethod
    def for_reader(
        cls, sigma_m: float, sigma_deg: float, others_from: int, reader: str = "g2o"
    ) -> PoseGraph:
        """A graph whose every edge's information is written for ``reader``: the odometry's
        from its σ per axis (metres, degrees), each closure's from its covariance."""
        return cls(odometry_information(sigma_m, sigma_deg, reader), others_from, reader=reader)

    def scan(self, frame: int, pose: np.ndarray | None, keyframe_id: str | None) -> None:
        """Observed scan ``frame`` at ``pose`` (None: the drive has none there, so it is not
        a vertex), and the keyframe it became, if any."""
        if pose is None:
            return
        if frame >= self.others_from:
            raise ValueError(f"frame {frame} is not below others_from {self.others_from}")
        self.vertices[frame] = _pose(pose)
        self.scans.append(frame)
        if keyframe_id is not None:
            self.keyframes[keyframe_id] = frame

    def closure(
        self,
        frame: int,
        keyframe_id: str | None,
        relative_pose: np.ndarray | None,
        covariance: np.ndarray | None,
        keyframe_pose: np.ndarray | list[float] | None = None,
    ) -> bool:
        """A verified closure of scan ``frame`` onto ``keyframe_id`` (whose stored pose,
        ``keyframe_pose``, places it when it is another drive's): an edge when both ends are
        vertices and it carries a covariance; else counted in :attr:`left_out`."""
        why = None
        if relative_pose is None or keyframe_id is None:
            why = "no relative pose"
        elif covariance is None:
            why = "the answer carries no covariance (no calibration, or a loose direction)"
        elif frame not in self.vertices:
            why = "its scan has no pose"
        elif keyframe_id not in self.keyframes and keyframe_pose is None:
            why = "its keyframe is another drive's, with no pose in the answer"
        if why is not None:
            self.left_out[why] = self.left_out.get(why, 0) + 1
            return False
        assert relative_pose is not None and covariance is not None and keyframe_id is not None
        if keyframe_id not in self.keyframes:
            vertex = self.others_from + self.others
            self.others += 1
            self.keyframes[keyframe_id] = vertex
            self.vertices[vertex] = _pose(keyframe_pose)
        info = file_information(covariance, self.reader)
        self.loops.append((self.keyframes[keyframe_id], frame, relative_pose, info))
        return True

    def write(self, path: Path) -> None:
        """The graph as g2o text, written whole or not at all."""
        frames = sorted(self.scans)
        lines = [f"VERTEX_SE3:QUAT {i} {_se3(self.vertices[i])}" for i in sorted(self.vertices)]
        for a, b in itertools.pairwise(frames):
            rel = np.linalg.inv(self.vertices[a]) @ self.vertices[b]
            lines.append(f"EDGE_SE3:QUAT {a} {b} {_se3(rel)} {_upper(self.odometry)}")
        for a, b, rel, info in self.loops:
            lines.append(f"EDGE_SE3:QUAT {a} {b} {_se3(rel)} {_upper(info)}")
        if frames:
            lines.append(f"FIX {frames[0]}")
        outfiles.write_whole(path, "\n".join(lines) + "\n")

    @contextlib.contextmanager
    def written_to(self, path: Path) -> Iterator[None]:
        """The graph written to ``path`` when the block ends. Where the block raises (the
        server gone, Ctrl-C), or writing it there fails (a full disk), the graph so far, if
        it holds a scan, goes beside it instead, to ``NAME.incomplete.g2o`` (``-2``, … : an
        earlier one is never replaced), named in :attr:`incomplete` (or why it could not be
        kept in :attr:`lost`), and the error goes on; what stood at ``path`` stays."""
        try:
            yield
        except BaseException:
            self._keep(path)
            raise
        try:
            self.write(path)
        except BaseException:
            self.write_failed = True
            self._keep(path)
            raise

    def _keep(self, path: Path) -> None:
        if not self.scans:
            return
        try:
            kept = outfiles.incomplete_path(path, ".g2o")
            self.write(kept)
            self.incomplete = kept
        except BaseException as err:  # Ctrl-C too: the error that brought us here goes on
            self.lost = f"{type(err).__name__}: {err}"


def read_g2o(path: Path) -> tuple[dict[int, np.ndarray], list[Edge]]:
    """A g2o file's SE(3) vertices (id → 4×4 pose) and edges (from, to, 4×4 measurement,
    6×6 information), as :meth:`PoseGraph.write` writes them."""
    vertices: dict[int, np.ndarray] = {}
    edges: list[Edge] = []
    for n, line in enumerate(path.read_text().splitlines(), start=1):
        f = line.split()
        if not f or f[0] == "FIX":
            continue
        if f[0] == "VERTEX_SE3:QUAT" and len(f) == 9:
            v = [float(x) for x in f[2:]]
            vertices[int(f[1])] = from_quaternion(v[:3], v[3:])
        elif f[0] == "EDGE_SE3:QUAT" and len(f) == 31:
            v = [float(x) for x in f[3:10]]
            info = np.zeros((6, 6))
            info[np.triu_indices(6)] = [float(x) for x in f[10:]]
            info = info + np.triu(info, 1).T
            edges.append((int(f[1]), int(f[2]), from_quaternion(v[:3], v[3:]), info))
        else:
            raise ValueError(f"{path}:{n}: not a VERTEX_SE3:QUAT, EDGE_SE3:QUAT or FIX line")
    return vertices, edges
