"""Train on a lent GPU machine: the towns simulated again there, several runs side by side.

A lent machine (one GPU, 16 cores, no network, a few minutes) receives the repository and
64 MiB beside it, none of this machine's data. The scans are cheap to simulate again from
their presets' seeds on its cores; the pair and loop tables are not (minutes a town here),
so they travel, with the manifests they were made beside:

    python benchmarks/lent_gpu.py pack TOWN… --carry .carry        # here: the tables
    python benchmarks/lent_gpu.py prepare TOWN… --carry .carry     # there: simulate, project
    python benchmarks/lent_gpu.py launch PRESET… --device cuda     # there: trainings, detached
    python benchmarks/lent_gpu.py collect PRESET… --out DIR [--stop]  # their best.pt, metrics
    python benchmarks/lent_gpu.py window TOWN… --presets PRESET… --seconds S --out DIR
    python benchmarks/lent_gpu.py wheels --dest .whl                # here: what it lacks

``pack`` checks that each carried loop table's fingerprint is what this repository computes
for the scans it was made on (so patching it there is the same computation over the
re-simulated scans). ``prepare`` simulates every town in a process of its own (a preset
name: ``overlapmamba.synth.presets``), installs its tables, gives the loop table the new
scans' fingerprint (the generator is deterministic up to a few returns at edges: previous
loans found every town's ``data_sha256`` changed, same worlds, drives and poses), and
projects the range images every training preset named by ``--input-preset`` takes, so the
runs start at once. ``launch`` starts each preset's ``overlapmamba train`` in its own
session (it outlives the command that started it, as a lent machine allows); ``collect``
copies each run's ``best.pt``, ``metrics.json`` and log tail to ``--out`` and, with
``--stop``, ends the runs first (the last finished epoch is on disk). ``window`` is the
three in one call, for a lease whose machine goes back moments after a call ends: it
prepares, launches, reports each run's finished epochs once a minute, and ``S`` seconds after
it started collects with ``--stop`` (the runs' logs packed beside, ``logs.tar.gz``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from reports_kit import write_report

ROOT = Path(__file__).resolve().parents[1]
SYNTH = ROOT / "data" / "synth"
TABLES = ("overlaps.npz", "loops.npz")
LOGS = ROOT / "runs" / "lent-logs"


def loop_fingerprint(town: Path) -> tuple[str, str]:
    """(stored, computed): the fingerprint in ``town``'s loop table and the one this
    repository computes for its scans and the table's parameters."""
    gt, computed = _loop_table(town)
    return str(gt.params.get("fingerprint")), computed


def _loop_table(town: Path) -> tuple[Any, str]:
    """``town``'s loop table and the fingerprint its scans give it
    (``overlapmamba.train.evaluate.shipped_loops``, as evaluation checks it)."""
    from overlapmamba.core.datasets import open_sequence
    from overlapmamba.train.evaluate import shipped_loops

    found = shipped_loops(open_sequence(town))
    if found is None:
        raise SystemExit(f"{town}: no loop table (ground_truth/loops.npz)")
    return found


def pack(towns: list[str], carry: Path) -> None:
    from overlapmamba.synth.presets import preset

    for name in towns:
        src, dst = SYNTH / name, carry / name
        manifest = json.loads((src / "manifest.json").read_text())
        if manifest["config"] != json.loads(json.dumps(preset(name).model_dump())):
            raise SystemExit(f"{src}: made with another config than the preset {name!r} now")
        stored, computed = loop_fingerprint(src)
        if stored != computed:
            raise SystemExit(f"{src}: its loop table's fingerprint is not recomputed here")
        dst.mkdir(parents=True, exist_ok=True)
        for f in TABLES:
            if (src / "ground_truth" / f).is_file():
                shutil.copy2(src / "ground_truth" / f, dst / f)
        shutil.copy2(src / "manifest.json", dst / "manifest.json")
        size = sum(p.stat().st_size for p in dst.iterdir()) / 1e6
        print(f"{name}: {sorted(p.name for p in dst.iterdir())} {size:.1f} MB")


def prepare_one(name: str, carry: Path, workers: int, input_presets: list[str]) -> dict:
    """Simulate one town, install its carried tables, project its range images."""
    from overlapmamba.synth.generate import generate
    from overlapmamba.synth.presets import preset

    out = SYNTH / name
    row: dict[str, Any] = {"town": name}
    t0 = time.perf_counter()
    if not (out / "manifest.json").is_file():
        shutil.rmtree(out, ignore_errors=True)
        made = generate(out, preset(name), workers=workers, ground_truth=False, progress=False)
        row |= {"frames": made["config"]["frames"], "data_sha256": made["data_sha256"]}
    row["sim_s"] = round(time.perf_counter() - t0, 1)
    if (carry / name).is_dir():
        old = json.loads((carry / name / "manifest.json").read_text())
        row["byte_identical"] = old["data_sha256"] == row.get("data_sha256")
        (out / "ground_truth").mkdir(exist_ok=True)
        for f in TABLES:
            if (carry / name / f).is_file():
                shutil.copy2(carry / name / f, out / "ground_truth" / f)
        if (out / "ground_truth" / "loops.npz").is_file():
            row["loop_fingerprint_patched"] = patch_loops(out)
    t1 = time.perf_counter()
    row["projected"] = project(out, input_presets)
    row["project_s"] = round(time.perf_counter() - t1, 1)
    return row


def patch_loops(town: Path) -> bool:
    """Give ``town``'s carried loop table the fingerprint and the content digest of the
    scans simulated here (they differ at a few edges from those it was made from)."""
    from overlapmamba.core.datasets import open_sequence

    gt, computed = _loop_table(town)
    content = open_sequence(town).content_digest()
    if gt.params.get("fingerprint") == computed and gt.params.get("content") == content:
        return False
    gt.params["fingerprint"] = computed
    gt.params["content"] = content
    gt.save(town / "ground_truth" / "loops.npz")
    return True


def project(town: Path, input_presets: list[str]) -> int:
    """Range images of ``town`` for each preset that trains or validates on it, cached where
    the trainer looks (one input a model config: the presets here share theirs)."""
    from overlapmamba.core.datasets import open_sequence
    from overlapmamba.core.sensors.input import check_mode
    from overlapmamba.train.model import OverlapMambaConfig
    from overlapmamba.train.presets import get_preset
    from overlapmamba.train.rangecache import range_images
    from overlapmamba.train.train_inputs import model_profile, training_input

    done = set()
    for name in input_presets:
        p = get_preset(name)
        paths = {str(ROOT / d) for d in (*p.data, p.val, *p.train.get("val_sensors", ()))}
        key = json.dumps(p.model, sort_keys=True)
        if str(town) not in paths or key in done:
            continue
        done.add(key)
        cfg = OverlapMambaConfig.from_dict(p.model)
        profile = model_profile(cfg)
        seq = open_sequence(town)
        inp = training_input(profile, seq, check_mode(cfg.sensor_input))
        range_images(seq, profile, sensor=inp, progress=False)
    return len(done)


def prepare(towns: list[str], carry: Path, workers: int, input_presets: list[str]) -> list[str]:
    """Every town in a process of its own, at once; a summary JSON per town. Returns the
    towns that failed."""
    from overlapmamba.synth.presets import preset

    LOGS.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    procs = {}
    for name in towns:
        cmd = [sys.executable, __file__, "prepare-one", name, "--carry", str(carry)]
        frames = preset(name).frames  # a 2,000-scan town gets twice a 1,000-scan one's workers
        cmd += ["--workers", str(max(workers, round(frames / 500))), "--input-preset"]
        cmd += input_presets
        log = (LOGS / f"prepare-{name}.log").open("w")
        procs[name] = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)
    failed = []
    for name, proc in procs.items():
        if proc.wait() != 0:
            failed.append(name)
            tail = (LOGS / f"prepare-{name}.log").read_text()[-1500:]
            print(f"prepare {name} failed ({proc.returncode}):\n{tail}", flush=True)
    rows = [json.loads((LOGS / f"prepare-{n}.json").read_text()) for n in towns if n not in failed]
    summary = {"towns": rows, "failed": failed, "prepare_s": round(time.perf_counter() - t0, 1)}
    write_report(LOGS / "prepare.json", summary)
    print(f"prepared {len(rows)} of {len(towns)} towns in {summary['prepare_s']} s", flush=True)
    return failed


def launch(presets: list[str], device: str, threads: int) -> dict[str, int]:
    """Each preset's training in a session of its own → {preset: pid} (also in LOGS)."""
    LOGS.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "PYTHONUNBUFFERED": "1"}
    pids: dict[str, int] = {}
    for name in presets:
        shutil.rmtree(ROOT / "runs" / name, ignore_errors=True)
        cmd = [sys.executable, "-m", "overlapmamba", "train", "--preset", name]
        cmd += ["--device", device]
        log = (LOGS / f"{name}.log").open("w")
        proc = subprocess.Popen(
            cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT, env=env, start_new_session=True
        )
        (LOGS / f"{name}.pid").write_text(f"{proc.pid}\n")
        print(f"{name}: pid {proc.pid}", flush=True)
        pids[name] = proc.pid
    return pids


def _alive(pid: int) -> bool:
    """Whether ``pid`` still runs: a child that ended is reaped (a zombie answers a signal
    as if it ran; a window once waited out its whole lease on three of them)."""
    try:
        if os.waitpid(pid, os.WNOHANG)[0] == pid:
            return False
    except ChildProcessError:
        pass  # not our child (launched by another call): ask the kernel
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def collect(presets: list[str], out: Path, stop: bool) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for name in presets:
        if not (LOGS / f"{name}.pid").is_file():
            print(f"== {name}: never launched", flush=True)
            continue
        pid = int((LOGS / f"{name}.pid").read_text())
        alive = _alive(pid)
        if stop and alive:
            os.killpg(pid, signal.SIGTERM)
            for _ in range(50):
                if not _alive(pid):
                    break
                time.sleep(0.2)
        run = ROOT / "runs" / name
        for f in ("best.pt", "metrics.json"):
            if (run / f).is_file():
                shutil.copy2(run / f, out / f"{name}-{f}")
        text = (LOGS / f"{name}.log").read_text(errors="replace").replace("\r", "\n")
        lines = [ln for ln in text.splitlines() if ln.strip() and "it/s" not in ln]
        print(f"== {name}: {'running' if alive else 'ended'}", flush=True)
        print("\n".join(lines[-6:]), flush=True)
        if (run / "metrics.json").is_file():
            m = json.loads((run / "metrics.json").read_text())
            for e in m["history"]:
                print(f"  epoch {e['epoch']}: val F1max {e['val']['all']['f1max']:.3f}", end="")
                for s, v in (e.get("val_sensors") or {}).items():
                    print(f" {s} {v['cross']['all']['f1max']:.3f}", end="")
                print(f" train {e.get('train_s', 0):.0f}s val {e.get('val_s', 0):.0f}s")
            print(f"  best {m['best']}")
    record = (
        json.loads((LOGS / "prepare.json").read_text()) if (LOGS / "prepare.json").is_file() else {}
    )
    record["device"] = machine()  # beside write_report's own record of the machine's CPU
    write_report(out / "prepare.json", record)


def window(towns: list[str], presets: list[str], seconds: float, out: Path, **opts: Any) -> None:
    """prepare, launch and, ``seconds`` after the start (or once every run has ended),
    collect with ``--stop``."""
    import tarfile

    t0 = time.monotonic()
    preflight(towns[0], opts["device"])
    failed = prepare(towns, opts["carry"], opts["workers"], presets)
    if failed:
        raise SystemExit(f"window: {', '.join(failed)} not prepared; no run launched")
    pids = launch(presets, opts["device"], opts["threads"])
    shown: dict[str, int] = {}
    while time.monotonic() - t0 < seconds and any(_alive(p) for p in pids.values()):
        time.sleep(5)
        for name in presets:
            done = _epochs_done(ROOT / "runs" / name)
            if done != shown.get(name, 0):
                shown[name] = done
                print(f"{time.monotonic() - t0:6.0f} s  {name}: {done} epochs done", flush=True)
    collect(presets, out, stop=True)
    with tarfile.open(out / "logs.tar.gz", "w:gz") as tar:
        tar.add(LOGS, arcname="lent-logs")


def preflight(town: str, device: str) -> None:
    """What a lent machine lacks shows here in seconds, not after its towns: two scans of
    ``town``'s preset simulated (the world's meshes, the ray caster, the writer) and one
    training step of a narrow network on ``device``."""
    import tempfile

    import torch

    from overlapmamba.synth.generate import generate
    from overlapmamba.synth.presets import preset
    from overlapmamba.train.model import OverlapMamba, OverlapMambaConfig
    from overlapmamba.train.recipes import NARROW

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        cfg = preset(town).model_copy(update={"frames": 2})
        generate(Path(tmp) / "town", cfg, workers=1, ground_truth=False, progress=False)
    net = OverlapMamba(OverlapMambaConfig.from_dict(NARROW)).to(device)
    x = torch.rand(4, 1, 64, 900, device=device)
    net(x)[0].pow(2).sum().backward()
    print(f"preflight on {device}: simulated and stepped in {time.perf_counter() - t0:.1f} s")


# What a lent machine's image lacks of what simulation and training import (its package list:
# the device tool's KINDS.md), as wheels for its Python (`wheels`; carried as .whl).
DEVICE_LACKS = (
    "pydantic",
    "pydantic-core",
    "annotated-types",
    "typing-inspection",
    "typing-extensions",
    "pypcd4",
    "python-neo-lzf",
    "trimesh",
    "embreex",
)


def wheels(dest: Path, python: str) -> None:
    """Download ``DEVICE_LACKS`` at this environment's versions, for CPython ``python``."""
    import importlib.metadata

    pins = [f"{name}=={importlib.metadata.version(name)}" for name in DEVICE_LACKS]
    cmd = [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:"]
    cmd += ["--python-version", python, "--implementation", "cp", "-d", str(dest)]
    for tag in (
        "manylinux_2_28",
        "manylinux_2_27",
        "manylinux_2_17",
        "manylinux2014",
        "manylinux1",
    ):
        cmd += ["--platform", f"{tag}_x86_64"]
    subprocess.run([*cmd, *pins], check=True)


def _epochs_done(run: Path) -> int:
    try:
        return len(json.loads((run / "metrics.json").read_text())["history"]) - 1
    except (OSError, ValueError, KeyError):
        return 0


def machine() -> dict[str, Any]:
    import platform

    import torch

    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "gpu": gpu,
        "cpus": os.cpu_count(),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("pack")
    a.add_argument("towns", nargs="+")
    a.add_argument("--carry", type=Path, default=ROOT / ".carry")
    for cmd in ("prepare", "prepare-one"):
        a = sub.add_parser(cmd)
        a.add_argument("towns", nargs="+")
        a.add_argument("--carry", type=Path, default=ROOT / ".carry")
        a.add_argument("--workers", type=int, default=2)
        a.add_argument("--input-preset", nargs="+", default=[])
    a = sub.add_parser("launch")
    a.add_argument("presets", nargs="+")
    a.add_argument("--device", default="cuda")
    a.add_argument("--threads", type=int, default=4)
    a = sub.add_parser("wheels")
    a.add_argument("--dest", type=Path, default=ROOT / ".whl")
    a.add_argument("--python", default="3.12")
    a = sub.add_parser("preflight")
    a.add_argument("town")
    a.add_argument("--device", default="cuda")
    a = sub.add_parser("window")
    a.add_argument("towns", nargs="+")
    a.add_argument("--presets", nargs="+", required=True)
    a.add_argument("--seconds", type=float, required=True)
    a.add_argument("--out", type=Path, required=True)
    a.add_argument("--carry", type=Path, default=ROOT / ".carry")
    a.add_argument("--workers", type=int, default=2)
    a.add_argument("--device", default="cuda")
    a.add_argument("--threads", type=int, default=4)
    a = sub.add_parser("collect")
    a.add_argument("presets", nargs="+")
    a.add_argument("--out", type=Path, required=True)
    a.add_argument("--stop", action="store_true")
    args = ap.parse_args()
    if args.cmd == "pack":
        pack(args.towns, args.carry)
    elif args.cmd == "prepare":
        prepare(args.towns, args.carry, args.workers, args.input_preset)
    elif args.cmd == "prepare-one":
        (name,) = args.towns
        row = prepare_one(name, args.carry, args.workers, args.input_preset)
        (LOGS / f"prepare-{name}.json").write_text(json.dumps(row) + "\n")
    elif args.cmd == "launch":
        launch(args.presets, args.device, args.threads)
    elif args.cmd == "wheels":
        wheels(args.dest, args.python)
    elif args.cmd == "preflight":
        preflight(args.town, args.device)
    elif args.cmd == "window":
        opts = {k: getattr(args, k) for k in ("carry", "workers", "device", "threads")}
        window(args.towns, args.presets, args.seconds, args.out, **opts)
    else:
        collect(args.presets, args.out, args.stop)


if __name__ == "__main__":
    main()
