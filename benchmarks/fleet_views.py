"""What a fleet gets from where the views meet: the fleet simulator against a real service of
each model, in alternating rounds on one machine (A, B, A, B, …), so that drift hits both.

Default: the shipped model (three views met at the descriptors) against the same weights
with the views met at the tokens (``models/overlapmamba-hdl64-tokens.onnx``, written by
``overlapmamba export models/overlapmamba-hdl64.onnx --views 3 --meet tokens`` and
calibrated on ``val`` by the three calibration benchmarks). Each round is
``overlapmamba-client simulate-fleet --robots N --sequence SEQ --duration S --rate R``
against a fresh ``overlapmamba serve`` of that model with default settings (verification
on): observations a second, latency, errors, verified closures' precision and recall.

    python benchmarks/fleet_views.py [--rounds 2] [--robots 8] [--sequence data/synth/val]

Writes JSON (default reports/client/fleet-views.json).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from bench_kit import ROOT, SERVER_CPU_S, OtherLoad, other_load
from reports_kit import REPORTS, write_report
from rich.console import Console
from rich.table import Table

from overlapmamba.service.process import serve_process
from overlapmamba.train.modelfile import read_metadata

MODELS = {
    "descriptors (shipped)": ROOT / "models" / "overlapmamba-hdl64.onnx",
    "tokens": ROOT / "models" / "overlapmamba-hdl64-tokens.onnx",
}
KEPT = ("observations", "throughput_per_s", "latency_ms", "errors", "precision", "recall")
KEPT += ("verified_closures", "loop_closures")


def _children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)  # children waited for: server, simulator
    return r.ru_utime + r.ru_stime


def round_of(model: Path, args: argparse.Namespace, tmp: Path, i: int) -> dict[str, Any]:
    """One simulate-fleet run against a fresh server of ``model``; the server's and the
    simulator's CPU time count as this benchmark's own (``OtherLoad``)."""
    cpu0 = _children_cpu_s()
    data = tmp / f"data-{i}"
    out = tmp / f"fleet-{i}.json"
    with serve_process(data, model=model, inherit_settings=False, startup_s=180, cwd=ROOT) as srv:
        cmd = [str(Path(sys.executable).parent / "overlapmamba-client"), "simulate-fleet"]
        cmd += ["--robots", str(args.robots), "--sequence", str(args.sequence)]
        cmd += ["--duration", str(args.duration), "--rate", str(args.rate)]
        cmd += ["--map", "fleet", "--url", srv.url, "--out", str(out)]
        cmd += ["--plot", str(tmp / f"fleet-{i}.png")]
        subprocess.run(cmd, check=True, capture_output=True, cwd=ROOT)
    SERVER_CPU_S[0] += _children_cpu_s() - cpu0
    got = json.loads(out.read_text())
    return {k: got.get(k) for k in KEPT}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=2, help="runs of each model, alternating")
    ap.add_argument("--robots", type=int, default=8)
    ap.add_argument("--sequence", type=Path, default=ROOT / "data" / "synth" / "val")
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--rate", type=float, default=10.0, help="scans a second asked per robot")
    ap.add_argument("--out", type=Path, default=REPORTS / "client" / "fleet-views.json")
    args = ap.parse_args()
    console = Console()
    for name, path in MODELS.items():
        if not path.is_file():
            raise SystemExit(f"{path} ({name}) is missing: see this script's docstring")
    if not (args.sequence / "manifest.json").is_file():
        raise SystemExit(f"{args.sequence} is not a generated town: run `make data`")

    runs: dict[str, list[dict[str, Any]]] = {k: [] for k in MODELS}
    watch = OtherLoad()
    with tempfile.TemporaryDirectory(prefix="om-fleet-views-") as tmp:
        i = 0
        for r in range(args.rounds):
            for name, path in MODELS.items():
                runs[name].append(round_of(path, args, Path(tmp), i))
                i += 1
                got = runs[name][-1]
                console.print(f"round {r + 1}, {name}: {got['throughput_per_s']:.1f} obs/s")
    busy = other_load(console, "fleet", watch, "during")
    result = {
        "robots": args.robots,
        "sequence": str(
            args.sequence.relative_to(ROOT) if args.sequence.is_absolute() else args.sequence
        ),
        "duration_s": args.duration,
        "rate_hz": args.rate,
        "rounds": args.rounds,
        "other_load": busy,
        "models": {
            k: {"path": str(p.relative_to(ROOT)), **_meta(p), "runs": runs[k]}
            for k, p in MODELS.items()
        },
    }
    write_report(args.out, result)
    t = Table(title=f"{args.robots} robots, {args.duration:.0f} s a round, alternating")
    for col in ("model", "observations/s per round", "median", "p50 latency", "errors"):
        t.add_column(col)
    for name, rs in runs.items():
        tput = [x["throughput_per_s"] for x in rs]
        t.add_row(
            name,
            ", ".join(f"{x:.1f}" for x in tput),
            f"{np.median(tput):.1f}",
            ", ".join(f"{x['latency_ms']['p50']:.0f} ms" for x in rs),
            str(sum(sum((x["errors"] or {}).values()) for x in rs)),
        )
    console.print(t)
    console.print(f"wrote {args.out}")


def _meta(path: Path) -> dict[str, Any]:
    m = read_metadata(path)
    return {"model_id": m.model_id, "views": m.views, "graph_views": m.graph_views}


if __name__ == "__main__":
    main()
