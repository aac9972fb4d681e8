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
    if u.device.type != "cpu":
        raise ValueError(f"the fused scan runs on CPU tensors, not {u.device}")
    # The kernel walks channel-major rows of u and Δ and reads B and C per step, token-major
    # as given: (B, L, N) keeps each step's N values together.
    y: Tensor = _FusedScan.apply(u.transpose(1, 2), delta.transpose(1, 2), A, Bm, Cm, D, circular)
    return y.transpose(1, 2)
