"""Shared fixtures: the real scans in ../shared/data (skipped cleanly when absent) and a
tiny seeded synthetic drive with a revisit."""

from __future__ import annotations

import importlib.util
import os
import pickle
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

# pytest-xdist's workers share the machine's cores: each computes (torch, OpenMP, BLAS) on
# its share, so two workers on 2 cores do not spin four threads. Set before numpy and torch
# start their pools; a test that wants another count sets it itself.
if (_workers := os.environ.get("PYTEST_XDIST_WORKER_COUNT")) is not None:
    os.environ.setdefault("OMP_NUM_THREADS", str(max(1, (os.cpu_count() or 1) // int(_workers))))

# The commands' rich consoles (and typer's error boxes) wrap at the terminal's width, 80 when
# there is none: a long temporary path then broke inside a word a test looked for. Wide
# enough for any path pytest makes; set before the commands' modules make their consoles. A
# test that wants a width passes COLUMNS itself.
os.environ["COLUMNS"] = "400"

import numpy as np
import pytest

from overlapmamba.core.poses import rotation_z, write_poses

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("OVERLAPMAMBA_SHARED_DATA", ROOT.parent / "shared" / "data"))


BENCHMARKS = ROOT / "benchmarks"


def benchmark_module(name: str) -> Any:
    """A script of benchmarks/ imported as a module (its own imports, e.g. ``reports_kit``,
    resolved from that folder as when it runs)."""
    sys.path.insert(0, str(BENCHMARKS))
    try:
        return importlib.import_module(name)
    finally:
        sys.path.remove(str(BENCHMARKS))


def resident_bytes(pid: int | str = "self") -> int:
    """A process's resident memory (Linux: ``/proc/PID/statm``); ``PROC_STATM`` says whether
    this machine has it."""
    pages = int(Path(f"/proc/{pid}/statm").read_text().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE")


PROC_STATM = Path("/proc/self/statm").exists()


def _need(sub: str) -> Path:
    path = SHARED_DATA / sub
    if not path.exists():
        pytest.skip(f"real LiDAR data not available: {path} is missing (see shared/data/README)")
    return path


@pytest.fixture(scope="session")
def kitti_seq_dir() -> Path:
    return _need("kitti00_0000-0100")


def kitti_head(kitti_dir: Path, out: Path, frames: int) -> Path:
    """The first ``frames`` scans of a KITTI sequence folder as a sequence of their own in
    ``out`` (scans linked, poses cut, calibration copied): a real drive small enough for a
    test that runs a whole evaluation over it."""
    (out / "velodyne").mkdir(parents=True)
    for i in range(frames):
        name = f"{i:06d}.bin"
        (out / "velodyne" / name).symlink_to(kitti_dir / "velodyne" / name)
    lines = (kitti_dir / "poses.txt").read_text().splitlines()[:frames]
    (out / "poses.txt").write_text("\n".join(lines) + "\n")
    shutil.copy(kitti_dir / "calib.txt", out / "calib.txt")
    return out


@pytest.fixture(scope="session")
def kitti_reference_dir() -> Path:
    return _need("kitti00_overlapnet_reference")


@pytest.fixture(scope="session")
def nuscenes_dir() -> Path:
    return _need("nuscenes_scene0061")


@pytest.fixture(scope="session", autouse=True)
def _session_cache(tmp_path_factory: pytest.TempPathFactory):
    """One cache folder for the run, never the user's. Range images, compiled kernels and
    ground truth are keyed by what they were made from, so tests share them safely: each tiny
    town is projected once per run instead of once per training call."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("OVERLAPMAMBA_CACHE", str(tmp_path_factory.mktemp("cache")))
        yield


@pytest.fixture(autouse=True)
def _torch_threads_kept():
    """torch's thread count as each test found it: runs compared across tests (and with the
    background run) compute in the same order only on the same count. Restored, not failed:
    an in-process service's FAISS index sets OpenMP's thread count for the whole process
    (``faiss.omp_set_num_threads``), and torch reads the same count."""
    torch = sys.modules.get("torch")
    before = torch.get_num_threads() if torch is not None else None
    yield
    torch = sys.modules.get("torch")
    if torch is not None and before is not None and torch.get_num_threads() != before:
        torch.set_num_threads(before)


def make_world(rng: np.random.Generator, extent: float = 60.0) -> np.ndarray:
    """Points on vertical walls and poles around a square road, plus a ground plane."""
    parts = []
    for _ in range(60):  # wall segments of random length and orientation off the road
        c = rng.uniform(-extent, extent, 2)
        if np.abs(c).max() < 28 and np.abs(c).min() < 22:
            continue
        a = rng.uniform(0, np.pi)
        length, height = rng.uniform(4, 15), rng.uniform(3, 10)
        s = rng.uniform(-0.5, 0.5, 400)[:, None] * length
        h = rng.uniform(0, height, 400)
        xy = c + s * np.array([np.cos(a), np.sin(a)])
        parts.append(np.column_stack([xy, h - 1.7]))
    for _ in range(80):  # poles
        c = rng.uniform(-extent, extent, 2)
        h = rng.uniform(0, 6, 40)
        parts.append(np.column_stack([np.repeat(c[None], 40, 0), h - 1.7]))
    g = rng.uniform(-extent, extent, (6000, 2))
    parts.append(np.column_stack([g, np.full(len(g), -1.7)]))
    return np.concatenate(parts).astype(np.float32)


def square_loop_poses(n_per_lap: int, laps: int, side: float = 40.0) -> np.ndarray:
    """Drive around a square ``laps`` times; the second lap revisits the first."""
    perim = 4 * side
    poses = []
    for k in range(n_per_lap * laps):
        s = (k % n_per_lap) / n_per_lap * perim
        edge, t = int(s // side), s % side
        start = np.array([[-20, -20], [20, -20], [20, 20], [-20, 20]], float)[edge]
        heading = edge * 90.0
        d = np.array([np.cos(np.radians(heading)), np.sin(np.radians(heading))])
        pose = rotation_z(heading)
        pose[:2, 3] = start + d * t
        poses.append(pose)
    return np.stack(poses)


def write_synthetic_kitti(
    root: Path,
    seed: int = 0,
    n_per_lap: int = 24,
    laps: int = 2,
    shift: np.ndarray | None = None,
) -> Path:
    """A tiny KITTI-layout sequence (no calib.txt: poses are LiDAR-frame) with a revisit;
    ``shift`` (4 × 4, in the vehicle's frame) drives the same world along another line."""
    rng = np.random.default_rng(seed)
    world = make_world(rng)
    poses = square_loop_poses(n_per_lap, laps)
    if shift is not None:
        poses = poses @ shift
    (root / "velodyne").mkdir(parents=True)
    for i, pose in enumerate(poses):
        inv = np.linalg.inv(pose)
        local = world @ inv[:3, :3].T.astype(np.float32) + inv[:3, 3].astype(np.float32)
        local = local[np.linalg.norm(local, axis=1) < 50]
        local = local + rng.normal(0, 0.01, local.shape).astype(np.float32)
        xyzi = np.column_stack([local, rng.uniform(0, 1, len(local))]).astype("<f4")
        xyzi.tofile(root / "velodyne" / f"{i:06d}.bin")
    write_poses(root / "poses.txt", poses)
    return root


@pytest.fixture(scope="session")
def synthetic_seq_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_synthetic_kitti(tmp_path_factory.mktemp("synth") / "loop")


@pytest.fixture(scope="session")
def shifted_seq_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``synthetic_seq_dir``'s world driven again 1.5 m to the left, 0.6 m back and turned
    by 12°: a second drive whose loop closures onto the first are far from the identity."""
    shift = rotation_z(12.0)
    shift[:3, 3] = (-0.6, 1.5, 0.0)
    return write_synthetic_kitti(tmp_path_factory.mktemp("synth") / "lane", shift=shift)


# The tiny towns, then the shared tiny run, are made from the start of a run in one
# background process, so they take the CPU the suite leaves idle (its service tests wait on
# sockets a good part of the time); the first test that needs one waits only for what is left
# of it. Each is made there only when a collected test needs it. With pytest-xdist's workers
# (`make test` runs two) the first worker to need them starts the process (at normal priority:
# it is then the run's critical path) in a folder the run's main process made; every worker
# waits on it, and the main process stops it when the run ends.
TOWN_FIXTURES = {"tiny_seq": "tiny", "tiny_val_seq": "tiny-check"}  # in the order generated
_TOWNS_NEEDED = pytest.StashKey[list[str]]()
_RUN_FOLDER = pytest.StashKey[Path]()
_background: dict[str, Any] = {}


def pytest_configure(config: pytest.Config) -> None:
    if not hasattr(config, "workerinput"):  # the run's main process (with or without workers)
        config.stash[_RUN_FOLDER] = Path(tempfile.mkdtemp(prefix="overlapmamba-tests-"))


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node: Any) -> None:
    """pytest-xdist: each worker is told the main process's folder."""
    node.workerinput["overlapmamba_run_folder"] = str(node.config.stash[_RUN_FOLDER])


def pytest_unconfigure(config: pytest.Config) -> None:
    if (proc := _background.get("proc")) is not None:
        proc.poll()  # reaped if done: the worker that started it would warn at exit otherwise
    if _RUN_FOLDER not in config.stash:
        return
    folder = config.stash[_RUN_FOLDER]
    pid = _background_pid(folder / "background")
    if pid is not None and _running(pid):  # a run that ended before needing them all
        os.killpg(pid, signal.SIGKILL)  # with its generation workers
    if (proc := _background.get("proc")) is not None:
        proc.wait()
    shutil.rmtree(folder, ignore_errors=True)


def _run_folder(config: pytest.Config) -> Path:
    if hasattr(config, "workerinput"):
        return Path(config.workerinput["overlapmamba_run_folder"])
    return config.stash[_RUN_FOLDER]


def pytest_collection_finish(session: pytest.Session) -> None:
    used = {f for item in session.items for f in getattr(item, "fixturenames", ())}
    needed = [t for f, t in TOWN_FIXTURES.items() if f in used]
    if "tiny_run" in used and importlib.util.find_spec("torch") is not None:
        needed.append("--run")
        if "tiny_onnx" in used:
            needed.append("--onnx")
    session.config.stash[_TOWNS_NEEDED] = needed


@pytest.fixture(scope="session", autouse=True)
def _towns_in_background(request: pytest.FixtureRequest, _session_cache) -> None:
    names = request.config.stash.get(_TOWNS_NEEDED, [])
    if not names or importlib.util.find_spec("embreex") is None:
        return
    root = _run_folder(request.config) / "background"
    _background.update(root=root, names=names)
    try:
        root.mkdir()  # one process makes the folder: that one starts the work
    except FileExistsError:
        return
    script = Path(__file__).with_name("background_towns.py")
    with (root / "background.log").open("w") as out:
        proc = subprocess.Popen(
            [sys.executable, str(script), str(root), *names],
            stdout=out,
            stderr=subprocess.STDOUT,
            # (the environment holds this process's cache: range images shared with its tests)
            # nice 10 beside one test process, which leaves a core idle a good part of the
            # time; beside xdist's workers, which keep both busy, it is their critical path
            preexec_fn=lambda: os.nice(0 if hasattr(request.config, "workerinput") else 10),
            start_new_session=True,  # its generation workers go with it
        )
    _background["proc"] = proc
    (root / "pid.tmp").write_text(str(proc.pid))
    (root / "pid.tmp").replace(root / "pid")


def _background_pid(root: Path) -> int | None:
    try:
        return int((root / "pid").read_text())
    except FileNotFoundError:
        return None


def _running(pid: int) -> bool:
    """Whether ``pid`` runs (not gone, not a zombie nobody has reaped yet)."""
    if (proc := _background.get("proc")) is not None and proc.pid == pid:
        return proc.poll() is None
    if not Path("/proc/self").exists():  # no /proc here: ask the kernel whether it exists
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        return True
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] not in ("Z", "X")


def _wait_for_background(name: str) -> Path:
    """The background folder once ``name`` is done in it; fails with its log if it stopped."""
    root = _background["root"]
    while not (root / f"{name}.done").exists():
        pid = _background_pid(root)
        if pid is not None and not _running(pid) and not (root / f"{name}.done").exists():
            tail = (root / "background.log").read_text()[-3000:]
            pytest.fail(f"the background work on {name} stopped:\n{tail}")
        time.sleep(0.5)
    return root


def _generate_preset(tmp_path_factory: pytest.TempPathFactory, name: str) -> Path:
    pytest.importorskip("embreex")
    if name in _background.get("names", ()):
        return _wait_for_background(name) / name
    return generate_preset(tmp_path_factory.mktemp("synth") / name, name)


def generate_preset(out: Path, name: str) -> Path:
    """The preset ``name`` generated into ``out`` (the background process calls it too)."""
    from overlapmamba.synth.generate import generate
    from overlapmamba.synth.presets import PRESETS

    # Its own limit: a stuck or dead worker fails in a minute, with the chunk named (a tiny
    # scan takes < 1 s, a ground-truth chunk a few seconds).
    generate(out, PRESETS[name], workers=2, progress=False, stall_timeout_s=60)
    return out


@pytest.fixture(scope="session")
def tiny_seq(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The ``tiny`` preset (600 HDL-64E scans, loops both ways), generated once per session."""
    return _generate_preset(tmp_path_factory, "tiny")


@pytest.fixture(scope="session")
def tiny_val_seq(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The ``tiny-check`` preset: another small town (350 scans), for validating tiny
    training runs."""
    return _generate_preset(tmp_path_factory, "tiny-check")


# A small OverlapMamba for training tests: the reference backbone, a narrow mixer and head.
SMALL_MODEL = dict(d_model=32, d_state=4, dt_rank=4, conv_last2=48, clusters=6, out_dim=32)
# The tiny run's recipe: 2 epochs of 2 steps, a health record every step, epoch 0 calibrated
# on 2 batches, a 2-step warm-up (so a resumed schedule matters). Tests that resume or repeat
# the run use the same dict.
TINY_TRAIN = dict(
    epochs=2,
    epoch_scans=32,
    batch_size=16,
    recalibrate_batches=2,
    log_every=1,
    warmup_steps=2,
    real="",  # the shared tiny run turns the real-scan check on; copies need not repeat it
)


def small_run(**changes: Any):
    """``TINY_TRAIN`` as a ``TrainConfig``, with ``changes``."""
    from overlapmamba.train.train import TrainConfig

    return TrainConfig(**{**TINY_TRAIN, **changes})


@pytest.fixture(scope="session")
def tiny_run(tiny_seq: Path, tiny_val_seq: Path, tmp_path_factory: pytest.TempPathFactory):
    """A finished run (``TINY_TRAIN``: epoch 0, then 2 epochs of 32 scans in batches of 16)
    of ``SMALL_MODEL`` on the tiny towns, trained once per session: ``(run folder,
    history)``. Tests that read a run share it and never write into it (copy it first)."""
    pytest.importorskip("torch")
    if "--run" in _background.get("names", ()):
        root = _wait_for_background("tiny-run")
        assert (tiny_seq, tiny_val_seq) == (root / "tiny", root / "tiny-check")
        return root / "runs" / "tiny", pickle.loads((root / "tiny-run.pkl").read_bytes())
    out = tmp_path_factory.mktemp("runs") / "tiny"
    return out, train_tiny_run(tiny_seq, tiny_val_seq, out)


@pytest.fixture(scope="session")
def tiny_onnx(tiny_run, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny run's last epoch exported (float32, verified against PyTorch), once per
    session (an export takes a dozen seconds): tests that change the file copy it first."""
    if "--onnx" in _background.get("names", ()):
        return _wait_for_background("tiny-onnx") / "tiny.onnx"
    return export_tiny_run(tiny_run[0], tmp_path_factory.mktemp("onnx") / "tiny.onnx")


def export_tiny_run(run: Path, out: Path) -> Path:
    """``tiny_onnx``'s export of ``run``'s epoch-002.pt (the background process runs it
    too)."""
    from overlapmamba.train.checkpoint import load_model
    from overlapmamba.train.export import export_onnx

    model, profile, _ = load_model(run / "epoch-002.pt")
    return export_onnx(model, profile, out, weight_format="float32").path


def train_tiny_run(tiny_seq: Path, tiny_val_seq: Path, out: Path) -> list[dict]:
    """``tiny_run``'s training (the background process runs it too): its history."""
    from overlapmamba.train.model import OverlapMambaConfig
    from overlapmamba.train.train import train
    from overlapmamba.train.train_config import REAL_SCANS

    cfg = small_run(real=REAL_SCANS)
    model = OverlapMambaConfig(**SMALL_MODEL)
    return train([tiny_seq], tiny_val_seq, out, model, cfg, progress=False)


def save_random_checkpoint(path: Path, **config) -> Path:
    """A checkpoint of an untrained OverlapMamba (seed 0) with the given config overrides."""
    import torch

    from overlapmamba.core.sensors import get_profile
    from overlapmamba.train.checkpoint import save_checkpoint
    from overlapmamba.train.model import OverlapMamba, OverlapMambaConfig

    torch.manual_seed(0)
    cfg = OverlapMambaConfig(**config)
    payload = {
        "model_config": cfg.to_dict(),
        "profile": get_profile(cfg.sensor).model_dump(),
        "state_dict": OverlapMamba(cfg).state_dict(),
    }
    save_checkpoint(path, payload)
    return path


@pytest.fixture
def anyio_backend() -> str:
    """The async tests (``pytest.mark.anyio``) run on asyncio."""
    return "asyncio"


@pytest.fixture(scope="module")
def encoder():
    """The shipped encoder as the service loads it (2 onnxruntime threads), once a module."""
    from service_kit import MODEL

    from overlapmamba.service.encoder import Encoder

    return Encoder(MODEL, intra_op_threads=2)
