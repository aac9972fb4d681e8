"""The service's work, independent of HTTP: scan → descriptor → index → answer.

Routes (``service.api``) and the WebSocket stream call these; they parse and authorise,
this module decides. Blocking work (decoding, projection, FAISS, SQLite) runs in worker
threads; encoding goes through the micro-batcher.
"""

from __future__ import annotations

import hashlib
import math
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np
from starlette.concurrency import run_in_threadpool

from lidar_core.points import PointCloud
from service.backend import Filters, InsertResult, MapBackend, PlaceMap, content_hash
from service.batcher import MicroBatcher
from service.bodies import decode_scan
from service.encoder import Encoder
from service.errors import BadRequest, Conflict, Unprocessable
from service.schemas import POSE_FORMAT
from service.settings import Settings
from service.stats import Stats
from service.store import NewKeyframe


def parse_pose(text: str | None) -> list[float] | None:
    if text is None or text == "":
        return None
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    return check_pose(values, text)


def check_pose(values: list[float], text: object = None) -> list[float]:
    """7 finite numbers with a non-zero quaternion → the pose with a unit quaternion."""
    shown = values if text is None else text
    if len(values) != 7 or not all(math.isfinite(v) for v in values):
        raise BadRequest(f"pose {shown!r} is not valid; allowed: {POSE_FORMAT}", code="bad_pose")
    q = np.array(values[3:], dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if not 1e-6 < norm < 1e6:
        raise BadRequest(
            f"pose {shown!r} has a quaternion of norm {norm:.3g}; allowed: {POSE_FORMAT}",
            code="bad_pose",
        )
    return [float(v) for v in values[:3]] + [float(v) for v in q / norm]


def check_descriptor(values: list[float] | np.ndarray, dim: int) -> np.ndarray:
    d = np.asarray(values, dtype=np.float64)
    if d.shape != (dim,):
        raise Unprocessable(
            f"descriptor has {d.size} values; allowed: exactly {dim}",
            code="bad_descriptor",
            dim=dim,
        )
    if not np.isfinite(d).all():
        raise Unprocessable("descriptor has NaN or infinite values", code="bad_descriptor")
    norm = float(np.linalg.norm(d))
    if not 1e-6 < norm < 1e6:
        raise Unprocessable(
            f"descriptor has norm {norm:.3g}; allowed: a unit vector (norm near 1)",
            code="bad_descriptor",
        )
    return (d / norm).astype(np.float32)


@dataclass
class Described:
    descriptor: np.ndarray  # (D,)
    yaw: np.ndarray  # (C, W)
    points: PointCloud  # kept for the content hash, computed only when it is inserted
    timings: dict[str, float]


@dataclass
class Observed:
    answer: dict[str, Any]
    inserted: bool
    keyframe_id: str | None
    reason: str

    def public(self) -> dict[str, Any]:
        return {
            **self.answer,
            "inserted": self.inserted,
            "keyframe_id": self.keyframe_id,
            "insert_reason": self.reason,
        }


class PlaceService:
    def __init__(self, settings: Settings, encoder: Encoder, registry: MapBackend) -> None:
        self.settings = settings
        self.encoder = encoder
        self.registry = registry
        self.stats = Stats(encoder.model_id)
        b = settings.batching
        self.batcher = MicroBatcher(
            encoder.encode,
            max_batch=b.max_batch,
            max_wait_ms=b.max_wait_ms,
            queue_size=b.queue_size,
            on_batch=self.stats.batch,
        )
        # (map, robot) -> (timestamp, position) of its last keyframe, for insert=auto; bounded
        # (robot ids come from clients), a dropped entry is read back from the store
        self._last_kf: OrderedDict[tuple[str, str], tuple[float, np.ndarray | None]] = OrderedDict()

    @property
    def model_id(self) -> str:
        return self.encoder.model_id

    def forget_map(self, map_id: str) -> None:
        self.stats.forget_map(map_id)
        for key in [k for k in self._last_kf if k[0] == map_id]:
            del self._last_kf[key]

    # ---- scan → descriptor ------------------------------------------------------------------

    def _decode_project(
        self, body: bytes, content_type: str | None, fields: str | None, source: str
    ) -> tuple[np.ndarray, PointCloud, float, float]:
        t0 = time.perf_counter()
        points = decode_scan(body, content_type, fields, self.settings.limits, source=source)
        t1 = time.perf_counter()
        image = self.encoder.project(points)
        t2 = time.perf_counter()
        return image, points, (t1 - t0) * 1e3, (t2 - t1) * 1e3

    async def describe(
        self, body: bytes, content_type: str | None, fields: str | None, *, source: str = "scan"
    ) -> Described:
        image, points, t_dec, t_proj = await run_in_threadpool(
            self._decode_project, body, content_type, fields, source
        )
        t0 = time.perf_counter()
        desc, yaw = await self.batcher.encode(
            image, timeout_s=self.settings.limits.request_timeout_s
        )
        t_enc = (time.perf_counter() - t0) * 1e3
        timings = {"decode": t_dec, "project": t_proj, "encode": t_enc}
        return Described(np.asarray(desc), np.asarray(yaw), points, timings)

    # ---- maps ---------------------------------------------------------------------------------

    async def map(self, map_id: str) -> PlaceMap:
        """The map, looked up off the event loop (the Qdrant backend may ask its server)."""
        return await run_in_threadpool(self.registry.get, map_id)

    def check_model(self, m: PlaceMap) -> None:
        if m.model_id != self.model_id:
            raise Conflict(
                f"map {m.map_id!r} holds descriptors of model {m.model_id!r}; this service "
                f"runs {self.model_id!r}, whose descriptors are not comparable",
                code="model_mismatch",
                map_model_id=m.model_id,
                model_id=self.model_id,
            )

    async def insert(
        self, m: PlaceMap, rows: list[NewKeyframe], robot: str | None
    ) -> list[InsertResult]:
        self.check_model(m)
        results = await run_in_threadpool(m.insert, rows)
        created = sum(r.created for r in results)
        if created:
            self.stats.insert(m.map_id, robot, created)
            count = await run_in_threadpool(lambda: m.count)
            self.stats.p_keyframes.labels(m.map_id).set(count)
            for r in results:
                if r.created:
                    self._remember(
                        m.map_id, r.keyframe.robot_id, r.keyframe.timestamp, r.keyframe.pose
                    )
        m.maintain()
        return results

    async def scan_keyframe(
        self,
        described: Described,
        *,
        keyframe_id: str,
        robot_id: str,
        session_id: str,
        timestamp: float,
        pose: list[float] | None,
    ) -> NewKeyframe:
        meta = {"robot": robot_id, "session": session_id, "timestamp": timestamp, "pose": pose}
        xyzi = described.points.as_xyzi()
        digest = await run_in_threadpool(lambda: hashlib.sha256(xyzi.tobytes()).digest())
        return NewKeyframe(
            keyframe_id=keyframe_id,
            robot_id=robot_id,
            session_id=session_id,
            timestamp=timestamp,
            pose=pose,
            descriptor=described.descriptor,
            yaw=described.yaw,
            content_hash=content_hash("scan", digest, meta),
        )

    async def query(
        self,
        m: PlaceMap,
        descriptor: np.ndarray,
        yaw: np.ndarray | None,
        k: int,
        filters: Filters,
        timings: dict[str, float],
        *,
        robot: str | None = None,
    ) -> dict[str, Any]:
        self.check_model(m)
        if not 1 <= k <= self.settings.limits.max_k:
            raise BadRequest(f"k={k} is out of range; allowed: 1 to {self.settings.limits.max_k}")
        t0 = time.perf_counter()
        # One more than asked: the runner-up gives the loop-closure margin.
        matches = await run_in_threadpool(m.search, descriptor, k + 1, filters, yaw)
        timings["search"] = (time.perf_counter() - t0) * 1e3
        lc = self.settings.loop_closure
        margin = matches[1].distance - matches[0].distance if len(matches) > 1 else None
        accepted = bool(
            matches
            and matches[0].distance <= lc.max_distance
            and (margin is None or margin >= lc.min_margin)
        )
        self.stats.query(m.map_id, robot, accepted)
        return {
            "matches": [x.public() for x in matches[:k]],
            "loop_closure": {
                "accepted": accepted,
                "threshold": lc.max_distance,
                "margin_top1_top2": margin,
            },
            "timings_ms": timings,
        }

    # ---- the robot's round trip -------------------------------------------------------------

    def _remember(
        self, map_id: str, robot: str, timestamp: float, pose: list[float] | None
    ) -> None:
        pos = None if pose is None else np.array(pose[:3])
        old = self._last_kf.pop((map_id, robot), None)
        self._last_kf[(map_id, robot)] = old if old and old[0] > timestamp else (timestamp, pos)
        while len(self._last_kf) > 10_000:
            self._last_kf.popitem(last=False)

    async def _last(self, m: PlaceMap, robot: str) -> tuple[float, np.ndarray | None] | None:
        key = (m.map_id, robot)
        if key not in self._last_kf:
            kf = await run_in_threadpool(m.last_keyframe, robot)
            if kf is None:
                return None
            self._remember(m.map_id, robot, kf.timestamp, kf.pose)
        return self._last_kf.get(key)

    async def insert_due(
        self, m: PlaceMap, robot: str, timestamp: float, pose: list[float] | None, mode: str
    ) -> str | None:
        """Why this observation becomes a keyframe, or None if it does not."""
        if mode == "always":
            return "always"
        if mode == "never":
            return None
        last = await self._last(m, robot)
        if last is None:
            return "first"
        o = self.settings.observe
        if abs(timestamp - last[0]) >= o.insert_min_interval_s:
            return "time"
        if pose is None or last[1] is None:
            return None
        moved = float(np.linalg.norm(np.array(pose[:3]) - last[1]))
        return "distance" if moved >= o.insert_min_distance_m else None

    async def observe(
        self,
        m: PlaceMap,
        described: Described,
        *,
        robot_id: str,
        session_id: str,
        timestamp: float,
        pose: list[float] | None,
        insert: str,
        k: int,
    ) -> Observed:
        filters = Filters(
            exclude_recent_s=self.settings.observe.exclude_recent_s,
            session_id=session_id,
            timestamp=timestamp,
        )
        timings = dict(described.timings)
        answer = await self.query(
            m, described.descriptor, described.yaw, k, filters, timings, robot=robot_id
        )
        reason = await self.insert_due(m, robot_id, timestamp, pose, insert)
        keyframe_id = None
        inserted = False
        if reason is not None:
            keyframe_id = f"{robot_id}:{session_id}:{timestamp!r}"
            row = await self.scan_keyframe(
                described,
                keyframe_id=keyframe_id,
                robot_id=robot_id,
                session_id=session_id,
                timestamp=timestamp,
                pose=pose,
            )
            (result,) = await self.insert(m, [row], robot_id)
            inserted = result.created
            if not inserted:
                reason = "existing"
        return Observed(
            answer, inserted, keyframe_id, reason or ("never" if insert == "never" else "not_due")
        )
