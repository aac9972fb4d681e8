"""The selective scan's C kernel (``csrc/selective_scan.c``): build, load, and a numpy forward.

Training reaches it through :mod:`overlapmamba.train.scan_fused` (autograd, torch tensors); the
service's fast path (:mod:`overlapmamba.service.fastscan`) calls :func:`scan_forward` on the arrays
of the exported graph's scan nodes. Both load the same library, so the scan a model was trained with
is the scan it is served with.

**Build.** Compiled with the system C compiler (``cc`` or ``$CC``) into
``$OVERLAPMAMBA_CACHE/kernels`` (default ``~/.cache/overlapmamba``), keyed by the source and
the flags, and, for ``-march=native`` (the default), by the processor, so a changed source or
another machine never loads a stale build. ``OVERLAPMAMBA_KERNEL_MARCH`` names another target
(the Docker image builds for ``x86-64-v2``, which every x86-64 server of the last decade runs).
``make serve`` and the Docker builder stage build it at install (``python -m
overlapmamba.core.scan_kernel``), so no request ever waits for a compiler, and a built library loads
without one; where none is built and no compiler exists, :func:`load` raises
:class:`KernelBuildError` with the reason and callers fall back.

Why these flags: ``-ffast-math`` lets gcc vectorise ``expf`` through glibc's libmvec (the
scan's cost is one exponential per state element per step). It is passed when compiling
only: linking with it would pull in ``crtfastmath.o``, which switches the *whole process*
to flush-subnormals-to-zero at load time. The kernel flushes subnormals itself instead, on
the calling thread for the length of each float call (``csrc/selective_scan.c``, FLUSH_BEGIN:
on some x86 processors a ring's fast-decaying lanes made it nine to ten times slower:
``benchmarks/scan_subnormals.py``).
"""

from __future__ import annotations

import ctypes
import hashlib
import itertools
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor, wait
from pathlib import Path

import numpy as np

from overlapmamba.core.cache import cache_root

SOURCE = Path(__file__).with_name("csrc") / "selective_scan.c"


def cflags() -> list[str]:
    march = os.environ.get("OVERLAPMAMBA_KERNEL_MARCH", "native")
    machine = platform.machine().lower()
    if march.startswith("x86-64") and machine not in ("x86_64", "amd64"):
        # an x86 target named for an image built on another processor (arm64): the compiler
        # would refuse it, and the build with it; that processor's baseline instead
        march = "armv8-a" if machine in ("aarch64", "arm64") else "native"
    return ["-O3", "-ffast-math", f"-march={march}", "-fPIC", "-std=c11"]


_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_error: str | None = None
_pools: dict[int, ThreadPoolExecutor] = {}


class KernelBuildError(RuntimeError):
    """The C kernel could not be compiled or loaded; the message says why."""


def _cpuinfo() -> dict[str, str]:
    """The first processor's fields of /proc/cpuinfo (empty where there is none)."""
    fields: dict[str, str] = {}
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = (part.strip() for part in line.partition(":"))
            fields.setdefault(key, value)
    except OSError:
        pass
    return fields


def _cpu_tag() -> str:
    try:
        info = Path("/proc/cpuinfo").read_text()
        flags = next((ln for ln in info.splitlines() if ln.startswith("flags")), "")
    except OSError:
        flags = ""
    return f"{platform.machine()}:{flags}"


def processor() -> dict[str, object]:
    """The processor the kernel runs on, as reports record it: its name, and the vendor,
    family and model numbers a cloud machine's generic name ("Intel Xeon Processor") leaves
    out, and whether it has AVX-512. The kernel's cost depends on them (subnormals: see
    ``csrc/selective_scan.c``)."""
    info = _cpuinfo()
    out: dict[str, object] = {"name": info.get("model name") or platform.machine()}
    for key in ("vendor_id", "cpu family", "model"):
        if key in info:
            out[key] = info[key]
    if "flags" in info:
        out["avx512f"] = "avx512f" in info["flags"].split()
    return out


def _compiler() -> str | None:
    return os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")


def library_path() -> Path:
    flags = cflags()
    cpu = _cpu_tag() if "-march=native" in flags else ""
    key = hashlib.sha256(SOURCE.read_bytes() + " ".join(flags).encode() + cpu.encode())
    return cache_root() / "kernels" / f"selective_scan-{key.hexdigest()[:16]}.so"


def _build(compiler: str, target: Path) -> None:
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
        objs = []
        for name, defines in (("f", []), ("d", ["-DSCAN_DOUBLE"])):
            obj = Path(tmp) / f"scan_{name}.o"
            cmd = [compiler, *cflags(), *defines, "-c", str(SOURCE), "-o", str(obj)]
            subprocess.run(cmd, check=True, capture_output=True, text=True)
            objs.append(str(obj))
        lib = Path(tmp) / "scan.so"
        # No -ffast-math here: see the module docstring (crtfastmath.o).
        subprocess.run(
            [compiler, "-shared", *objs, "-o", str(lib), "-lmvec", "-lm"],
            check=True,
            capture_output=True,
            text=True,
        )
        os.replace(lib, target)  # atomic: concurrent builders never load a half-written file


def load() -> ctypes.CDLL:
    """The compiled kernel library, building it on first use; raises KernelBuildError."""
    global _lib, _error
    with _lock:
        if _lib is not None:
            return _lib
        if _error is not None:
            raise KernelBuildError(_error)
        path = library_path()
        try:
            if not path.is_file():
                compiler = _compiler()
                if compiler is None:
                    raise KernelBuildError(
                        f"no C compiler found (set $CC or install gcc) and no built kernel at "
                        f"{path}"
                    )
                _build(compiler, path)
            lib = ctypes.CDLL(str(path))
        except subprocess.CalledProcessError as err:
            _error = f"compiling {SOURCE.name} failed: {err.stderr.strip()[-2000:]}"
            raise KernelBuildError(_error) from None
        except (OSError, KernelBuildError) as err:
            _error = str(err)
            raise KernelBuildError(_error) from None
        # the C signatures, so that ctypes refuses a wrong argument instead of passing it on
        ptr, i32 = ctypes.c_void_p, ctypes.c_int
        for suffix in ("f", "d"):
            fwd, bwd = getattr(lib, f"scan_fwd_{suffix}"), getattr(lib, f"scan_bwd_{suffix}")
            fwd.restype = bwd.restype = None
            fwd.argtypes = [ptr] * 7 + [i32] * 7  # u Δ A B C D y; B E L N circular b0 b1
            bwd.argtypes = [ptr] * 12 + [i32] * 7  # … dy du dΔ dA dB dC; the same ints
        lib.scan_fwd_tokens_f.restype = None
        # u Δ Aᵀ B C D y; M L E N circular; units [k0, k1)
        lib.scan_fwd_tokens_f.argtypes = [ptr] * 7 + [i32] * 5 + [ctypes.c_long] * 2
        lib.scan_tokens_lanes.restype = ctypes.c_int
        lib.scan_tokens_lanes.argtypes = []
        # subnormals flushed in float calls (1, the default); returns the setting replaced
        lib.scan_set_flush.restype = ctypes.c_int
        lib.scan_set_flush.argtypes = [ctypes.c_int]
        lib.scan_flush_supported.restype = ctypes.c_int  # 0: not on this processor (not x86)
        lib.scan_flush_supported.argtypes = []
        _lib = lib
        return lib


def available() -> bool:
    try:
        load()
    except KernelBuildError:
        return False
    return True


def run_split(fn: Callable[..., object], rows: int, threads: int, *args: object) -> None:
    """Call fn(*args, r0, r1) over [0, rows), split evenly across ``threads`` threads: the
    first part on the calling thread, the others on a pool (ctypes releases the GIL during
    each call), so the caller works instead of waiting."""
    threads = max(1, min(threads, rows))
    if threads == 1:
        fn(*args, 0, rows)
        return
    with _lock:
        pool = _pools.get(threads - 1)
        if pool is None:
            pool = _pools[threads - 1] = ThreadPoolExecutor(threads - 1, thread_name_prefix="scan")
    bounds = [round(rows * i / threads) for i in range(threads + 1)]
    parts = [(lo, hi) for lo, hi in itertools.pairwise(bounds) if hi > lo]
    jobs: list[Future[object]] = []
    try:
        for lo, hi in parts[1:]:
            jobs.append(pool.submit(fn, *args, lo, hi))
        fn(*args, *parts[0])
    finally:
        _settle(jobs)


def _settle(jobs: list[Future[object]]) -> None:
    """Wait until every job has ended, then raise the first one's error, if any. The jobs
    write into buffers that only the caller's frame keeps alive, so nothing may leave before
    they end: not another job's error, not an interrupt (Ctrl-C) arriving while waiting."""
    interrupted: BaseException | None = None
    while True:
        try:
            wait(jobs)
            break
        except BaseException as err:  # re-raised below, once the jobs have ended
            interrupted = interrupted or err
    if interrupted is not None:
        raise interrupted
    for j in jobs:
        j.result()


def _ptr(a: np.ndarray) -> ctypes.c_void_p:
    return ctypes.c_void_p(a.ctypes.data)


def scan_forward(
    u: np.ndarray,
    delta: np.ndarray,
    A: np.ndarray,
    Bm: np.ndarray,
    Cm: np.ndarray,
    D: np.ndarray,
    circular: bool,
    threads: int = 1,
) -> np.ndarray:
    """The scan on float32 arrays in the exported node's token-major layout:
    u, delta (M, L, E); A (E, N); B, C (M, L, N); D (E,) → y (M, L, E).

    The kernel (``scan_fwd_tokens_f``) reads this layout as it is, a block of 8 (AVX) or 4
    channels per vector; E is padded to a multiple of 8 where it is not one. The M · E/lanes
    (row, block) units are split across ``threads`` threads."""
    if u.ndim != 3 or A.ndim != 2:
        raise ValueError(f"u must be (M, L, E) and A (E, N); got u {u.shape}, A {A.shape}")
    M, L, E = u.shape
    N = A.shape[1]
    if delta.shape != u.shape or Bm.shape != (M, L, N) or Cm.shape != (M, L, N):
        raise ValueError(
            f"scan shapes disagree: u {u.shape}, delta {delta.shape}, A {A.shape}, "
            f"B {Bm.shape}, C {Cm.shape}; want (M, L, E), (M, L, E), (E, N), (M, L, N) ×2"
        )
    if A.shape != (E, N) or D.shape != (E,):
        raise ValueError(f"A {A.shape} and D {D.shape} must be ({E}, N) and ({E},)")
    lib = load()
    lanes = 8  # the kernel's blocks are 8 or 4 channels; pad E to a multiple of 8
    pad = -E % lanes
    f32 = np.float32

    def prep(x: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(x, dtype=f32)
        return np.pad(x, [(0, 0)] * (x.ndim - 1) + [(0, pad)]) if pad else x

    uc, dc, Dc = prep(u), prep(delta), prep(D)
    At = prep(np.ascontiguousarray(A.T))  # (N, E): a state's channels side by side
    if pad:  # padded channels read u = 0 and Δ = 0, so they stay 0; A = −(n + 1) there keeps
        # their block on the kernel's powers path (see selective_scan.c)
        At[:, E:] = -np.arange(1, N + 1, dtype=f32)[:, None]
    Bc, Cc = (np.ascontiguousarray(x, dtype=f32) for x in (Bm, Cm))
    y = np.empty_like(uc)
    ptrs = [_ptr(x) for x in (uc, dc, At, Bc, Cc, Dc, y)]
    units = M * (E + pad) // lib.scan_tokens_lanes()
    dims = [ctypes.c_int(v) for v in (M, L, E + pad, N, int(circular))]
    fn = lib.scan_fwd_tokens_f
    run_split(lambda k0, k1: fn(*ptrs, *dims, ctypes.c_long(k0), ctypes.c_long(k1)), units, threads)
    return np.ascontiguousarray(y[..., :E]) if pad else y


def main() -> int:
    """``python -m overlapmamba.core.scan_kernel``: build (or find) the kernel; say where, or
    why not."""
    try:
        load()
    except KernelBuildError as err:
        print(f"selective-scan kernel not built: {err}", file=sys.stderr)
        return 1
    print(f"selective-scan kernel: {library_path()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
