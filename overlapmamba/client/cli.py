"""``overlapmamba-client``: operate the service from a shell.

Every command takes ``--url`` (env ``OVERLAPMAMBA_URL``) and ``--api-key``
(env ``OVERLAPMAMBA_API_KEY``). Errors print the server's message and exit with 1 (the
service refused) or 2 (it could not be reached, or bad arguments).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from pathlib import Path
from typing import Annotated

import typer
from rich.live import Live
from rich.markup import escape
from rich.table import Table

from overlapmamba.client._cli_maps import maps_app
from overlapmamba.client._cli_options import (
    DEFAULT_URL,
    DRIVE_HELP,
    GraphReader,
    GraphReaderOpt,
    KeyOpt,
    MapOpt,
    MountOpt,
    OdometryOpt,
    SensorOpt,
    TfOpt,
    TopicOpt,
    UrlOpt,
    VerifyOpt,
    client,
    console,
    errors,
    make_map,
    out,
    within,
)
from overlapmamba.client._display import (
    fleet_table,
    matrix_text,
    note_unposed,
    pose_text,
    progress,
    report_skipped,
    stats_table,
)
from overlapmamba.client._replay import open_drive
from overlapmamba.client._sync import PlaceRecognitionClient
from overlapmamba.client.posegraph import PoseGraph
from overlapmamba.core import outfiles

app = typer.Typer(
    name="overlapmamba-client",
    help="Client of the OverlapMamba place-recognition service.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
app.add_typer(maps_app, name="maps")


@app.command(
    "ingest",
    epilog="Examples:\n\n  overlapmamba-client ingest data/synth/val --map town --every 5\n\n"
    "  overlapmamba-client ingest drive.mcap --map town --odometry /odom --sensor os1-64",
)
@errors
def ingest(
    seq_dir: Annotated[Path, typer.Argument(help=DRIVE_HELP)],
    map_id: MapOpt,
    robot: Annotated[str, typer.Option(help="robot id")] = "mapper",
    session: Annotated[
        str | None, typer.Option(help="session \\[default: the drive's name, as an id]")
    ] = None,
    every: Annotated[int, typer.Option(min=1, help="insert every N-th scan")] = 1,
    topic: TopicOpt = None,
    odometry: OdometryOpt = None,
    tf: TfOpt = None,
    sensor: SensorOpt = None,
    mount: MountOpt = None,
    compress: Annotated[bool, typer.Option(help="zstd-compress the scans")] = False,
    url: UrlOpt = DEFAULT_URL,
    api_key: KeyOpt = None,
) -> None:
    """Insert a recorded sequence as keyframes (ids SESSION-FRAME; re-running is harmless)."""
    drive = open_drive(seq_dir, topic=topic, odometry=odometry, tf=tf, sensor=sensor, mount=mount)
    note_unposed(drive)
    session = session or drive.session
    frames = range(0, len(drive), every)
    t0 = time.monotonic()
    created = retried = 0
    skipped: list[str] = []  # scans that could not be read: left out, named at the end
    with (
        PlaceRecognitionClient(url, api_key=api_key, compress=compress) as pr,
        progress(console) as bar,
    ):
        make_map(pr, map_id, drive.sensor)
        task = bar.add_task(f"ingest {drive.name}", total=len(frames), rate=0.0, latency=0.0)
        for n, (i, points) in enumerate(drive.scans(frames, skipped), start=1):
            t = time.monotonic()
            kf = pr.insert_keyframe(
                map_id,
                points,
                keyframe_id=f"{session}-{i:06d}",
                timestamp=float(drive.times[i]),
                robot_id=robot,
                session_id=session,
                pose=drive.pose(i),
                sensor=drive.sensor,
                mount=drive.mount,
            )
            created += bool(kf.created)
            retried += bool(kf.retried and not kf.created)
            now = time.monotonic()
            done = n + len(skipped)
            bar.update(task, completed=done, rate=n / (now - t0), latency=(now - t) * 1e3)
    sent = len(frames) - len(skipped)
    lost = (
        f" ({retried} of them answered after a retry whose first answer was lost: written by "
        "that try, or before)"
        if retried
        else ""
    )
    out.print(
        f"{sent} scans → map {map_id}: {created} new keyframes, "
        f"{sent - created} already there{lost}; {time.monotonic() - t0:.1f} s"
    )
    report_skipped(skipped, len(frames))


@app.command("query", epilog="Example:\n\n  overlapmamba-client query scan.bin --map town -k 5")
@errors
def query(
    scan: Annotated[Path, typer.Argument(help=".bin, .npy or .pcd scan")],
    map_id: MapOpt,
    k: Annotated[int, typer.Option("-k", min=1, help="matches to show")] = 5,
    verify: VerifyOpt = True,
    sensor: SensorOpt = None,
    mount: MountOpt = None,
    url: UrlOpt = DEFAULT_URL,
    api_key: KeyOpt = None,
) -> None:
    """The top-k places for one scan, with yaw, each verified candidate's relative pose and
    fitness, and the loop-closure verdict with its pose."""
    with client(url, api_key, mount) as pr:
        r = pr.query(map_id, scan, k=k, verify=verify, sensor=sensor)
    table = Table(
        "rank", "keyframe", "distance", "yaw °", "verified", "fitness", "x, y m / yaw °", "robot"
    )
    skipped: list[str] = []  # why candidates were not registered, each reason once
    for rank, m in enumerate(r.matches, start=1):
        yaw = "" if m.yaw_deg is None else f"{m.yaw_deg:.1f}"
        v = m.verification
        if v is not None and v.verified is None and v.reason and v.reason not in skipped:
            skipped.append(v.reason)
        table.add_row(
            str(rank),
            m.keyframe_id,
            f"{m.distance:.5f}",
            yaw,
            "" if v is None else {True: "yes", False: "no", None: "skipped"}[v.verified],
            "" if v is None or v.fitness is None else f"{v.fitness:.3f}",
            pose_text(m.relative_pose),
            m.robot_id,
        )
    out.print(table)
    for reason in skipped:
        out.print(f"skipped: {reason}")
    lc = r.loop_closure
    if lc.accepted and lc.verified:
        out.print(f"loop closure: ACCEPTED, verified: {lc.keyframe_id} (fitness {lc.fitness:.3f})")
        out.print(f"relative pose T_keyframe←query:\n{matrix_text(lc.relative_pose)}")
    elif lc.verified is False:
        out.print("loop closure: not accepted (no candidate passed verification)")
    else:
        out.print(
            f"loop closure: {'ACCEPTED' if lc.accepted else 'not accepted'}, descriptor only "
            f"(threshold {lc.threshold:g}, margin {lc.margin_top1_top2})"
        )


@app.command(
    "observe",
    epilog="Example:\n\n  overlapmamba-client observe data/synth/val --map town --robot r1",
)
@errors
def observe(
    seq_dir: Annotated[Path, typer.Argument(help=DRIVE_HELP)],
    map_id: MapOpt,
    robot: Annotated[str, typer.Option(help="robot id")] = "robot-1",
    session: Annotated[
        str | None, typer.Option(help="session \\[default: the drive's name, as an id]")
    ] = None,
    every: Annotated[int, typer.Option(min=1, help="use every N-th scan")] = 1,
    topic: TopicOpt = None,
    odometry: OdometryOpt = None,
    tf: TfOpt = None,
    k: Annotated[int, typer.Option("-k", min=1)] = 5,
    verify: VerifyOpt = True,
    sensor: SensorOpt = None,
    mount: MountOpt = None,
    record: Annotated[
        Path | None,
        typer.Option(help="write an MCAP of robot poses, keyframes and loop closures (Foxglove)"),
    ] = None,
    g2o: Annotated[
        Path | None,
        typer.Option(
            help="write the drive's pose graph (g2o text): its scans' poses, odometry edges "
            "and each verified loop closure with the server's covariance"
        ),
    ] = None,
    odometry_sigma_m: Annotated[
        float, typer.Option(min=1e-9, help="with --g2o: the odometry edges' σ per axis, metres")
    ] = 0.1,
    odometry_sigma_deg: Annotated[
        float, typer.Option(min=1e-9, help="with --g2o: and per rotation axis, degrees")
    ] = 1.0,
    g2o_for: GraphReaderOpt = GraphReader.g2o,
    url: UrlOpt = DEFAULT_URL,
    api_key: KeyOpt = None,
) -> None:
    """Replay a drive as a robot (observe: query, then insert when due); print each loop
    closure as it is detected, with its relative pose when verified."""
    for flag, path in (("--record", record), ("--g2o", g2o)):
        if path is not None and within(path, seq_dir):
            raise ValueError(
                f"{flag} {path} is the drive {seq_dir} or inside it: it would overwrite what "
                "is being replayed; write it elsewhere"
            )
    outfiles.check_outputs(("--record", record, None), ("--g2o", g2o, ("g2o",)))
    if g2o is None and g2o_for != GraphReader.g2o:
        raise ValueError(f"--g2o-for {g2o_for.value} says whom --g2o FILE is for: give --g2o")
    drive = open_drive(seq_dir, topic=topic, odometry=odometry, tf=tf, sensor=sensor, mount=mount)
    note_unposed(drive)
    graph = None
    if g2o is not None:
        if drive.poses is None:
            raise ValueError(
                f"--g2o needs the drive's poses (its vertices and odometry edges): {seq_dir} "
                "has none; give --odometry or --tf for a bag"
            )
        sigma = (odometry_sigma_m, odometry_sigma_deg)
        graph = PoseGraph.for_reader(*sigma, len(drive), g2o_for.value)
    session = session or drive.session
    closures = inserted = 0
    frames = range(0, len(drive), every)
    skipped: list[str] = []
    with contextlib.ExitStack() as stack:
        if graph is not None and g2o is not None:  # written last: after the recording's end
            stack.callback(kept_graph, graph, g2o, g2o.exists())  # after the graph's exit
            stack.enter_context(graph.written_to(g2o))
        pr = stack.enter_context(client(url, api_key))
        rec = None
        if record is not None:
            from overlapmamba.client.recording import MapRecording

            existed = record.exists()
            made = MapRecording(record)

            def kept() -> None:  # after the recording's own exit, on a failed replay
                if made.incomplete is not None:
                    stays = "is as it was" if existed else "was not written"
                    console.print(
                        f"[yellow]note:[/] the replay stopped; what it recorded is in "
                        f"{escape(str(made.incomplete))} ({escape(str(record))} {stays})"
                    )

            stack.callback(kept)
            rec = stack.enter_context(made)
        make_map(pr, map_id, drive.sensor)
        for i, points in drive.scans(frames, skipped):
            o = pr.observe(
                map_id,
                points,
                robot_id=robot,
                session_id=session,
                timestamp=float(drive.times[i]),
                pose=drive.pose(i),
                k=k,
                verify=verify,
                sensor=drive.sensor,
                mount=drive.mount,
            )
            inserted += o.keyframe is not None
            lc = o.loop_closure
            if graph is not None:
                graph.scan(i, drive.pose(i), o.keyframe)
                if lc.accepted and lc.verified:
                    stored = next(
                        (m.pose for m in o.matches if m.keyframe_id == lc.keyframe_id), None
                    )
                    graph.closure(i, lc.keyframe_id, lc.relative_pose, lc.covariance, stored)
            if rec is not None:
                rec.observe(pr, map_id, robot, float(drive.times[i]), drive.pose(i), o)
            if lc.accepted and o.matches:
                closures += 1
                if lc.verified:
                    out.print(
                        f"frame {i}: verified loop closure with {lc.keyframe_id} (fitness "
                        f"{lc.fitness:.3f}; x, y m / yaw °: {pose_text(lc.relative_pose)})"
                    )
                else:
                    m = o.matches[0]
                    yaw = "" if m.yaw_deg is None else f", yaw {m.yaw_deg:.1f}°"
                    out.print(
                        f"frame {i}: loop closure with {m.keyframe_id} (descriptor only, "
                        f"distance {m.distance:.5f}{yaw})"
                    )
    sent = len(frames) - len(skipped)
    out.print(f"{sent} scans observed: {inserted} inserted, {closures} loop closures")
    if record is not None:
        out.print(f"recorded {record} (open it in Foxglove: a 3D panel, frame 'map')")
    if graph is not None and g2o is not None:
        out.print(
            f"wrote {g2o} (for {graph.reader}): {len(graph.scans)} scans, {graph.others} "
            "keyframes of other "
            f"drives, {len(graph.loops)} loop edges"
            + "".join(f"; {n} closures left out: {why}" for why, n in graph.left_out.items())
        )
    report_skipped(skipped, len(frames))


def kept_graph(graph: PoseGraph, g2o: Path, existed: bool) -> None:
    """A failed replay's note: where its pose graph so far was kept, or why it was not."""
    what = f"writing {escape(str(g2o))} failed" if graph.write_failed else "the replay stopped"
    if graph.incomplete is not None:
        stays = "is as it was" if existed else "was not written"
        console.print(
            f"[yellow]note:[/] {what}; its pose graph so far is in "
            f"{escape(str(graph.incomplete))} ({escape(str(g2o))} {stays})"
        )
    elif graph.lost is not None:
        console.print(f"[yellow]note:[/] {what}; its pose graph was lost ({escape(graph.lost)})")


@app.command("stats")
@errors
def stats(
    map_id: Annotated[str | None, typer.Option("--map", "-m", help="one map's stats")] = None,
    watch: Annotated[bool, typer.Option("--watch", help="refresh until Ctrl-C")] = False,
    interval: Annotated[float, typer.Option(min=0.2, help="seconds between refreshes")] = 2.0,
    url: UrlOpt = DEFAULT_URL,
    api_key: KeyOpt = None,
) -> None:
    """Recognition statistics (counts, latency percentiles, robots). With ``--watch`` on a
    terminal the table refreshes in place; written to a file or a pipe, each refresh is
    printed whole and flushed (a log keeps them, and a stopped watch loses none)."""
    with client(url, api_key) as pr:
        if not watch:
            out.print(stats_table(pr.stats(map_id)))
            return
        if not out.is_terminal:
            try:
                while True:
                    out.print(stats_table(pr.stats(map_id)))
                    out.file.flush()
                    time.sleep(interval)
            except KeyboardInterrupt:
                return
        with Live(stats_table(pr.stats(map_id)), console=out, auto_refresh=False) as live:
            try:
                while True:
                    time.sleep(interval)
                    live.update(stats_table(pr.stats(map_id)), refresh=True)
            except KeyboardInterrupt:
                pass


@app.command(
    "simulate-fleet",
    epilog="Example:\n\n  overlapmamba-client simulate-fleet --robots 8 --map fleet "
    "--sequence data/synth/val --duration 60 --rate 10",
)
@errors
def simulate_fleet(
    map_id: MapOpt,
    sequence: Annotated[
        list[Path], typer.Option("--sequence", "-s", help="drive(s) to replay; repeatable")
    ],
    topic: TopicOpt = None,
    odometry: OdometryOpt = None,
    tf: TfOpt = None,
    sensor: SensorOpt = None,
    mount: MountOpt = None,
    robots: Annotated[int, typer.Option(min=1, max=256)] = 4,
    duration: Annotated[float, typer.Option(min=0.1, help="seconds")] = 60.0,
    rate: Annotated[float, typer.Option(min=0.01, help="scans per second per robot")] = 10.0,
    scans: Annotated[
        int | None,
        typer.Option(
            min=1,
            help="each robot stops after this many scans, --duration only bounds the run: "
            "the same stretches of the drives on any machine, so recall compares",
        ),
    ] = None,
    k: Annotated[int, typer.Option("-k", min=1)] = 5,
    out_json: Annotated[Path, typer.Option("--out", help="report JSON")] = Path(
        "fleet-report.json"
    ),
    plot: Annotated[Path | None, typer.Option(help="latency plot PNG")] = Path("fleet-latency.png"),
    seed: Annotated[int, typer.Option(help="offsets and session names")] = 0,
    url: UrlOpt = DEFAULT_URL,
    api_key: KeyOpt = None,
) -> None:
    """N robots replay drives concurrently through observe; report throughput, latency,
    errors and loop closures against ground truth."""
    from overlapmamba.client.fleet import check_outputs, simulate, write_outputs

    check_outputs(out_json, plot)
    drives = [
        open_drive(p, topic=topic, odometry=odometry, tf=tf, sensor=sensor, mount=mount)
        for p in sequence
    ]
    report, samples = asyncio.run(
        simulate(
            url,
            map_id,
            drives,
            robots=robots,
            duration_s=duration,
            rate_hz=rate,
            api_key=api_key,
            k=k,
            seed=seed,
            scans=scans,
        )
    )
    write_outputs(report, samples, out_json, plot)
    out.print(fleet_table(report, robots, rate))
    out.print(f"wrote {out_json}" + (f" and {plot}" if plot else ""))
    if report.observations and report.throughput_per_s == 0:  # every observation failed
        console.print("[bold red]error:[/] no observation was answered (the errors above)")
        raise typer.Exit(1)


def main() -> None:
    app()
