"""Selective scan: the fast chunked path against the plain loop (house style §5)."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from model_export.scan import selective_scan, selective_scan_ref  # noqa: E402


def inputs(B: int, E: int, L: int, N: int, seed: int = 0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    u = torch.randn(B, E, L, generator=g, dtype=dtype)
    # Mamba's initialisation: Δ in [0.001, 0.1], A = −(1 … N).
    delta = torch.exp(torch.empty(B, E, L, dtype=dtype).uniform_(-6.9, -2.3, generator=g))
    A = -torch.arange(1, N + 1, dtype=dtype).repeat(E, 1)
    Bm = torch.randn(B, N, L, generator=g, dtype=dtype)
    Cm = torch.randn(B, N, L, generator=g, dtype=dtype)
    D = torch.randn(E, generator=g, dtype=dtype)
    return u, delta, A, Bm, Cm, D


@pytest.mark.parametrize("L", [1, 7, 32, 45, 128])
@pytest.mark.parametrize("circular", [False, True])
def test_fast_matches_reference_forward_and_gradients(L, circular):
    args = [x.requires_grad_() for x in inputs(2, 5, L, 4, seed=L)]
    ref = selective_scan_ref(*args, circular=circular)
    g_ref = torch.autograd.grad(ref.square().sum(), args)
    fast = selective_scan(*args, circular=circular)
    g_fast = torch.autograd.grad(fast.square().sum(), args)
    torch.testing.assert_close(fast, ref, rtol=1e-5, atol=1e-8)
    for a, b in zip(g_fast, g_ref, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-8)


@pytest.mark.parametrize("chunk", [1, 4, 16, 64])
def test_any_chunk_length_gives_the_same_result(chunk):
    args = inputs(1, 3, 50, 4, seed=1)
    torch.testing.assert_close(
        selective_scan(*args, circular=True, chunk=chunk),
        selective_scan_ref(*args, circular=True),
        rtol=1e-5,
        atol=1e-8,
    )


@pytest.mark.parametrize("fn", [selective_scan_ref, selective_scan])
def test_circular_scan_is_equivariant_to_rolls(fn):
    u, delta, A, Bm, Cm, D = inputs(2, 4, 60, 8, seed=3, dtype=torch.float32)
    y = fn(u, delta, A, Bm, Cm, D, circular=True)
    for k in (1, 17, 59):
        rolled = [torch.roll(x, k, dims=-1) for x in (u, delta, Bm, Cm)]
        y_k = fn(rolled[0], rolled[1], A, rolled[2], rolled[3], D, circular=True)
        torch.testing.assert_close(y_k, torch.roll(y, k, dims=-1), rtol=1e-4, atol=1e-5)
    # Without the ring start, the first columns see a different history: not equivariant.
    y_open = fn(u, delta, A, Bm, Cm, D, circular=False)
    rolled = [torch.roll(x, 17, dims=-1) for x in (u, delta, Bm, Cm)]
    y_open_k = fn(rolled[0], rolled[1], A, rolled[2], rolled[3], D, circular=False)
    assert (y_open_k - torch.roll(y_open, 17, dims=-1)).abs().max() > 1e-3


def test_ring_with_almost_no_decay_stays_finite():
    u, delta, A, Bm, Cm, D = inputs(1, 2, 30, 3, seed=4)
    y = selective_scan(u, delta * 1e-9, A, Bm, Cm, D, circular=True)
    assert torch.isfinite(y).all()
