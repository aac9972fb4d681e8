"""What a fleet gets from where the views meet: the fleet simulator against a real service of
each model, in alternating rounds on one machine (A, B, A, B, …), so that drift hits both.

Default: the shipped model (three views met at the descriptors) against the same weights
with the views met at the tokens (``models/overlapmamba-hdl64-tokens.onnx``, written by
``overlapmamba export models/overlapmamba-hdl64.onnx --views 3 --meet tokens`` and
calibrated on ``val`` by the three calibration benchmarks), and against the same weights
with one view whose columns start at each scan's mean bearing
(``models/overlapmamba-hdl64-one-view.onnx``, written by ``overlapmamba export
models/overlapmamba-hdl64.onnx --views 1 --column-phase aligned`` and calibrated on ``val``
likewise): what one encoder pass a scan buys a fleet; and the
shipped file served with ``verify.stop_at_first = false`` (every candidate registered, as
before that became the default): what registering past a verified candidate costs. Each round
is ``overlapmamba-client simulate-fleet --robots N --sequence SEQ --duration S --rate R``
against a fresh ``overlapmamba serve`` of that model with default settings (verification
on): observations a second, latency, errors, verified closures' precision and recall.

Where the time goes: the CPU time the server spent while the fleet ran (from /proc, after it
was ready) and the simulator's own (the robots' client, on the same cores), each divided by
the observations, and the server's stage medians (``/v1/stats``). Their sum per observation
bounds the throughput any fleet gets on this machine: cores ÷ (server + client CPU an
observation), the ``ceiling`` column.

    python benchmarks/fleet_views.py [--rounds 2] [--robots 8] [--sequence data/synth/test]
        [--scans 250]

``--scans N``: each robot observes N scans a round (``simulate-fleet --scans``, as the
end-to-end load run asks), and ``--duration`` (then 300 s) only bounds a round; without it
a round lasts ``--duration`` (60 s), in which a slower model's robots get less far along the
drive, where the loops differ, so its recall is not the faster one's to compare.

``--model NAME`` (repeated) runs those models instead, e.g. the shipped file against the
every-sensor option (``models/overlapmamba-any-sensor.onnx``, one pass a scan, calibrated
on the validation towns of every sensor): ``--model "descriptors (shipped)" --model "every
sensor (the option)" --out reports/client/fleet-any-sensor.json``; the shipped file, the
one-view twin and the one-pass file (``--model "one pass, spectrum in the first stage"``,
``reports/client/fleet-one-pass.json``); or the shipped file under
the service's settings before encoder lanes and one-thread registration, and each change
alone: ``--model "descriptors (shipped)" --model "descriptors (shipped), settings before
lanes" --model "descriptors (shipped), one lane" --model "descriptors (shipped), GICP on 2
threads" --out reports/client/fleet-lanes.json``; or registration in a child process (the
default, ``verify.processes`` 1) against the server's own threads, for the one-pass file and
the shipped one: ``--model "one pass, spectrum in the first stage" --model "one pass,
registration in the server's threads" --model "descriptors (shipped)" --model "descriptors
(shipped), registration in the server's threads" --out reports/client/fleet-registrar.json``.
The server's CPU counts its registration processes.

Writes JSON (default reports/client/fleet-views.json).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from bench_kit import (
    CORES,
    ROOT,
    SERVER_CPU_S,
    OtherLoad,
    _pid_cpu_s,
    fleet_command,
    other_load,
)
from reports_kit import REPORTS, write_report
from rich.console import Console
from rich.table import Table

from overlapmamba.service.process import serve_process
from overlapmamba.train.modelfile import read_metadata

SHIPPED = ROOT / "models" / "overlapmamba-hdl64.onnx"
ONE_VIEW = ROOT / "models" / "overlapmamba-hdl64-one-view.onnx"
# name → (model file, the server's environment beside the defaults)
MODELS: dict[str, tuple[Path, dict[str, str]]] = {
    "descriptors (shipped)": (SHIPPED, {}),
    "tokens": (ROOT / "models" / "overlapmamba-hdl64-tokens.onnx", {}),
    "one view, aligned columns": (ONE_VIEW, {}),
    "descriptors (shipped), every candidate registered": (
        SHIPPED,
        {"OVERLAPMAMBA_VERIFY__STOP_AT_FIRST": "false"},
    ),
    "every sensor (the option)": (ROOT / "models" / "overlapmamba-any-sensor.onnx", {}),
    # the one-view twin with the yaw features' spectrum in its first stage (768 floats)
    "one pass, spectrum in the first stage": (
        ROOT / "models" / "overlapmamba-hdl64-one-pass.onnx",
        {},
    ),
    # the same first stage reduced to 256 floats by its principal directions on val
    # (overlapmamba.train.reduce_head)
    "one pass, 256 floats": (ROOT / "models" / "overlapmamba-hdl64-one-pass-256.onnx", {}),
    # the service's threads as they were before encoder lanes (batching.lanes), one-thread
    # registration (verify.threads) and batches of 2 became the defaults, and each of the
    # first two changes alone
    "descriptors (shipped), settings before lanes": (
        SHIPPED,
        {
            "OVERLAPMAMBA_BATCHING__LANES": "1",
            "OVERLAPMAMBA_VERIFY__THREADS": "2",
            "OVERLAPMAMBA_BATCHING__MAX_BATCH": "8",
        },
    ),
    "descriptors (shipped), one lane": (SHIPPED, {"OVERLAPMAMBA_BATCHING__LANES": "1"}),
    "descriptors (shipped), GICP on 2 threads": (SHIPPED, {"OVERLAPMAMBA_VERIFY__THREADS": "2"}),
    # encoder batches a lane (batching.max_batch): each lane holds its batch's working memory
    "descriptors (shipped), batches of 8": (SHIPPED, {"OVERLAPMAMBA_BATCHING__MAX_BATCH": "8"}),
    "descriptors (shipped), batches of 2": (SHIPPED, {"OVERLAPMAMBA_BATCHING__MAX_BATCH": "2"}),
    "descriptors (shipped), batches of 1": (SHIPPED, {"OVERLAPMAMBA_BATCHING__MAX_BATCH": "1"}),
    "one view, batches of 8": (ONE_VIEW, {"OVERLAPMAMBA_BATCHING__MAX_BATCH": "8"}),
    "one view, batches of 2": (ONE_VIEW, {"OVERLAPMAMBA_BATCHING__MAX_BATCH": "2"}),
    # registration in the server's own threads, as before verify.processes (small_gicp holds
    # Python's lock for each call: overlapmamba.service.registrar)
    "one pass, registration in the server's threads": (
        ROOT / "models" / "overlapmamba-hdl64-one-pass.onnx",
        {"OVERLAPMAMBA_VERIFY__PROCESSES": "0"},
    ),
    "descriptors (shipped), registration in the server's threads": (
        SHIPPED,
        {"OVERLAPMAMBA_VERIFY__PROCESSES": "0"},
    ),
}
# the models a plain run compares (--model picks others)
DEFAULT_MODELS = (
    "descriptors (shipped)",
    "tokens",
    "one view, aligned columns",
    "descriptors (shipped), every candidate registered",
)
STAGES = ("decode", "project", "encode", "search", "verify", "total")
KEPT = ("observations", "throughput_per_s", "latency_ms", "errors", "precision", "recall")
KEPT += ("verified_closures", "loop_closures", "verified_pose_right")


def _children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)  # children waited for: server, simulator
    return r.ru_utime + r.ru_stime


def round_of(
    model: Path, args: argparse.Namespace, tmp: Path, i: int, env: dict[str, str]
) -> dict[str, Any]:
    """One simulate-fleet run against a fresh server of ``model``; the server's and the
    simulator's CPU time count as this benchmark's own (``OtherLoad``), and each, divided by
    the observations, says where an observation's time goes."""
    import httpx

    cpu0 = _children_cpu_s()
    data = tmp / f"data-{i}"
    out = tmp / f"fleet-{i}.json"
    with serve_process(
        data, model=model, env=env, inherit_settings=False, startup_s=180, cwd=ROOT
    ) as srv:
        cmd = fleet_command(
            srv.url,
            out,
            robots=args.robots,
            sequence=args.sequence,
            rate=args.rate,
            duration=args.duration,
            scans=args.scans,
        )
        server0 = _pid_cpu_s(srv.proc.pid)
        with (tmp / f"client-{i}.log").open("w") as log:
            client = subprocess.Popen(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
            _, status, usage = os.wait4(client.pid, 0)  # its own CPU time, as it ends
        client.returncode = os.waitstatus_to_exitcode(status)
        server_s = _pid_cpu_s(srv.proc.pid) - server0
        if client.returncode:
            tail = (tmp / f"client-{i}.log").read_text()[-2000:]
            raise SystemExit(f"simulate-fleet failed ({client.returncode}): {tail}")
        stats = httpx.get(f"{srv.url}/v1/stats", timeout=30).json()["latency_ms"]
    SERVER_CPU_S[0] += _children_cpu_s() - cpu0 + usage.ru_utime + usage.ru_stime
    got = json.loads(out.read_text())
    n = max(int(got["observations"]), 1)
    server_ms = 1e3 * server_s / n
    client_ms = 1e3 * (usage.ru_utime + usage.ru_stime) / n
    return {
        **{k: got.get(k) for k in KEPT},
        "cpu_ms_per_observation": {"server": server_ms, "client": client_ms},
        "ceiling_per_s": 1e3 * CORES / (server_ms + client_ms),
        "stage_p50_ms": {k: stats[k]["p50"] for k in STAGES if k in stats},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=2, help="runs of each model, alternating")
    ap.add_argument("--robots", type=int, default=8)
    ap.add_argument("--sequence", type=Path, default=ROOT / "data" / "synth" / "test")
    ap.add_argument(
        "--duration", type=float, help="seconds a round [60; with --scans, its bound: 300]"
    )
    ap.add_argument("--scans", type=int, help="scans each robot observes a round")
    ap.add_argument("--rate", type=float, default=10.0, help="scans a second asked per robot")
    ap.add_argument("--out", type=Path, default=REPORTS / "client" / "fleet-views.json")
    ap.add_argument(
        "--model",
        action="append",
        choices=list(MODELS),
        help=f"a model to run (repeat; default: {', '.join(DEFAULT_MODELS)})",
    )
    args = ap.parse_args()
    if args.scans is not None and args.scans < 1:
        raise SystemExit(f"--scans must be at least 1; got {args.scans}")
    if args.duration is None:
        args.duration = 60.0 if args.scans is None else 300.0
    console = Console()
    models = {k: MODELS[k] for k in (args.model or DEFAULT_MODELS)}
    for name, (path, _) in models.items():
        if not path.is_file():
            raise SystemExit(f"{path} ({name}) is missing: see this script's docstring")
    if not (args.sequence / "manifest.json").is_file():
        raise SystemExit(f"{args.sequence} is not a generated town: run `make data`")

    runs: dict[str, list[dict[str, Any]]] = {k: [] for k in models}
    watch = OtherLoad()
    with tempfile.TemporaryDirectory(prefix="om-fleet-views-") as tmp:
        meta = {k: _meta(p) for k, (p, _) in models.items()}
        i = 0
        for r in range(args.rounds):
            for name, (path, env) in models.items():
                runs[name].append(round_of(path, args, Path(tmp), i, env))
                i += 1
                got = runs[name][-1]
                console.print(
                    f"round {r + 1}, {name}: {got['throughput_per_s']:.1f} obs/s, CPU an "
                    f"observation {got['cpu_ms_per_observation']['server']:.0f} ms server + "
                    f"{got['cpu_ms_per_observation']['client']:.0f} ms client"
                )
    busy = other_load(console, "fleet", watch, "during")
    result = {
        "robots": args.robots,
        "sequence": str(
            args.sequence.relative_to(ROOT) if args.sequence.is_absolute() else args.sequence
        ),
        "duration_s": args.duration,
        "scans_per_robot": args.scans,
        "rate_hz": args.rate,
        "rounds": args.rounds,
        "other_load": busy,
        "cores": CORES,
        "models": {
            k: {
                "path": str(p.relative_to(ROOT)),
                **meta[k],
                "settings": env,  # the server's environment beside defaults
                "runs": runs[k],
            }
            for k, (p, env) in models.items()
        },
    }
    write_report(args.out, result)
    each = f"{args.duration:.0f} s" if args.scans is None else f"{args.scans} scans a robot"
    t = Table(title=f"{args.robots} robots, {each} a round, alternating")
    cols = ("model", "observations/s per round", "median", "p50 latency", "errors")
    for col in (*cols, "CPU an observation: server + client", "ceiling"):
        t.add_column(col)
    for name, rs in runs.items():
        tput = [x["throughput_per_s"] for x in rs]
        t.add_row(
            name,
            ", ".join(f"{x:.1f}" for x in tput),
            f"{np.median(tput):.1f}",
            ", ".join(f"{x['latency_ms']['p50']:.0f} ms" for x in rs),
            str(sum(sum((x["errors"] or {}).values()) for x in rs)),
            ", ".join(
                f"{x['cpu_ms_per_observation']['server']:.0f} + "
                f"{x['cpu_ms_per_observation']['client']:.0f} ms"
                for x in rs
            ),
            ", ".join(f"{x['ceiling_per_s']:.1f}/s" for x in rs),
        )
    console.print(t)
    console.print(f"wrote {args.out}")


def _meta(path: Path) -> dict[str, Any]:
    m = read_metadata(path)
    return {"model_id": m.model_id, "views": m.views, "graph_views": m.graph_views}


if __name__ == "__main__":
    main()
