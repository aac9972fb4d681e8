"""Recognition statistics: JSON for dashboards (``/v1/stats``) and Prometheus (``/metrics``).

Percentiles come from a sliding window of the last ``WINDOW`` samples per stage, so they
describe now, not the process's lifetime; Prometheus gets cumulative histograms.
Each app has its own ``CollectorRegistry`` so several apps (tests) never share counters.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections import Counter, OrderedDict, defaultdict, deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from prometheus_client import CollectorRegistry, Gauge, Histogram, ProcessCollector
from prometheus_client import Counter as PCounter
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

WINDOW = 2048
MAP_WINDOW = 512  # a map's: ≈ 100 kB of latencies a map, not 400 (a service may hold hundreds)
MAX_ROBOTS = 1000  # per-robot rows kept (least recently seen dropped): ids come from clients
STAGES = ("decode", "project", "encode", "search", "verify", "total")
# up to the request timeout (30 s by default, 120 s at most): a slow request's quantile is
# read from its bucket, not capped at the last one
_LATENCY_BUCKETS = (
    *(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0),
    *(10.0, 20.0, 30.0, 60.0, 120.0),
)


@dataclass
class _Robot:
    last_seen: float = 0.0
    observations: int = 0
    inserts: int = 0
    loop_closures: int = 0


def _windows(n: int) -> dict[str, deque[float]]:
    return {s: deque(maxlen=n) for s in STAGES}


@dataclass
class _Counts:
    inserts: int = 0
    queries: int = 0
    loop_closures: int = 0
    verified: int = 0  # candidates whose registration passed the thresholds
    # candidates that did not: registered and below the thresholds, refused by registration
    # (too few points), or kept from registering by the descriptor gate
    rejected: int = 0
    registered: int = 0  # candidates registered to a fitness: the verify stage's GICP work
    # of the rejected, those that passed the thresholds and that a turned pose fits nearly as
    # well (verify.ambiguity_margin)
    ambiguous: int = 0
    robots: OrderedDict[str, _Robot] = field(default_factory=OrderedDict)
    # queries a second over the last minute, as [second, count] (a window of samples would
    # cap the rate at WINDOW / 60 a second)
    recent: deque[list[int]] = field(default_factory=deque)
    # each stage's latency (ms) of the last WINDOW requests (a map's: MAP_WINDOW)
    latency: dict[str, deque[float]] = field(default_factory=lambda: _windows(WINDOW))

    def queried(self, now: float) -> None:
        second = int(now)
        if self.recent and self.recent[-1][0] == second:
            self.recent[-1][1] += 1
        else:
            self.recent.append([second, 1])
        while self.recent and self.recent[0][0] < second - 60:
            self.recent.popleft()

    def public(self, started: float | None = None) -> dict[str, Any]:
        """The counts; rates are None where nothing was counted (a rate of 0 would say
        every query failed to close a loop). ``started``: the service's start, so that the
        first minute's query rate is over the time it has run, not a whole minute."""
        now = time.time()
        last_min = sum(n for second, n in self.recent if now - second < 60.0)
        span = 60.0 if started is None else min(60.0, max(now - started, 1.0))
        return {
            "inserts": self.inserts,
            "queries": self.queries,
            "queries_per_s_1m": last_min / span,
            "loop_closures": self.loop_closures,
            "loop_closure_rate": self.loop_closures / self.queries if self.queries else None,
            "verification": {
                "verified": self.verified,
                "rejected": self.rejected,
                "registered": self.registered,
                "ambiguous": self.ambiguous,
                "registered_per_query": self.registered / self.queries if self.queries else None,
            },
            "robots": {
                name: {
                    "last_seen": r.last_seen,
                    "observations": r.observations,
                    "inserts": r.inserts,
                    "loop_closures": r.loop_closures,
                }
                for name, r in sorted(self.robots.items())
            },
        }


class Stats:
    def __init__(self, model_id: str) -> None:
        self.model_id = model_id
        self.started = time.time()
        self._lock = threading.Lock()
        self.total = _Counts()
        self.by_map: dict[str, _Counts] = defaultdict(lambda: _Counts(latency=_windows(MAP_WINDOW)))
        self.batch_sizes: Counter[int] = Counter()
        self.registry = CollectorRegistry()
        r = self.registry
        # The process's own series (process_resident_memory_bytes, process_cpu_seconds_total,
        # open file descriptors, start time; Linux), which the default registry would carry:
        # what an alert on a growing process watches.
        ProcessCollector(registry=r)
        self.p_latency = Histogram(
            "overlapmamba_stage_seconds",
            "Time per request stage",
            ["stage"],
            buckets=_LATENCY_BUCKETS,
            registry=r,
        )
        self.p_requests = PCounter(
            "overlapmamba_requests",
            "HTTP requests by route and status",
            ["route", "status"],
            registry=r,
        )
        self.p_queries = PCounter("overlapmamba_queries", "Place queries", ["map"], registry=r)
        self.p_inserts = PCounter("overlapmamba_inserts", "Keyframes inserted", ["map"], registry=r)
        # No robot label: robot ids come from clients, and every label value is a series.
        self.p_loops = PCounter(
            "overlapmamba_loop_closures", "Accepted loop closures", ["map"], registry=r
        )
        self.p_verify = PCounter(
            "overlapmamba_verifications",
            "Candidates geometrically verified, by outcome (verified, rejected)",
            ["map", "outcome"],
            registry=r,
        )
        self.p_registered = PCounter(
            "overlapmamba_registrations",
            "Candidates registered to a fitness (GICP runs): the verify stage's work",
            ["map"],
            registry=r,
        )
        self.p_ambiguous = PCounter(
            "overlapmamba_ambiguous_closures",
            "Candidates rejected as ambiguous: a pose turned by a quarter, a half or three "
            "quarters fits nearly as well (verify.ambiguity_margin); counted in rejected too",
            ["map"],
            registry=r,
        )
        self.p_batch = Histogram(
            "overlapmamba_encoder_batch_size",
            "Scans per encoder call",
            buckets=(1, 2, 4, 8, 16, 32, 64, 128, 256),  # batching.max_batch: 256 at most
            registry=r,
        )
        self.p_keyframes = Gauge(
            "overlapmamba_map_keyframes", "Keyframes per map", ["map"], registry=r
        )
        self.p_queue = Gauge(
            "overlapmamba_encoder_queue",
            "Scans waiting to encode whose requests still wait for them",
            registry=r,
        )
        self.p_ready = Gauge(
            "overlapmamba_ready",
            "1 once the model is loaded and every map replayed (/readyz 200), else 0",
            registry=r,
        )

    def watch_row_cache(self, info: Callable[[], dict[str, int] | None]) -> None:
        """Put the backend's row cache on ``/metrics``, read at each scrape from ``info``
        (its ``RowCache.info``; None: no series):
        ``overlapmamba_row_cache_bytes`` of ``_max_bytes``, ``_rows``, and
        ``overlapmamba_row_cache_lookups_total`` by outcome (hit, miss)."""
        self.registry.register(_RowCacheCollector(info))

    def watch_registration(self, usage: Callable[[], dict[str, float]]) -> None:
        """Put the registration processes on ``/metrics``, read at each scrape from
        ``usage`` (``Registrar.usage``): ``overlapmamba_registration_processes``,
        ``_restarts_total``, and the children's ``_resident_bytes`` and
        ``_cpu_seconds_total`` (Linux), which the process's own series leave out."""
        self.registry.register(_RegistrationCollector(usage))

    def timings(self, ms: dict[str, float], map_id: str | None = None) -> None:
        """One request's stage times, in the service's windows and in ``map_id``'s (the
        map it was about, if any)."""
        with self._lock:
            windows = [self.total.latency]
            if map_id is not None:
                windows.append(self.by_map[map_id].latency)
            for stage, v in ms.items():
                if stage in STAGES:
                    for w in windows:
                        w[stage].append(v)
                    self.p_latency.labels(stage).observe(v / 1000.0)

    def batch(self, size: int, _seconds: float) -> None:
        with self._lock:
            self.batch_sizes[size] += 1
        self.p_batch.observe(size)

    def request(self, route: str, status: int) -> None:
        self.p_requests.labels(route, str(status)).inc()

    def _robot(self, counts: _Counts, robot: str | None) -> _Robot | None:
        if robot is None:
            return None
        rec = counts.robots.pop(robot, None) or _Robot()
        counts.robots[robot] = rec  # most recent last
        while len(counts.robots) > MAX_ROBOTS:
            counts.robots.popitem(last=False)
        rec.last_seen = time.time()
        return rec

    def query(
        self, map_id: str, robot: str | None, accepted: bool, candidates: Sequence[Any] = ()
    ) -> None:
        """One answered query; ``candidates``: its matches that went through verification
        (those whose keyframe had no geometry, or not registered after an earlier one verified
        under ``verify.stop_at_first``, count as neither verified nor rejected); those
        registered to a fitness count as ``registered`` too, whatever their outcome."""
        self.p_queries.labels(map_id).inc()
        if accepted:
            self.p_loops.labels(map_id).inc()
        verdicts = [c.verification for c in candidates if c.verification is not None]
        verified = sum(v.verified is True for v in verdicts)
        rejected = sum(v.verified is False for v in verdicts)
        registered = sum(v.fitness is not None for v in verdicts)
        ambiguous = sum(v.ambiguous for v in verdicts)
        if verified:
            self.p_verify.labels(map_id, "verified").inc(verified)
        if rejected:
            self.p_verify.labels(map_id, "rejected").inc(rejected)
        if registered:
            self.p_registered.labels(map_id).inc(registered)
        if ambiguous:
            self.p_ambiguous.labels(map_id).inc(ambiguous)
        now = time.time()
        with self._lock:
            for c in (self.total, self.by_map[map_id]):
                c.queries += 1
                c.verified += verified
                c.rejected += rejected
                c.registered += registered
                c.ambiguous += ambiguous
                c.queried(now)
                c.loop_closures += accepted
                rec = self._robot(c, robot)
                if rec is not None:
                    rec.observations += 1
                    rec.loop_closures += accepted

    def insert(self, map_id: str, robot: str | None, n: int = 1) -> None:
        self.p_inserts.labels(map_id).inc(n)
        with self._lock:
            for c in (self.total, self.by_map[map_id]):
                c.inserts += n
                rec = self._robot(c, robot)
                if rec is not None:
                    rec.inserts += n

    def known_maps(self) -> set[str]:
        """The maps with counts or series here."""
        with self._lock:
            known = set(self.by_map)
        return known | _maps_of(self.p_keyframes, self.p_queries, self.p_inserts)

    def reconcile(self, known: set[str], live: dict[str, int]) -> None:
        """The maps the backend lists now (``live``, with their keyframe counts, listed
        after ``known`` was taken, so that a map made in between is not lost): the keyframes
        gauge set from them, and the counts and series of a known map no longer listed
        forgotten. A replica beside others on one Qdrant learns of another's writes and
        deletions only so (its own are counted as they happen)."""
        for map_id, count in live.items():
            self.p_keyframes.labels(map_id).set(count)
        for map_id in known - set(live):
            self.forget_map(map_id)

    def forget_map(self, map_id: str) -> None:
        """A deleted map's counts and every /metrics series labelled with it go: maps that
        come and go must not grow the service's memory and its scrapes for ever."""
        with self._lock:
            self.by_map.pop(map_id, None)
        labelled: list[tuple[Gauge | PCounter, tuple[str, ...]]] = [
            (m, (map_id,))
            for m in (
                self.p_keyframes,
                self.p_queries,
                self.p_inserts,
                self.p_loops,
                self.p_registered,
                self.p_ambiguous,
            )
        ]
        labelled += [(self.p_verify, (map_id, outcome)) for outcome in ("verified", "rejected")]
        for metric, labels in labelled:
            with contextlib.suppress(KeyError):
                metric.remove(*labels)

    def percentiles(self, map_id: str | None = None) -> dict[str, dict[str, float | None]]:
        """Each stage's p50/p90/p99 over the last WINDOW requests (the last MAP_WINDOW of
        ``map_id``'s, if given)."""
        out: dict[str, dict[str, float | None]] = {}
        with self._lock:
            counts = self.total if map_id is None else self.by_map[map_id]
            for stage, window in counts.latency.items():
                a = np.array(window, dtype=np.float64)
                if a.size:
                    p50, p90, p99 = np.percentile(a, [50, 90, 99])
                    out[stage] = {"p50": p50, "p90": p90, "p99": p99, "n": int(a.size)}
                else:  # no request yet: no figure (a 0 ms line on the dashboard)
                    out[stage] = {"p50": None, "p90": None, "p99": None, "n": 0}
        return out

    def public(self, map_id: str | None = None) -> dict[str, Any]:
        with self._lock:
            counts = (self.by_map[map_id] if map_id is not None else self.total).public(
                self.started
            )
            hist = {str(k): v for k, v in sorted(self.batch_sizes.items())}
        return {
            "model_id": self.model_id,
            "uptime_s": time.time() - self.started,
            **counts,
            "latency_ms": self.percentiles(map_id),
            # encoder batches mix every map's scans: the service's, on a map's stats too
            "batch_size_histogram": hist,
        }


def _maps_of(*metrics: Gauge | PCounter) -> set[str]:
    """The maps these metrics (labelled ``map``) have series for."""
    return {
        sample.labels["map"]
        for metric in metrics
        for family in metric.collect()
        for sample in family.samples
        if "map" in sample.labels
    }


class _RowCacheCollector(Collector):
    def __init__(self, info: Callable[[], dict[str, int] | None]) -> None:
        self.info = info

    def collect(self) -> Iterator[Metric]:
        got = self.info()
        if got is None:
            return
        for name, key, doc in (
            (
                "bytes",
                "bytes",
                "Bytes the row cache holds (yaw spectra of keyframes searched last)",
            ),
            ("max_bytes", "max_bytes", "The row cache's budget (index.row_cache_mb)"),
            ("rows", "rows", "Keyframes the row cache holds"),
        ):
            yield GaugeMetricFamily(f"overlapmamba_row_cache_{name}", doc, value=got[key])
        lookups = CounterMetricFamily(
            "overlapmamba_row_cache_lookups",
            "Shortlisted keyframes looked up in the row cache, by outcome",
            labels=["outcome"],
        )
        lookups.add_metric(["hit"], got["hits"])
        lookups.add_metric(["miss"], got["misses"])
        yield lookups


class _RegistrationCollector(Collector):
    def __init__(self, usage: Callable[[], dict[str, float]]) -> None:
        self.usage = usage

    def collect(self) -> Iterator[Metric]:
        got = self.usage()
        yield GaugeMetricFamily(
            "overlapmamba_registration_processes",
            "Registration's child processes (verify.processes; 0: in the server's threads)",
            value=got["processes"],
        )
        yield CounterMetricFamily(
            "overlapmamba_registration_restarts",
            "Registration processes that died and were started again",
            value=got["restarts"],
        )
        yield CounterMetricFamily(
            "overlapmamba_registration_stale",
            "Registration calls skipped: queued in a child past the request timeout",
            value=got.get("stale", 0),
        )
        if "resident_bytes" in got:  # Linux: the children's /proc
            yield GaugeMetricFamily(
                "overlapmamba_registration_resident_bytes",
                "Resident memory of the registration processes together",
                value=got["resident_bytes"],
            )
            yield CounterMetricFamily(
                "overlapmamba_registration_cpu_seconds",
                "CPU time (user + system) of the registration processes running now",
                value=got["cpu_seconds"],
            )
