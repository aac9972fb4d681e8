"""The selective scan as a fused CPU kernel (C, ``overlapmamba/core/csrc/selective_scan.c``), with
autograd.

Same signature and result as :func:`overlapmamba.train.scan.selective_scan_ref`; the shape legend is
in :mod:`overlapmamba.train.scan`. One compiled loop per (batch, channel) row keeps the N-wide
state in registers, and the backward recomputes the states of a row into a private L × N
buffer instead of saving (B, E, L, N) tensors. A batch is split across
``torch.get_num_threads()`` threads (ctypes releases the GIL during the call).

Building and loading the library is :mod:`overlapmamba.core.scan_kernel`'s (the service runs the
same kernel); without a compiler :func:`available` is False and
:func:`overlapmamba.train.scan.scan` falls back to the chunked PyTorch path.
"""

from __future__ import annotations

import ctypes

import torch
from torch import Tensor

from overlapmamba.core.scan_kernel import KernelBuildError, available, load, run_split

__all__ = ["KernelBuildError", "available", "load", "selective_scan_fused"]


def _ptr(t: Tensor) -> ctypes.c_void_p:
    return ctypes.c_void_p(t.data_ptr())


def _run_split(fn, B: int, *args) -> None:
    """Call fn(*args, b0, b1) over the batch, split across torch's thread count."""
    run_split(fn, B, torch.get_num_threads(), *args)


def _suffix(dtype: torch.dtype) -> str:
    if dtype == torch.float32:
        return "f"
    if dtype == torch.float64:
        return "d"
    raise TypeError(f"the fused scan takes float32 or float64 tensors, not {dtype}")


class _FusedScan(torch.autograd.Function):
    @staticmethod
    def forward(ctx, u, delta, A, Bt, Ct, D, circular):
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
    def backward(ctx, dy):
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
    """Same result as :func:`overlapmamba.train.scan.selective_scan_ref`; CPU, float32/float64."""
    _check(u, delta, A, Bm, Cm, D)
    # The kernel walks channel-major rows of u and Δ and reads B and C per step, token-major
    # as given: (B, L, N) keeps each step's N values together.
    y: Tensor = _FusedScan.apply(u.transpose(1, 2), delta.transpose(1, 2), A, Bm, Cm, D, circular)
    return y.transpose(1, 2)


def _check(u: Tensor, delta: Tensor, A: Tensor, Bm: Tensor, Cm: Tensor, D: Tensor) -> None:
    """The kernel reads raw memory as u's type and the legend's shapes: any other tensor, or
    one elsewhere than the CPU, is refused here rather than read out of bounds."""
    named = {"u": u, "delta": delta, "A": A, "B": Bm, "C": Cm, "D": D}
    if off := [f"{k} on {t.device}" for k, t in named.items() if t.device.type != "cpu"]:
        raise ValueError(f"the fused scan runs on CPU tensors; got {', '.join(off)}")
    _suffix(u.dtype)
    if off := [f"{k} {t.dtype}" for k, t in named.items() if t.dtype != u.dtype]:
        raise TypeError(f"the fused scan takes one dtype, u's {u.dtype}; got {', '.join(off)}")
    if u.dim() != 3 or A.dim() != 2:
        raise ValueError(
            f"u must be (B, L, E) and A (E, N); got u {tuple(u.shape)}, A {tuple(A.shape)}"
        )
    (Bsz, L, E), N = u.shape, A.shape[1]
    want = {"delta": (Bsz, L, E), "A": (E, N), "B": (Bsz, L, N), "C": (Bsz, L, N), "D": (E,)}
    if off := [f"{k} {tuple(named[k].shape)}" for k, s in want.items() if named[k].shape != s]:
        raise ValueError(
            f"scan shapes disagree with u {tuple(u.shape)} and A {tuple(A.shape)}: "
            f"{', '.join(off)}; want delta (B, L, E), A (E, N), B and C (B, L, N), D (E,)"
        )
