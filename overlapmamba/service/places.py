"""The service's use cases, independent of HTTP: scan → descriptor → map → answer.

Routes and the WebSocket stream (``overlapmamba.service.api``) parse their transport, authorise,
open the map (:meth:`PlaceService.open_map`, which refuses another model's map) and call one method
here; it returns a dataclass, which the route turns into its HTTP shape. Scans go through
:class:`~overlapmamba.service.pipeline.ScanPipeline`; map work (FAISS, SQLite, Qdrant) runs in
worker threads.
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Sequence
from contextlib import nullcontext
from dataclasses import replace

import numpy as np

from overlapmamba.core.rerank import OFF
from overlapmamba.core.sensors.input import SensorInput
from overlapmamba.core.sensors.mount import Mount
from overlapmamba.service.answers import (
    Answer,
    Inserted,
    Observation,
    Observed,
)
from overlapmamba.service.backends.base import MapBackend, PlaceMap
from overlapmamba.service.calibration import Threshold
from overlapmamba.service.closure import unverified_call, verified_closure
from overlapmamba.service.domain import (
    DescriptorKeyframe,
    Filters,
    InsertResult,
    Match,
    NewKeyframe,
    check_descriptor,
    content_hash,
    descriptor_keyframe,
)
from overlapmamba.service.encoder import Encoder
from overlapmamba.service.errors import Conflict, Unprocessable
from overlapmamba.service.keyframing import KeyframeSchedule
from overlapmamba.service.overview import Overview
from overlapmamba.service.pipeline import Description, ScanPipeline
from overlapmamba.service.ranking import rerank_matches, rerank_params, shortlist
from overlapmamba.service.registrar import Held, Registrar
from overlapmamba.service.registration import RegistrationParams
from overlapmamba.service.scans import ScanBody
from overlapmamba.service.sensors import Sensors
from overlapmamba.service.settings import Settings
from overlapmamba.service.stats import Stats
from overlapmamba.service.threads import in_thread
from overlapmamba.service.verify import params_of


class PlaceService:
    """The use cases, each one method from parsed input to a typed answer:
    :meth:`describe`, :meth:`query`, :meth:`observe`, :meth:`insert_scan` (and
    :meth:`insert` for precomputed rows). Each records its stage timings once, with one
    definition of "total": from the request's bytes in hand to its answer."""

    def __init__(
        self,
        settings: Settings,
        encoder: Encoder,
        registry: MapBackend,
        thresholds: dict[str, Threshold] | None = None,
    ) -> None:
        self.settings = settings
        self.encoder = encoder
        self.registry = registry
        self.sensors = Sensors(encoder.meta, settings.sensors.files)
        self.thresholds = thresholds or {}  # where each calibrated threshold came from
        # the second stage, for this model's first stage (a score it cannot give stops here)
        self.rerank = rerank_params(settings.rerank, encoder.meta)
        self.stats = Stats(encoder.model_id)
        self.stats.watch_row_cache(registry.row_cache_info)
        self.overview = Overview()
        self.pipeline = ScanPipeline(
            encoder,
            settings.batching,
            settings.limits,
            on_batch=self.stats.batch,
            registrar=Registrar(
                settings.verify.processes, stale_s=settings.limits.request_timeout_s
            ),
        )
        self.stats.watch_registration(self.pipeline.registrar.usage)
        self.keyframing = KeyframeSchedule(settings.observe)  # insert=auto

    @property
    def model_id(self) -> str:
        return self.encoder.model_id

    def forget_map(self, map_id: str) -> None:
        self.stats.forget_map(map_id)
        self.overview.forget(map_id)
        self.keyframing.forget(map_id)

    async def delete_keyframe(self, m: PlaceMap, keyframe_id: str) -> None:
        """One keyframe out of an opened map (404 when it has none of that id). The map's
        insert schedule is read back from the store afterwards: the deleted keyframe may have
        been a robot's last, which ``insert=auto`` measures its next keyframe from."""
        await in_thread(m.delete, keyframe_id)
        self.keyframing.forget(m.map_id)
        count = await in_thread(lambda: m.count)
        if not m.retired:
            self.stats.p_keyframes.labels(m.map_id).set(count)
        m.maintain()

    def _done(
        self, timings: dict[str, float], t0: float, m: PlaceMap | None = None
    ) -> dict[str, float]:
        """The request's total time, and its stage times in the statistics (the service's,
        and its map's while that map has not been deleted)."""
        timings["total"] = (time.perf_counter() - t0) * 1e3
        self.stats.timings(timings, None if m is None or m.retired else m.map_id)
        return timings

    # ---- scan → descriptor ------------------------------------------------------------------

    async def describe(self, scan: ScanBody) -> Description:
        t0 = time.perf_counter()
        d = await self.pipeline.describe(scan, sensor=self._input(scan))
        self._done(d.timings, t0)
        return d

    def _sensor(self, scan: ScanBody, m: PlaceMap | None = None) -> str:
        """The scan's sensor: its own, else its map's, else the model's
        (overlapmamba.service.sensors)."""
        return self.sensors.resolve(scan.sensor, None if m is None else m.sensor)

    def _input(self, scan: ScanBody, m: PlaceMap | None = None) -> SensorInput:
        return self.sensors.input(self._sensor(scan, m), self._mount(scan, m))

    @staticmethod
    def _mount(scan: ScanBody, m: PlaceMap | None = None) -> Mount | None:
        """Where the scan's sensor sits: its own mount, else its map's, else none said."""
        return scan.mount if scan.mount is not None or m is None else m.mount

    # ---- maps ---------------------------------------------------------------------------------

    async def map(self, map_id: str) -> PlaceMap:
        """The map: at once where the backend knows it without I/O (FAISS; Qdrant while its
        last look is fresh), else looked up off the event loop (Qdrant asks its server)."""
        m = self.registry.get_nowait(map_id)
        return m if m is not None else await in_thread(self.registry.get, map_id)

    async def open_map(self, map_id: str) -> PlaceMap:
        """The map for descriptor work: refused (409) when it holds another model's
        descriptors. The use cases below take maps opened here."""
        m = await self.map(map_id)
        if m.model_id != self.model_id:
            raise Conflict(
                f"map {m.map_id!r} holds descriptors of model {m.model_id!r}; this service "
                f"runs {self.model_id!r}, whose descriptors are not comparable",
                code="model_mismatch",
                map_model_id=m.model_id,
                model_id=self.model_id,
            )
        return m

    # ---- keyframes ----------------------------------------------------------------------------

    async def insert(
        self, m: PlaceMap, rows: list[NewKeyframe], robot: str | None
    ) -> list[InsertResult]:
        """Precomputed rows into an opened map (all or nothing)."""
        results = await in_thread(m.insert, rows)
        created = sum(r.created for r in results)
        if created:
            count = await in_thread(lambda: m.count)
            if not m.retired:  # a map deleted meanwhile: its forgotten counts stay forgotten
                self.stats.insert(m.map_id, robot, created)
                self.stats.p_keyframes.labels(m.map_id).set(count)
                for r in results:
                    if r.created:
                        kf = r.keyframe
                        self.keyframing.remember(
                            m.map_id, kf.robot_id, kf.session_id, kf.timestamp, kf.pose
                        )
        m.maintain()
        return results

    async def insert_descriptors(
        self, m: PlaceMap, model_id: str, keyframes: Sequence[DescriptorKeyframe]
    ) -> list[InsertResult]:
        """Precomputed descriptors of ``model_id`` into an opened map (offline map building):
        each checked and hashed (:func:`~overlapmamba.service.domain.descriptor_keyframe`), then all
        or nothing."""
        if model_id != m.model_id:
            raise Conflict(
                f"descriptors of model {model_id!r} cannot go into map {m.map_id!r} of model "
                f"{m.model_id!r}",
                code="model_mismatch",
                map_model_id=m.model_id,
            )
        yaw_shape = (self.encoder.meta.yaw_channels, self.encoder.meta.profile.width)
        for k in keyframes:
            self.sensors.check(k.sensor)

        def rows() -> list[NewKeyframe]:
            return [descriptor_keyframe(k, i, m.dim, yaw_shape) for i, k in enumerate(keyframes)]

        return await self.insert(m, await in_thread(rows), None)

    async def insert_scan(
        self, m: PlaceMap, scan: ScanBody, keyframe_id: str, obs: Observation
    ) -> Inserted:
        """A scan into an opened map as keyframe ``keyframe_id`` (idempotent on the id)."""
        t0 = time.perf_counter()
        sensor = self._sensor(scan, m)
        d = await self.pipeline.describe(scan, self._registration(False, m), self._input(scan, m))
        row = await self._row(m, d, keyframe_id, obs, sensor)
        (result,) = await self.insert(m, [row], obs.robot_id)
        return Inserted(result, self._done(d.timings, t0, m))

    async def _row(
        self, m: PlaceMap, d: Description, keyframe_id: str, obs: Observation, sensor: str
    ) -> NewKeyframe:
        meta: dict[str, object] = {
            "robot": obs.robot_id,
            "session": obs.session_id,
            "timestamp": obs.timestamp,
            "pose": obs.pose,
        }
        if not self.sensors.is_model_sensor(sensor):  # the model's own keeps older hashes
            meta["sensor"] = sensor
        params = params_of(self.settings.verify)

        def digest_and_geometry() -> tuple[bytes, bytes | None]:
            digest = hashlib.sha256(d.points.as_xyzi().tobytes()).digest()
            if not m.keep_geometry or d.prepared is None:
                return digest, None
            return digest, self.pipeline.registrar.geometry(d.prepared, params)

        digest, geometry = await in_thread(digest_and_geometry)
        return NewKeyframe(
            keyframe_id=keyframe_id,
            robot_id=obs.robot_id,
            session_id=obs.session_id,
            timestamp=obs.timestamp,
            pose=obs.pose,
            descriptor=d.descriptor,
            yaw=d.yaw,
            content_hash=content_hash("scan", digest, meta),
            geometry=geometry,
            sensor=sensor,
        )

    # ---- queries ------------------------------------------------------------------------------

    async def query(
        self,
        m: PlaceMap,
        probe: ScanBody | Sequence[float],
        k: int,
        filters: Filters,
        *,
        robot: str | None = None,
        verify: bool = True,
    ) -> Answer:
        """Top ``k`` keyframes of an opened map for a scan, or for a descriptor (checked and
        normalised here; a descriptor has no yaw features, so its matches have no yaw, and
        no points, so they are not verified)."""
        t0 = time.perf_counter()
        self.check_k(k)
        prepared = None
        if isinstance(probe, ScanBody):
            d = await self.pipeline.describe(
                probe, self._registration(verify), self._input(probe, m)
            )
            desc, yaw, timings, prepared = d.descriptor, d.yaw, d.timings, d.prepared
        else:
            desc, yaw = check_descriptor(probe, m.dim), None
            timings = {"decode": (time.perf_counter() - t0) * 1e3}
        sensor = self._sensor(probe, m) if isinstance(probe, ScanBody) else None
        answer = await self._search(m, desc, yaw, k, filters, timings, robot, prepared, sensor)
        self._done(timings, t0, m)
        return answer

    def _registration(self, verify: bool, m: PlaceMap | None = None) -> RegistrationParams | None:
        """What the pipeline prepares a scan with, when its answer will be verified or it
        may become a keyframe of a map that keeps geometry (the prepared grid is what the
        keyframe keeps)."""
        v = self.settings.verify
        wanted = (verify and v.candidates > 0) or (m is not None and m.keep_geometry)
        return params_of(v) if wanted else None

    def check_k(self, k: int) -> None:
        """``k`` within ``limits.max_k``: refused as every other out-of-range parameter is
        (422 ``invalid_request``, naming the parameter and its range)."""
        top = self.settings.limits.max_k
        if not 1 <= k <= top:
            raise Unprocessable(
                f"invalid request: query.k: k={k} is out of range; allowed: 1 to {top} "
                "(limits.max_k)",
                code="invalid_request",
                parameter="k",
                allowed=[1, top],
            )

    async def _search(
        self,
        m: PlaceMap,
        descriptor: np.ndarray,
        yaw: np.ndarray | None,
        k: int,
        filters: Filters,
        timings: dict[str, float],
        robot: str | None,
        prepared: Held | None = None,
        sensor: str | None = None,
    ) -> Answer:
        """Search, verify the first ``verify.candidates`` candidates when the query is prepared
        for it (``sensor``: the query scan's), and make the loop-closure call (see
        :class:`LoopClosure`)."""
        n_verify = self.settings.verify.candidates if prepared is not None else 0
        rerank = self.rerank if yaw is not None else OFF

        def search_and_verify() -> list[Match]:  # one thread hop for all stages
            t0 = time.perf_counter()
            # One more than asked: the runner-up gives the loop-closure margin (no yaw).
            n = max(shortlist(k, rerank), n_verify)
            found = m.search(
                descriptor, n + 1, filters, yaw, yaw_k=n, descriptors=rerank.part is not None
            )
            found = rerank_matches(found, rerank, descriptor)
            t1 = time.perf_counter()
            timings["search"] = (t1 - t0) * 1e3
            if n_verify and found and prepared is not None:
                found[:n_verify] = self._verify(m, prepared, found[:n_verify], sensor)
                timings["verify"] = (time.perf_counter() - t1) * 1e3
            return found

        matches = await in_thread(search_and_verify)
        closure = unverified_call(matches, self.settings.loop_closure)
        if closure.accepted:
            closure = replace(closure, keyframe_id=matches[0].keyframe.keyframe_id)
        if n_verify and matches:  # verified (n_verify > 0 only with a prepared query)
            closure = verified_closure(matches[:n_verify], closure, self.settings.covariance)
        if not m.retired:  # a map deleted meanwhile: its forgotten counts stay forgotten
            self.stats.query(m.map_id, robot, closure.accepted, matches[:n_verify])
        return Answer(matches[:k], closure, timings)

    def _verify(
        self, m: PlaceMap, prepared: Held, candidates: list[Match], sensor: str | None
    ) -> list[Match]:
        blobs = m.geometry([c.keyframe.keyframe_id for c in candidates])
        verdicts = self.pipeline.registrar.verify(
            prepared,
            [(blobs.get(c.keyframe.keyframe_id), c.yaw_deg, c.distance) for c in candidates],
            self.settings.verify,
            [self.sensors.view(c.keyframe.sensor, sensor) for c in candidates],
        )
        return [replace(c, verification=v) for c, v in zip(candidates, verdicts, strict=True)]

    # ---- the robot's round trip -------------------------------------------------------------

    async def _draw(self, m: PlaceMap, obs: Observation, answer: Answer) -> None:
        """The observation on the map's picture (:mod:`overlapmamba.service.overview`): the robot's
        position and, for a loop closure, the keyframe's."""
        lc = answer.loop_closure
        to = None
        if lc.accepted and lc.keyframe_id is not None and obs.pose is not None:
            hits = [x.keyframe for x in answer.matches if x.keyframe.keyframe_id == lc.keyframe_id]
            to = hits[0] if hits else await in_thread(m.get, lc.keyframe_id)  # below k
        closure = to.pose if to is not None else None
        if m.retired:
            return
        self.overview.observed(
            m.map_id, obs.robot_id, obs.pose, closure, lc.keyframe_id, lc.verified
        )

    async def observe(self, m: PlaceMap, scan: ScanBody, obs: Observation) -> Observed:
        """Query an opened map excluding this session's recent keyframes, then insert the
        scan as keyframe ``robot:session:timestamp`` when due."""
        t0 = time.perf_counter()
        self.check_k(obs.k)
        verify = obs.verify and self.settings.verify.candidates > 0
        sensor = self._sensor(scan, m)
        d = await self.pipeline.describe(scan, self._registration(verify, m), self._input(scan, m))
        filters = Filters(
            exclude_recent_s=self.settings.observe.exclude_recent_s,
            session_id=obs.session_id,
            robot_id=obs.robot_id,
            timestamp=obs.timestamp,
        )
        answer = await self._search(
            m,
            d.descriptor,
            d.yaw,
            obs.k,
            filters,
            d.timings,
            obs.robot_id,
            d.prepared if verify else None,
            sensor,
        )
        await self._draw(m, obs, answer)
        keyframe_id = None
        inserted = False
        auto = obs.insert == "auto"
        async with self.keyframing.deciding(m.map_id, obs.robot_id) if auto else nullcontext():
            reason = await self.keyframing.due(m, obs)
            if reason is None and auto and await self.keyframing.retried(m, obs):
                # not due only because its own id is the robot's last keyframe: a retry whose
                # answer was lost. Inserted again, idempotently: the same scan is "existing",
                # another scan under that id a 409, as with insert=always
                reason = "existing"
            if reason is not None:
                keyframe_id = obs.keyframe_id
                row = await self._row(m, d, keyframe_id, obs, sensor)
                (result,) = await self.insert(m, [row], obs.robot_id)
                inserted = result.created
                if not inserted:
                    reason = "existing"
        self._done(answer.timings, t0, m)
        return Observed(
            answer.matches,
            answer.loop_closure,
            answer.timings,
            inserted,
            keyframe_id,
            reason or ("never" if obs.insert == "never" else "not_due"),
        )
