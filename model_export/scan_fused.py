"""The selective scan as a fused CPU kernel (C, ``csrc/selective_scan.c``), with autograd.

Same signature and result as :func:`model_export.scan.selective_scan_ref`; the shape legend is
in :mod:`model_export.scan`. One compiled loop per (batch, channel) row keeps the N-wide
state in registers, and the backward recomputes the states of a row into a private L × N
buffer instead of saving (B, E, L, N) tensors. A batch is split across
``torch.get_num_threads()`` threads (ctypes releases the GIL during the call).

The kernel is compiled on first use with the system C compiler (``cc`` or ``$CC``) into
``$OVERLAPMAMBA_CACHE/kernels`` (default ``~/.cache/overlapmamba``), keyed by the source,
the flags and the processor, so a changed source or another machine never loads a stale
build. Without a compiler :func:`available` is False and :func:`model_export.scan.scan`
falls back to the chunked PyTorch path.

Why these flags: ``-ffast-math`` lets gcc vectorise ``expf`` through glibc's libmvec (the
scan's cost is one exponential per state element per step). It is passed when compiling
only: linking with it would pull in ``crtfastmath.o``, which switches the *whole process*
to flush-subnormals-to-zero at load time.
"""

from __future__ import annotations

import ctypes
import hashlib
import itertools
import os
import platform
import shutil
import subprocess
import tempfile
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import torch
from torch import Tensor

from lidar_core.cache import cache_root

SOURCE = Path(__file__).with_name("csrc") / "selective_scan.c"
CFLAGS = ["-O3", "-ffast-math", "-march=native", "-fPIC", "-std=c11"]

_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_error: str | None = None
_pool: ThreadPoolExecutor | None = None


class KernelBuildError(RuntimeError):
    """The C kernel could not be compiled or loaded; the message says why."""


def _cpu_tag() -> str:
    try:
        info = Path("/proc/cpuinfo").read_text()
        flags = next((ln for ln in info.splitlines() if ln.startswith("flags")), "")
    except OSError:
        flags = ""
    return f"{platform.machine()}:{flags}"


def _library_path(compiler: str) -> Path:
    base = cache_root()
    key = hashlib.sha256(
        SOURCE.read_bytes() + " ".join([compiler, *CFLAGS]).encode() + _cpu_tag().encode()
    ).hexdigest()[:16]
    return base / "kernels" / f"selective_scan-{key}.so"


def _build(compiler: str, target: Path) -> None:
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
        objs = []
        for name, defines in (("f", []), ("d", ["-DSCAN_DOUBLE"])):
            obj = Path(tmp) / f"scan_{name}.o"
            cmd = [compiler, *CFLAGS, *defines, "-c", str(SOURCE), "-o", str(obj)]
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
        compiler = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
        try:
            if compiler is None:
                raise KernelBuildError("no C compiler found (set $CC or install gcc)")
            path = _library_path(compiler)
            if not path.is_file():
                _build(compiler, path)
            lib = ctypes.CDLL(str(path))
        except subprocess.CalledProcessError as err:
            _error = f"compiling {SOURCE.name} failed: {err.stderr.strip()[-2000:]}"
            raise KernelBuildError(_error) from None
        except (OSError, KernelBuildError) as err:
            _error = str(err)
            raise KernelBuildError(_error) from None
        for suffix in ("f", "d"):
            getattr(lib, f"scan_fwd_{suffix}").restype = None
            getattr(lib, f"scan_bwd_{suffix}").restype = None
        _lib = lib
        return lib


def available() -> bool:
    try:
        load()
    except KernelBuildError:
        return False
    return True


def _ptr(t: Tensor) -> ctypes.c_void_p:
    return ctypes.c_void_p(t.data_ptr())


def _run_split(fn, B: int, *args) -> None:
    """Call fn(*args, b0, b1) over the batch, split across torch's thread count."""
    global _pool
    threads = max(1, min(torch.get_num_threads(), B))
    if threads == 1:
        fn(*args, 0, B)
        return
    if _pool is None or _pool._max_workers < threads:
        _pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="scan")
    bounds = [round(B * i / threads) for i in range(threads + 1)]
    jobs = [_pool.submit(fn, *args, lo, hi) for lo, hi in itertools.pairwise(bounds) if hi > lo]
    for j in jobs:
        j.result()


def _suffix(dtype: torch.dtype) -> str:
    if dtype == torch.float32:
        return "f"
    if dtype == torch.float64:
        return "d"
    raise TypeError(f"the fused scan takes float32 or float64 tensors, not {dtype}")


class _FusedScan(torch.autograd.Function):
    @staticmethod
    def forward(ctx, u, delta, A, Bt, Ct, D, circular):  # type: ignore[override]
        # u, delta: (B, E, L); A: (E, N); Bt, Ct: (B, L, N); D: (E,)
        lib = load()
        u, delta, A, Bt, Ct, D = (x.contiguous() for x in (u, delta, A, Bt, Ct, D))
        Bsz, E, L = u.shape
        N = A.shape[1]
        y = torch.empty_like(u)
        fwd = getattr(lib, f"scan_fwd_{_suffix(u.dtype)}")
        ptrs = [_ptr(x) for x in (u, delta, A, Bt, Ct, D, y)]
        _run_split(fwd, Bsz, *ptrs, Bsz, E, L, N, int(circular))
        ctx.save_for_backward(u, delta, A, Bt, Ct, D)
        ctx.circular = circular
        return y

    @staticmethod
    def backward(ctx, dy):  # type: ignore[override]
        u, delta, A, Bt, Ct, D = ctx.saved_tensors
        dy = dy.contiguous()
        Bsz, E, L = u.shape
        N = A.shape[1]
        du, ddelta = torch.empty_like(u), torch.empty_like(u)
        dA = u.new_empty(Bsz, E, N)  # per-batch partial sums
        dB, dC = torch.empty_like(Bt), torch.empty_like(Ct)
        bwd = getattr(load(), f"scan_bwd_{_suffix(u.dtype)}")
        ptrs = [_ptr(x) for x in (u, delta, A, Bt, Ct, D, dy, du, ddelta, dA, dB, dC)]
        _run_split(bwd, Bsz, *ptrs, Bsz, E, L, N, int(ctx.circular))
        dD = (dy * u).sum((0, 2))
        return du, ddelta, dA.sum(0), dB, dC, dD, None


def selective_scan_fused(
    u: Tensor, delta: Tensor, A: Tensor, Bm: Tensor, Cm: Tensor, D: Tensor, circular: bool = False
) -> Tensor:
    """Same result as :func:`model_export.scan.selective_scan_ref`; CPU, float32/float64."""
    if u.device.type != "cpu":
        raise ValueError(f"the fused scan runs on CPU tensors, not {u.device}")
    # The kernel walks channel-major rows of u and Δ and reads B and C per step, token-major
    # as given: (B, L, N) keeps each step's N values together.
    y: Tensor = _FusedScan.apply(u.transpose(1, 2), delta.transpose(1, 2), A, Bm, Cm, D, circular)
    return y.transpose(1, 2)
