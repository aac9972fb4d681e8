"""The fleet simulator: N robots replay recorded drives through ``observe`` at once.

Each robot has its own robot id, session and starting offset into its drive, sends one
scan every 1/rate seconds (never faster; a slow answer delays only that robot), and stops
at the end of its drive or of the duration, whichever comes first: every loop is bounded
in count and time, and only the given URL is contacted.

Ground truth, where a drive ships ``ground_truth/loops.npz``: an accepted loop closure is
correct when its top match is a keyframe of the same drive whose pose lies within the
drive's loop radius of the query's. A query *has* a loop when such a keyframe had been
acknowledged before the query was sent and the service's own-session recency filter
(``exclude_recent_s``, the server default) did not hide it. Precision = correct / accepted,
recall = correct closures of queries that had a loop / queries that had a loop (a right
closure to a keyframe not yet acknowledged counts for precision only). A verified closure's
relative pose is scored against the drive's poses (T = P_keyframe⁻¹ · P_query): translation
and yaw errors of the correct ones, and how many verified closures of all had a right pose (within
``overlapmamba.core.poses.POSE_RIGHT``, wherever their keyframe lies on the same drive: an edge
a pose graph can take, even beyond the loop radius; one to another drive's keyframe counts
as not right, its truth unknown here).
"""

from __future__ import annotations

import asyncio
import json
import math
import time
from collections import Counter
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from overlapmamba.client._async import AsyncPlaceRecognitionClient
from overlapmamba.client._base import MountArg
from overlapmamba.client._exceptions import APIError, ClientError
from overlapmamba.client._replay import Drive
from overlapmamba.client._retry import Retry
from overlapmamba.core import outfiles, posecov
from overlapmamba.core.errors import LidarCoreError
from overlapmamba.core.poses import POSE_RIGHT, pose_error

# a call started before the run's end may finish this long (s) after it; then it is cut
GRACE_S = 5.0


@dataclass
class _Sample:
    robot: str
    drive: int
    frame: int
    sent: float  # monotonic seconds since start
    latency_ms: float
    accepted: bool
    top: str | None  # the accepted closure's keyframe (else the top match)
    inserted: str | None
    error: str | None
    verified: bool | None = None
    relative_pose: np.ndarray | None = None
    covariance: np.ndarray | None = None  # the closure's, when the server gives one


@dataclass
class FleetReport:
    robots: int
    duration_s: float
    rate_hz: float
    observations: int
    throughput_per_s: float
    latency_ms: dict[str, float | None]  # None where no observation was answered
    errors: dict[str, int]
    inserted: int
    loop_closures: int
    correct: int | None
    queries_with_loop: int | None
    precision: float | None
    recall: float | None
    verified_closures: int = 0
    pose_error: dict[str, dict[str, float]] | None = None  # correct verified closures
    verified_pose_right: int | None = None  # verified closures whose relative pose is right
    # of those that carry a covariance: how many, and the share whose error against the truth
    # lies inside their 95 % ellipsoid (a right covariance: 0.95); None: none carried one
    covariance: dict[str, float] | None = None
    per_robot: dict[str, dict[str, Any]] = field(default_factory=dict)
    # what was measured: the service's model (its /readyz), the drives, when (UTC)
    server: dict[str, Any] = field(default_factory=dict)
    drives: list[str] = field(default_factory=list)
    when: str = ""
    scans_per_robot: int | None = None  # asked of each robot (None: as many as the time let)
    # tries the server refused (or the link failed) that a retry then got through, by code:
    # the load it shed, which the errors (final failures only) do not show
    retried: dict[str, int] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return dict(self.__dict__)


async def simulate(
    url: str,
    map_id: str,
    drives: list[Drive],
    *,
    robots: int,
    duration_s: float,
    rate_hz: float,
    api_key: str | None = None,
    k: int = 5,
    exclude_recent_s: float = 30.0,
    seed: int = 0,
    retry: Retry | None = None,
    mount: MountArg = None,
    scans: int | None = None,
) -> tuple[FleetReport, list[_Sample]]:
    """``retry``: how each robot retries (default: 3 attempts); ``NO_RETRY`` makes every
    overload or transport error count as an error, as load tests want. ``mount``: where
    every robot's sensor sits (HEIGHT[,PITCH[,ROLL]]); None: each drive's own (``open_drive``:
    the one named, else its manifest's), else the map's.

    ``scans``: each robot stops after that many scans (or at its drive's end), and
    ``duration_s`` only bounds the run. The robots then cover the same stretches of their
    drives on any machine, so the closures' recall compares across machines and files: in
    a fixed time a slower server's robots get less far, where the loops differ (measured:
    the same server, robots asked for fewer scans a second, recall fell with them)."""
    # `not x > 0`: NaN is no duration and no rate either
    if robots < 1 or not duration_s > 0 or not 0 < rate_hz < math.inf or not drives:
        raise ValueError(
            "need robots ≥ 1, duration > 0 s, a finite rate > 0 Hz and at least one drive; "
            f"got robots {robots}, duration_s {duration_s}, rate_hz {rate_hz}, "
            f"{len(drives)} drives"
        )
    if scans is not None and scans < 1:
        raise ValueError(
            f"scans must be at least 1 a robot (or None: until the deadline); got {scans}"
        )
    samples: list[_Sample] = []
    # keyframe id -> (drive, frame, acknowledged at)
    keyframes: dict[str, tuple[int, int, float]] = {}
    start = time.monotonic()
    deadline = start + duration_s

    async with AsyncPlaceRecognitionClient(
        url,
        api_key=api_key,
        retry=retry or Retry(attempts=3, backoff_s=0.2),
        mount=mount,
        # a connection a robot: beyond httpx's 100, robots would wait in this client, and
        # that wait (or its timeout) would be measured as the server's
        max_connections=max(100, robots),
    ) as pr:
        made = await pr.create_map(map_id)
        if made.keyframes and _scored(drives):  # closures to them could not be scored: not misread
            raise ValueError(
                f"map {map_id!r} already holds {made.keyframes} keyframes; the simulator "
                "scores closures against the keyframes its robots insert, so it needs a map "
                f"of its own: another --map, or `overlapmamba-client maps delete {map_id}`"
            )
        try:  # what the report measured; a service not ready now is not an error here
            ready = (await pr.health()).get("detail") or {}
        except ClientError:
            ready = {}
        server = {k: ready.get(k) for k in ("model_id", "views", "scan", "sensor")}
        pr.retried.clear()  # the robots' observations only, not the set-up's calls

        async def robot(r: int) -> None:
            d = r % len(drives)
            drive = drives[d]
            name, session = f"robot-{r:02d}", f"sim-{seed}-{r:02d}"
            # Robots sharing a drive start spread evenly along it, so each later drives
            # through places another has already mapped: cross-robot loop closures.
            sharing = -(-robots // len(drives))
            offset = (r // len(drives)) * len(drive) // sharing
            period = 1.0 / rate_hz
            next_t = time.monotonic()
            end = len(drive) if scans is None else min(len(drive), offset + scans)
            for i in range(offset, end):
                now = time.monotonic()
                if max(now, next_t) >= deadline:  # due after the end: not sent, not waited
                    return
                if next_t > now:
                    await asyncio.sleep(next_t - now)
                next_t = max(next_t + period, time.monotonic())
                try:
                    scan = await asyncio.to_thread(drive.scan, i)
                except LidarCoreError:  # counted as the robot's error; the drive goes on
                    at = time.monotonic() - start
                    samples.append(
                        _Sample(name, d, i, at, 0.0, False, None, None, "unreadable_scan")
                    )
                    continue
                sent = time.monotonic()
                try:
                    # the run ends at its duration: a call still waiting GRACE_S after it
                    # (a hung server, retries) is cut and counted, not waited out for minutes
                    async with asyncio.timeout(max(0.0, deadline - sent) + GRACE_S):
                        o = await pr.observe(
                            map_id,
                            scan,
                            robot_id=name,
                            session_id=session,
                            timestamp=float(drive.times[i]),
                            pose=drive.pose(i),
                            k=k,
                            sensor=drive.sensor,
                            mount=drive.mount if mount is None else None,  # None: the client's
                        )
                except (ClientError, TimeoutError) as err:
                    kind = (
                        err.code
                        if isinstance(err, APIError)
                        else "duration"
                        if isinstance(err, TimeoutError)
                        else type(err).__name__
                    )
                    samples.append(
                        _Sample(
                            name,
                            d,
                            i,
                            sent - start,
                            (time.monotonic() - sent) * 1e3,
                            False,
                            None,
                            None,
                            kind,
                        )
                    )
                    continue
                done = time.monotonic()
                if o.keyframe:  # inserted now, or by a retried try whose answer was lost
                    keyframes[o.keyframe] = (d, i, done)
                lc = o.loop_closure
                samples.append(
                    _Sample(
                        name,
                        d,
                        i,
                        sent - start,
                        (done - sent) * 1e3,
                        lc.accepted,
                        lc.keyframe_id or (o.matches[0].keyframe_id if o.matches else None),
                        o.keyframe,
                        None,
                        lc.verified,
                        lc.relative_pose,
                        lc.covariance,
                    )
                )

        try:  # an unforeseen failure in one robot stops the others with it
            async with asyncio.TaskGroup() as tg:
                for r in range(robots):
                    tg.create_task(robot(r))
        except ExceptionGroup as group:
            raise group.exceptions[0] from None  # the caller's own error, as one robot hit it
        retried = dict(sorted(pr.retried.items()))
    elapsed = time.monotonic() - start
    report = _report(samples, keyframes, drives, robots, elapsed, rate_hz, exclude_recent_s, start)
    report.retried = retried
    report.server, report.drives = server, [d.name for d in drives]
    report.scans_per_robot = scans
    report.when = datetime.now(UTC).isoformat(timespec="seconds")
    return report, samples


def _scored(drives: list[Drive]) -> bool:
    """Whether closures can be scored: every drive ships its loop radius and poses."""
    return all(d.loop_radius is not None and d.poses is not None for d in drives)


def _report(
    samples: list[_Sample],
    keyframes: dict[str, tuple[int, int, float]],
    drives: list[Drive],
    robots: int,
    elapsed: float,
    rate_hz: float,
    exclude_recent_s: float,
    start: float,
) -> FleetReport:
    ok = [s for s in samples if s.error is None]
    lat = np.array([s.latency_ms for s in ok])
    accepted = [s for s in ok if s.accepted]
    has_gt = _scored(drives)
    correct = with_loop = pose_right = found = None  # found: correct, of those with a loop
    t_err: list[float] = []
    chi2: list[float] = []  # right verified closures' δᵀ Σ⁻¹ δ, where they carry Σ
    yaw_err: list[float] = []
    if has_gt:
        correct, with_loop, pose_right, found = 0, 0, 0, 0
        kf_by_drive: dict[int, list[tuple[int, float, str]]] = {}
        for kid, (d, i, t) in keyframes.items():
            kf_by_drive.setdefault(d, []).append((i, t - start, kid))
        for s in ok:
            drive = drives[s.drive]
            radius = float(drive.loop_radius or 0.0)
            assert drive.poses is not None and drive.seq.poses is not None  # has_gt
            p = drive.poses[s.frame, :3]
            own_session = s.robot
            ts = drive.times[s.frame]
            cands = [
                (i, kid)
                for i, t_ack, kid in kf_by_drive.get(s.drive, [])
                if t_ack <= s.sent
                and not (
                    kid.startswith(own_session + ":") and drive.times[i] > ts - exclude_recent_s
                )
                and np.linalg.norm(drive.poses[i, :3] - p) < radius
            ]
            with_loop += bool(cands)
            if not (s.accepted and s.top in keyframes):
                continue
            d, j, _ = keyframes[s.top]
            near = bool(d == s.drive and np.linalg.norm(drive.poses[j, :3] - p) < radius)
            correct += near
            # recall's numerator within its denominator: a right closure to a keyframe whose
            # robot had not yet been answered is right, but no loop the query could count on
            found += near and bool(cands)
            # a verified closure's pose, wherever its keyframe on this drive lies
            if d == s.drive and s.verified and s.relative_pose is not None:
                poses = drive.seq.poses
                truth = np.linalg.inv(poses[j]) @ poses[s.frame]  # T_keyframe←query
                t, y = pose_error(s.relative_pose, truth)
                right = t <= POSE_RIGHT[0] and y <= POSE_RIGHT[1]
                pose_right += right
                if right and s.covariance is not None:
                    delta = posecov.error(s.relative_pose, truth)
                    chi2.append(posecov.mahalanobis2(delta, s.covariance))
                if near:
                    t_err.append(t)
                    yaw_err.append(y)
    per_robot: dict[str, dict[str, Any]] = {}
    for s in samples:
        r = per_robot.setdefault(s.robot, {"observations": 0, "errors": 0, "loop_closures": 0})
        r["observations"] += 1
        r["errors"] += s.error is not None
        r["loop_closures"] += s.accepted
    return FleetReport(
        robots=robots,
        duration_s=elapsed,
        rate_hz=rate_hz,
        observations=len(samples),
        throughput_per_s=len(ok) / elapsed if elapsed > 0 else 0.0,
        latency_ms={  # None where no observation was answered
            name: float(np.percentile(lat, q)) if len(lat) else None
            for name, q in (("p50", 50), ("p95", 95), ("p99", 99), ("max", 100))
        },
        errors=dict(Counter(s.error for s in samples if s.error is not None)),
        inserted=len(keyframes),
        loop_closures=len(accepted),
        correct=correct,
        queries_with_loop=with_loop,
        precision=(correct / len(accepted)) if correct is not None and accepted else None,
        recall=(found / with_loop) if found is not None and with_loop else None,
        verified_closures=sum(bool(s.verified) for s in accepted),
        verified_pose_right=pose_right,
        covariance=None
        if not chi2
        else {
            "closures": len(chi2),
            "inside_95": float(np.mean(np.asarray(chi2) <= posecov.CHI2_6_95)),
        },
        pose_error=None
        if not t_err
        else {
            "translation_m": {
                "median": float(np.median(t_err)),
                "p90": float(np.percentile(t_err, 90)),
            },
            "yaw_deg": {
                "median": float(np.median(yaw_err)),
                "p90": float(np.percentile(yaw_err, 90)),
            },
        },
        per_robot=per_robot,
    )


def check_outputs(out: Path, plot: Path | None) -> None:
    """Where the report and the plot go, checked (their folders made) before the run: a
    plot format matplotlib does not write, or a file in a folder's place, was found after
    the whole simulation, with the JSON written and the plot lost. A ValueError names it."""
    formats = None
    if plot is not None:
        from matplotlib.backend_bases import FigureCanvasBase

        formats = FigureCanvasBase.get_supported_filetypes()  # what savefig writes
    outfiles.check_outputs(("--out", out, None), ("--plot", plot, formats))


def write_outputs(
    report: FleetReport, samples: list[_Sample], out: Path, plot: Path | None
) -> None:
    outfiles.write_whole(out, json.dumps(report.to_json(), indent=2) + "\n")
    if plot is None:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    for name in sorted({s.robot for s in samples}):
        mine = [s for s in samples if s.robot == name and s.error is None]
        a.plot([s.sent for s in mine], [s.latency_ms for s in mine], ".", ms=3, label=name)
    a.set_xlabel("time since start (s)")
    a.set_ylabel("observe latency (ms)")
    a.set_title(f"{report.robots} robots at {report.rate_hz:g} Hz")
    if report.robots <= 8:
        a.legend(fontsize=7, markerscale=3)
    lat = [s.latency_ms for s in samples if s.error is None]
    b.hist(lat, bins=40)
    for q, v in report.latency_ms.items():
        if q != "max" and v is not None:
            b.axvline(v, ls="--", lw=1, color="k")
            b.text(v, b.get_ylim()[1] * 0.95, q, rotation=90, va="top", fontsize=8)
    b.set_xlabel("observe latency (ms)")
    b.set_ylabel("observations")
    fig.tight_layout()
    plot.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(plot, dpi=110)
    plt.close(fig)
