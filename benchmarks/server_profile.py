"""Where a server's CPU goes under a fleet: py-spy's samples of the server and its
registration process, grouped by the part of the serving path they fall in.

    python benchmarks/server_profile.py                     # the default file and the one-pass file
    python benchmarks/server_profile.py --model FILE --py-spy /path/to/py-spy

For each model file in turn: a fresh ``overlapmamba serve`` with its defaults, ``--robots``
robots replaying ``--sequence`` through ``overlapmamba-client simulate-fleet`` (each robot
``--scans`` scans at ``--rate``); after ``--warmup`` seconds py-spy records the server and
its child processes for ``--seconds`` at ``--hz`` samples a second. Each sample is counted
in the first part whose code its stack holds (``PARTS``), else in "the rest": the event
loop, HTTP, the index and re-rank, and waits py-spy takes for work. py-spy is not a
dependency of the project (``pip install py-spy`` anywhere; ``--py-spy`` names its path).
Writes reports/service/server-profile.json.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

from bench_kit import fleet_command
from reports_kit import REPORTS, ROOT, shown_path, write_report
from rich.console import Console
from rich.table import Table

from overlapmamba.service.process import serve_process
from overlapmamba.train.modelfile import read_metadata

# (part, code whose frames mark it), first match wins: the encoder's onnxruntime session and
# C scan, registration (the child's GICP and the server's side of it), the projection of a
# scan into the network's input, and the pipe that carries points to the registration child
PARTS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("encoder", ("onnxruntime", "overlapmamba/core/scan_kernel.py", "service/fastscan.py")),
    ("registration", ("service/registration.py", "service/registrar.py", "small_gicp")),
    ("projection", ("core/projection.py", "core/views.py", "core/sensors/")),
    ("pipe to the registration process", ("multiprocessing/connection.py",)),
)
REST = "the rest"
NAMES = (*(part for part, _ in PARTS), REST)  # every sample counts in one of these
DEFAULT_MODELS = (
    ROOT / "models" / "overlapmamba-hdl64.onnx",
    ROOT / "models" / "overlapmamba-hdl64-one-pass.onnx",
)


def part_of(stack: str) -> str:
    """The part a sample's stack (py-spy's raw format: frames joined by ';') falls in."""
    for part, marks in PARTS:
        if any(mark in stack for mark in marks):
            return part
    return REST


def shares(raw: str) -> tuple[dict[str, float], int]:
    """Each part's share of the samples in py-spy's raw output (``STACK COUNT`` lines), and
    the samples counted."""
    counts: Counter[str] = Counter()
    for line in raw.splitlines():
        stack, _, n = line.rstrip().rpartition(" ")
        if stack and n.isdigit():
            counts[part_of(stack)] += int(n)
    total = sum(counts.values())
    if total == 0:
        raise SystemExit("py-spy recorded no samples: is the server busy, and may py-spy trace it?")
    return {p: counts[p] / total for p in NAMES}, total


def profile(model: Path, args: argparse.Namespace, tmp: Path, spy: str) -> dict[str, Any]:
    """One fresh server of ``model`` under the fleet, recorded by py-spy."""
    tag = model.stem
    raw, fleet = tmp / f"{tag}.txt", tmp / f"fleet-{tag}.json"
    with serve_process(
        tmp / f"data-{tag}", model=model, env={}, inherit_settings=False, startup_s=180, cwd=ROOT
    ) as srv:
        cmd = fleet_command(
            srv.url,
            fleet,
            robots=args.robots,
            sequence=args.sequence,
            rate=args.rate,
            duration=600,  # (the robots stop after --scans)
            scans=args.scans,
        )
        with (tmp / f"client-{tag}.log").open("w") as log:
            client = subprocess.Popen(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
            time.sleep(args.warmup)
            rec = [spy, "record", "--pid", str(srv.proc.pid), "--subprocesses", "--nonblocking"]
            rec += ["--duration", str(args.seconds), "--rate", str(args.hz)]
            rec += ["--format", "raw", "--output", str(raw)]
            done = subprocess.run(rec, capture_output=True, text=True)
            if client.wait() != 0:
                tail = (tmp / f"client-{tag}.log").read_text()[-2000:]
                raise SystemExit(f"simulate-fleet failed ({client.returncode}): {tail}")
    if done.returncode != 0 or not raw.exists():
        raise SystemExit(f"py-spy failed ({done.returncode}): {done.stderr[-2000:]}")
    got, samples = shares(raw.read_text())
    ran = json.loads(fleet.read_text())
    meta = read_metadata(model)
    return {
        "model": shown_path(model),
        "model_id": meta.model_id,
        "views": meta.views,
        "samples": samples,
        "shares": got,
        "fleet": {k: ran.get(k) for k in ("observations", "throughput_per_s", "errors")},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, action="append", help="default: the shipped files")
    ap.add_argument("--sequence", type=Path, default=ROOT / "data" / "synth" / "test")
    ap.add_argument("--robots", type=int, default=8)
    ap.add_argument("--rate", type=float, default=10.0, help="scans a second a robot asks")
    ap.add_argument("--scans", type=int, default=250, help="scans a robot")
    ap.add_argument("--warmup", type=float, default=8.0, help="seconds before recording")
    ap.add_argument("--seconds", type=int, default=40, help="seconds recorded")
    ap.add_argument("--hz", type=int, default=200, help="py-spy's samples a second")
    ap.add_argument("--py-spy", default=shutil.which("py-spy"), help="py-spy's path")
    ap.add_argument("--out", type=Path, default=REPORTS / "service" / "server-profile.json")
    args = ap.parse_args()
    if not args.py_spy or not shutil.which(args.py_spy):
        ap.error(
            f"py-spy not found ({args.py_spy or 'not on PATH'}): pip install py-spy "
            "(anywhere), then put it on PATH or give --py-spy PATH"
        )
    if not (args.sequence / "manifest.json").exists():
        ap.error(f"{args.sequence} is not made (make data)")
    console = Console()
    runs = []
    with tempfile.TemporaryDirectory(prefix="om-profile-") as tmp:
        for model in args.model or DEFAULT_MODELS:
            console.print(f"profiling {model} …")
            runs.append(profile(model, args, Path(tmp), args.py_spy))
    version = subprocess.run([args.py_spy, "--version"], capture_output=True, text=True)
    report = {
        "drive": shown_path(args.sequence),
        "robots": args.robots,
        "rate_hz": args.rate,
        "scans_per_robot": args.scans,
        "warmup_s": args.warmup,
        "recorded_s": args.seconds,
        "sample_hz": args.hz,
        "py_spy": version.stdout.strip(),
        "parts": list(NAMES),
        "runs": runs,
    }
    table = Table(title="where the server's CPU goes (share of py-spy's samples)")
    for col in ("model", *report["parts"], "observations/s"):
        table.add_column(col, justify="right")
    for r in runs:
        cells = [f"{100 * r['shares'][p]:.1f}%" for p in report["parts"]]
        table.add_row(Path(r["model"]).name, *cells, f"{r['fleet']['throughput_per_s']:.1f}")
    console.print(table)
    write_report(args.out, report)
    console.print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
