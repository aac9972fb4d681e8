"""Where a scan's firings fall, and what it does to each model file: every town of a set
rendered twice, its head firing at the same azimuths every turn (``locked``, every preset
made before generator 1.8.0) and with each scan's firings a random fraction of a spacing
later (``drifting``, the ``NAME-drift`` presets, ``make data-drift``), as a real head's drift
from turn to turn (:mod:`overlapmamba.synth.lidar`). The two renderings share the drive and
every other draw, so a row's two columns differ by the firings alone.

Why it matters: a range image's columns meet a locked head's firings in the same pattern in
every scan (the kitti-hdl64's 2,083 firings a turn give 900 columns two or three each, always
the same ones), and every model here was trained on locked towns. A file whose columns start
at each scan's own mean bearing (``--column-phase aligned``, the one-pass twin) meets them in
a new pattern every scan even in a locked town, as every file does on a real head.

For each model file and town, ``overlapmamba eval --checkpoint FILE --sequence TOWN
--rerank 20,0.2`` (the service's second stage), with ``--scan-context`` for the first file
(Scan Context's height map beside them): loop closure F1max and Recall@1, all / same /
reverse direction, the descriptor alone and two stages. ``val`` rows are the selection town's;
the summary is the test towns' (``test``, ``test-b``, ``test-c``).

    python benchmarks/firing_phase.py [--town val --town test ...] [--model FILE ...]

Needs the towns (``make data data-drift``). Writes JSON (default
reports/model/firing-phase.json). ≈ 40 min on 2 cores for the four files and four towns.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from reports_kit import REPORTS, ROOT, shown_path, write_report
from rich.console import Console
from rich.table import Table

from overlapmamba.train.modelfile import read_metadata, with_views

MODELS = ROOT / "models"
DEFAULT_MODELS = {
    "three views (shipped)": MODELS / "overlapmamba-hdl64.onnx",
    "views met at the tokens": MODELS / "overlapmamba-hdl64-tokens.onnx",
    "one view, aligned columns": MODELS / "overlapmamba-hdl64-one-view.onnx",
}
PLAIN = "one view, the sensor's columns"  # the shipped weights at one view: no turn invariance
TOWNS = ("val", "test", "test-b", "test-c")
PHASES = ("locked", "drifting")
SUBSETS = ("all", "same", "reverse")
STAGES = {"descriptor": "metrics", "two_stages": "metrics_reranked"}


def check_twins(locked: Path, drift: Path) -> None:
    """``drift`` must be ``locked``'s town rendered with drifting firings, nothing else."""
    for p in (locked, drift):
        if not (p / "manifest.json").is_file():
            raise SystemExit(f"{p} is not a generated town: run `make data data-drift`")
    a = json.loads((locked / "manifest.json").read_text())["config"]
    b = json.loads((drift / "manifest.json").read_text())["config"]
    if a.get("firing_phase", "locked") != "locked" or b.get("firing_phase") != "drifting":
        raise SystemExit(f"{locked} must be locked and {drift} drifting")
    differ = sorted(k for k in {*a, *b} - {"firing_phase", "preset"} if a.get(k) != b.get(k))
    if differ:
        raise SystemExit(f"{drift} is not {locked} with drifting firings: {differ} differ")


def evaluate(model: Path, town: Path, rerank: str, scan_context: bool, tmp: Path) -> dict:
    js = tmp / "eval.json"
    cmd = [sys.executable, "-m", "overlapmamba", "eval", "--checkpoint", str(model)]
    cmd += ["--sequence", str(town), "--rerank", rerank, "--json", str(js), "-q"]
    cmd += ["--scan-context"] if scan_context else []
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{done.stdout[-1500:]}{done.stderr[-1500:]}")
    got = json.loads(js.read_text())
    keys = {**STAGES, **({"scan_context": "metrics_scan_context"} if scan_context else {})}
    return {
        stage: {sub: {m: float(got[key][sub][m]) for m in ("f1max", "recall@1")} for sub in SUBSETS}
        for stage, key in keys.items()
    }


def summary(rows: dict, towns: list[str]) -> dict[str, Any]:
    """Per file and stage, over the test towns: the mean all-revisit F1max locked and
    drifting, and their difference."""
    tests = [t for t in towns if t != "val"]
    out: dict[str, Any] = {"towns": tests}
    for name, by_town in rows.items():
        out[name] = {}
        for stage in (*STAGES, "scan_context"):
            if not tests or stage not in by_town[tests[0]]["locked"]:
                continue
            f1 = {
                ph: float(np.mean([by_town[t][ph][stage]["all"]["f1max"] for t in tests]))
                for ph in PHASES
            }
            out[name][stage] = {**f1, "drifting_minus_locked": f1["drifting"] - f1["locked"]}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--town", action="append", default=[], help=f"default: {' '.join(TOWNS)}")
    ap.add_argument(
        "--model", type=Path, action="append", default=[], help="default: the shipped three"
    )
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "synth")
    ap.add_argument("--rerank", default="20,0.2", help="the second stage: SHORTLIST,WEIGHT")
    ap.add_argument("--out", type=Path, default=REPORTS / "model" / "firing-phase.json")
    args = ap.parse_args()
    towns = args.town or list(TOWNS)
    for t in towns:
        check_twins(args.data / t, args.data / f"{t}-drift")
    console = Console(width=160)
    t0 = time.perf_counter()
    rows: dict[str, dict] = {}
    files: dict[str, dict[str, object]] = {}
    with tempfile.TemporaryDirectory(prefix="om-firing-") as tmp_name:
        tmp = Path(tmp_name)
        models = {shown_path(p): p for p in args.model} or dict(DEFAULT_MODELS)
        if not args.model:
            models[PLAIN] = tmp / "one-view-sensor-columns.onnx"
            with_views(DEFAULT_MODELS["three views (shipped)"], models[PLAIN], 1)
        for name, path in models.items():
            if not path.is_file():
                raise SystemExit(f"{path} ({name}) is missing")
            meta = read_metadata(path)
            files[name] = {
                "path": "the shipped file at one view (with_views(..., 1))"
                if name == PLAIN
                else shown_path(path),
                "model_id": meta.model_id,
                "views": meta.views,
                "column_phase": meta.column_phase,
            }
        for i, (name, path) in enumerate(models.items()):
            rows[name] = {}
            for town in towns:
                rows[name][town] = {}
                for phase in PHASES:
                    seq = args.data / (town if phase == "locked" else f"{town}-drift")
                    got = evaluate(path, seq, args.rerank, i == 0, tmp)
                    rows[name][town][phase] = got
                    console.print(
                        f"{name}, {seq.name}: descriptor {got['descriptor']['all']['f1max']:.3f}"
                        f", two stages {got['two_stages']['all']['f1max']:.3f} "
                        f"({time.perf_counter() - t0:.0f} s)"
                    )
    sc = next(iter(rows))
    rows["Scan Context"] = {
        t: {ph: {"scan_context": rows[sc][t][ph].pop("scan_context")} for ph in PHASES}
        for t in towns
    }
    result = {
        "towns": {t: [f"data/synth/{t}", f"data/synth/{t}-drift"] for t in towns},
        "rerank": args.rerank,
        "models": files,
        "rows": rows,
        "summary": summary(rows, towns),
        "seconds": time.perf_counter() - t0,
    }
    write_report(args.out, result)

    table = Table(title="loop closure, all revisits: F1max locked → drifting firings")
    table.add_column("file")
    table.add_column("stage")
    for t in towns:
        table.add_column(t, justify="right")
    for name, by_town in rows.items():
        for stage in (*STAGES, "scan_context"):
            if stage not in by_town[towns[0]]["locked"]:
                continue
            cells = [
                f"{by_town[t]['locked'][stage]['all']['f1max']:.3f} → "
                f"{by_town[t]['drifting'][stage]['all']['f1max']:.3f}"
                for t in towns
            ]
            table.add_row(name, stage, *cells)
    console.print(table)
    console.print(f"wrote {args.out} ({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
