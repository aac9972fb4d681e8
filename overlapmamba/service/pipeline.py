"""Scan bytes → descriptor, in one direction and in one place.

    ScanBody (bytes as received: media type, point fields, Content-Encoding)
      ─ worker thread ─ decode: decompress, parse → PointCloud
                        project: the scan's sensor into the model's input (its range
                        projection, overlapmamba.service.sensors) → (V, H, W) views
      ─ MicroBatcher ── waits at most batching.max_wait_ms for scans still being decoded
      ─ encoder thread  encode: Encoder.encode on the stacked batch
        (meanwhile, when the caller will verify: a worker thread prepares the points for
        registration — hidden behind the encoder's wait — in a registration process, or in
        the thread itself with verify.processes 0: overlapmamba.service.registrar)
      → Description (unit descriptor, yaw features, the points, the prepared query, stage
        timings)

Two thread hops per scan: one for decode + project, one (shared by a micro-batch) for the
encoder; a third, in parallel with the encoder, when the answer will be verified. The
encoder's graph ends in an L2 normalisation, so descriptors leave here unit norm; nothing
downstream normalises them again.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from overlapmamba.core.points import PointCloud
from overlapmamba.core.sensors import Sensor
from overlapmamba.core.sensors.input import SensorInput
from overlapmamba.core.sensors.profile import SensorProfile
from overlapmamba.service.batcher import MicroBatcher
from overlapmamba.service.encoder import Encoder
from overlapmamba.service.errors import BadRequest, Unprocessable
from overlapmamba.service.registrar import Held, Registrar
from overlapmamba.service.registration import RegistrationParams
from overlapmamba.service.scans import ScanBody, decode_scan
from overlapmamba.service.settings import BatchSettings, LimitSettings
from overlapmamba.service.threads import encoder_threads, in_thread


@dataclass(frozen=True)
class Description:
    descriptor: np.ndarray  # (D,) float32, unit norm
    yaw: np.ndarray  # (C, W) float32 yaw features
    points: PointCloud  # kept for the content hash and geometry of a keyframe
    timings: dict[str, float]  # ms: decode, project, encode
    prepared: Held | None = None  # the query's side of registration, when asked for


def check_rings(points: PointCloud, sensor: Sensor | None) -> None:
    """A cloud whose ``ring`` field (a PointCloud2's) numbers more rings than its sensor has
    beams is not that sensor's scan: refused (400) with both counts, so the robot names its
    sensor instead of being projected as another's. Nothing is inferred from the rings."""
    if points.ring is None or sensor is None or not len(points.ring):
        return
    low, high = int(points.ring.min()), int(points.ring.max())
    if low < 0 or high >= sensor.beams:
        raise BadRequest(
            f"the cloud's ring field runs {low}–{high}, but it is projected as sensor "
            f"{sensor.name!r}, which has {sensor.beams} beams (rings 0–{sensor.beams - 1}): "
            "name the scan's sensor with ?sensor= (GET /v1/sensors lists them)",
            code="sensor_mismatch",
            sensor=sensor.name,
            beams=sensor.beams,
            rings=[low, high],
        )


def check_in_range(
    image: np.ndarray, model: SensorProfile, sensor: SensorInput | None, points: int
) -> None:
    """A scan none of whose points lies within the sensor's range (all at the origin, or
    all beyond ``max_range``) projects to an image with no point: its descriptor would be
    the empty image's, which matches every other empty scan, and is refused (422)."""
    if np.any(image != np.float32(model.empty_value)):
        return
    name = sensor.sensor.name if sensor is not None else model.name
    low, high = sensor.reach if sensor is not None else (model.min_range, model.max_range)
    raise Unprocessable(
        f"no point of the scan's {points} lies within the range the model takes from sensor "
        f"{name!r} ({low:g} m < range < {high:g} m), in the rows of its beams: the scan holds "
        "no geometry to describe (are the coordinates in metres, in the sensor's frame?)",
        code="no_points_in_range",
        sensor=name,
        min_range=low,
        max_range=high,
    )


class ScanPipeline:
    def __init__(
        self,
        encoder: Encoder,
        batching: BatchSettings,
        limits: LimitSettings,
        on_batch: Callable[[int, float], None] | None = None,
        registrar: Registrar | None = None,
    ) -> None:
        self.encoder = encoder
        self.limits = limits
        self.registrar = registrar or Registrar()  # where registration runs (verify.processes)
        self.batcher = MicroBatcher(
            encoder.encode,
            max_batch=batching.max_batch,
            max_wait_ms=batching.max_wait_ms,
            queue_size=batching.queue_size,
            lanes=encoder_threads(batching.lanes, batching.intra_op_threads)[0],
            on_batch=on_batch,
        )

    async def start(self) -> None:
        await self.batcher.start()
        self.registrar.start()

    async def stop(self) -> None:
        await self.batcher.stop()
        await in_thread(self.registrar.stop)

    @property
    def pending(self) -> int:
        """Scans waiting for the encoder."""
        return self.batcher.pending

    def _prepare(
        self, scan: ScanBody, sensor: SensorInput | None
    ) -> tuple[np.ndarray, float, PointCloud, dict[str, float]]:
        t0 = time.perf_counter()
        points = decode_scan(scan, self.limits)
        check_rings(points, sensor.sensor if sensor is not None else None)
        t1 = time.perf_counter()
        image, offset = self.encoder.project_offset(points, sensor)
        check_in_range(image, self.encoder.meta.profile, sensor, len(points.xyz))
        t2 = time.perf_counter()
        return image, offset, points, {"decode": (t1 - t0) * 1e3, "project": (t2 - t1) * 1e3}

    async def describe(
        self,
        scan: ScanBody,
        registration: RegistrationParams | None = None,
        sensor: SensorInput | None = None,
    ) -> Description:
        """``registration``: also prepare the points for verification, while the encoder
        works (its wait, if any, is added to the encode stage). ``sensor``: the scan's
        sensor as the model takes it (None: the model's own); where the model file carries
        a map for that sensor (:mod:`overlapmamba.core.sensormaps`), the descriptor is
        mapped into the model sensor's space."""
        with self.batcher.incoming():
            image, offset, points, timings = await in_thread(self._prepare, scan, sensor)
        t0 = time.perf_counter()
        task = None
        if registration is not None:
            task = asyncio.ensure_future(
                in_thread(self.registrar.prepare, points.xyz, registration)
            )
        try:
            desc, yaw = await self.batcher.encode(
                image, offset, timeout_s=self.limits.request_timeout_s
            )
            prepared = await task if task is not None else None
        finally:
            if task is not None and not task.done():
                task.cancel()
        timings["encode"] = (time.perf_counter() - t0) * 1e3
        desc = self.encoder.to_model_space(desc, sensor)
        return Description(np.asarray(desc), np.asarray(yaw), points, timings, prepared)
