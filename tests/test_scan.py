"""Selective scan: the chunked path and the fused C kernel against the plain loop (house
style §5), forward and gradients, open and circular."""

from __future__ import annotations

import pytest
from conftest import PROC_STATM, resident_bytes

torch = pytest.importorskip("torch")

from overlapmamba.train import scan_fused  # noqa: E402
from overlapmamba.train.scan import (  # noqa: E402
    selective_scan,
    selective_scan_loop,
    selective_scan_ref,
)
from overlapmamba.train.scan_backends import scan  # noqa: E402


def inputs(B: int, E: int, L: int, N: int, seed: int = 0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    u = torch.randn(B, L, E, generator=g, dtype=dtype)  # token-major, as the model feeds it
    # Mamba's initialisation: Δ in [0.001, 0.1], A = −(1 … N).
    delta = torch.exp(torch.empty(B, L, E, dtype=dtype).uniform_(-6.9, -2.3, generator=g))
    A = -torch.arange(1, N + 1, dtype=dtype).repeat(E, 1)
    Bm = torch.randn(B, L, N, generator=g, dtype=dtype)
    Cm = torch.randn(B, L, N, generator=g, dtype=dtype)
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


@pytest.mark.parametrize("L", [1, 7, 30, 45, 128])
@pytest.mark.parametrize("circular", [False, True])
@pytest.mark.parametrize("chunk", [None, 1, 4, 64])
def test_loop_form_matches_reference(L, circular, chunk):
    # The form the ONNX export uses: chunks side by side, three loops (padding when T ∤ L).
    args = inputs(3, 5, L, 4, seed=L)
    torch.testing.assert_close(
        selective_scan_loop(*args, circular=circular, chunk=chunk),
        selective_scan_ref(*args, circular=circular),
        rtol=1e-6,
        atol=1e-9,
    )


@pytest.mark.parametrize("fn", [selective_scan_ref, selective_scan, selective_scan_loop])
def test_circular_scan_is_equivariant_to_rolls(fn):
    u, delta, A, Bm, Cm, D = inputs(2, 4, 60, 8, seed=3, dtype=torch.float32)
    y = fn(u, delta, A, Bm, Cm, D, circular=True)
    for k in (1, 17, 59):
        rolled = [torch.roll(x, k, dims=1) for x in (u, delta, Bm, Cm)]
        y_k = fn(rolled[0], rolled[1], A, rolled[2], rolled[3], D, circular=True)
        torch.testing.assert_close(y_k, torch.roll(y, k, dims=1), rtol=1e-4, atol=1e-5)
    # Without the ring start, the first columns see a different history: not equivariant.
    y_open = fn(u, delta, A, Bm, Cm, D, circular=False)
    rolled = [torch.roll(x, 17, dims=1) for x in (u, delta, Bm, Cm)]
    y_open_k = fn(rolled[0], rolled[1], A, rolled[2], rolled[3], D, circular=False)
    assert (y_open_k - torch.roll(y_open, 17, dims=1)).abs().max() > 1e-3


def test_ring_with_almost_no_decay_stays_finite():
    u, delta, A, Bm, Cm, D = inputs(1, 2, 30, 3, seed=4)
    y = selective_scan(u, delta * 1e-9, A, Bm, Cm, D, circular=True)
    assert torch.isfinite(y).all()


def test_the_fused_kernel_builds_here():
    # CI machines have gcc: a silent fallback to the slow path would hide a broken build.
    scan_fused.load()
    assert scan_fused.available()


@pytest.mark.parametrize("L", [1, 2, 7, 45, 128])
@pytest.mark.parametrize("circular", [False, True])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_fused_matches_reference_forward_and_gradients(L, circular, dtype):
    args = [x.requires_grad_() for x in inputs(3, 5, L, 4, seed=L, dtype=dtype)]
    ref = selective_scan_ref(*args, circular=circular)
    g_ref = torch.autograd.grad(ref.square().sum(), args)
    fused = scan(*args, circular=circular, backend="fused")
    g_fused = torch.autograd.grad(fused.square().sum(), args)
    tol = {"rtol": 1e-5, "atol": 1e-8} if dtype == torch.float64 else {"rtol": 1e-5, "atol": 1e-5}
    torch.testing.assert_close(fused, ref, **tol)
    for a, b in zip(g_fused, g_ref, strict=True):
        scale = b.abs().max().clamp_min(1.0)
        torch.testing.assert_close(a / scale, b / scale, **tol)


@pytest.mark.parametrize("circular", [False, True])
def test_fused_backward_passes_gradcheck(circular):
    args = [x.requires_grad_() for x in inputs(2, 3, 11, 3, seed=5)]
    assert torch.autograd.gradcheck(lambda *a: scan(*a, circular=circular, backend="fused"), args)


def test_fused_gradient_where_the_ring_clamp_holds():
    # Δ ≈ 0: 1 − P is clamped, so the start state no longer depends on P.
    u, delta, A, Bm, Cm, D = inputs(1, 2, 9, 3, seed=6)
    args = [x.requires_grad_() for x in (u, delta * 1e-9, A, Bm, Cm, D)]
    ref = selective_scan_ref(*args, circular=True)
    fused = scan(*args, circular=True, backend="fused")
    torch.testing.assert_close(fused, ref, rtol=1e-6, atol=1e-6)
    for a, b in zip(
        torch.autograd.grad(fused.sum(), args), torch.autograd.grad(ref.sum(), args), strict=True
    ):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-3 * float(b.abs().max()) + 1e-9)


def test_fused_kernel_split_across_threads_gives_the_same_result():
    args = inputs(5, 4, 33, 4, seed=7, dtype=torch.float32)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = scan(*args, circular=True, backend="fused")
        torch.set_num_threads(2)
        two = scan(*args, circular=True, backend="fused")
    finally:
        torch.set_num_threads(before)
    torch.testing.assert_close(one, two, rtol=0, atol=0)


def test_loading_the_kernel_keeps_subnormal_floats():
    # Linking with -ffast-math would switch the process to flush-to-zero (crtfastmath.o).
    scan_fused.load()
    tiny = torch.tensor([1e-40], dtype=torch.float32)
    assert float(tiny) != 0.0 and float(tiny * 1.0) != 0.0


def test_scan_rejects_unknown_backends_and_dtypes():
    args = inputs(1, 2, 5, 3)
    with pytest.raises(ValueError, match="allowed: auto, fused, chunked, loop, onnx, ref"):
        scan(*args, backend="cuda")
    with pytest.raises(TypeError, match="float32 or float64"):
        scan(*(x.half() for x in args), backend="fused")


@pytest.mark.parametrize("circular", [False, True])
@pytest.mark.parametrize("threads", [1, 2, 3])
def test_numpy_forward_of_the_served_kernel_matches_the_reference(circular, threads):
    """overlapmamba.core.scan_kernel.scan_forward (the service's fast path: token-major float32
    arrays, rows split across threads, uneven splits included) against the plain loop."""
    from overlapmamba.core.scan_kernel import scan_forward

    args = inputs(3, 7, 45, 4, seed=threads, dtype=torch.float32)
    ref = selective_scan_ref(*args, circular=circular).numpy()
    y = scan_forward(*(x.numpy() for x in args), circular=circular, threads=threads)
    assert y.shape == ref.shape and y.dtype == ref.dtype and y.flags.c_contiguous
    torch.testing.assert_close(torch.from_numpy(y), torch.from_numpy(ref), rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="scan shapes disagree"):
        scan_forward(
            *(x.numpy() for x in args[:3]),
            args[3].numpy()[:, :5],
            args[4].numpy(),
            args[5].numpy(),
            circular,
        )


def _served_inputs(kind: str, L: int = 240, E: int = 16, N: int = 16):
    """Inputs for each path of the served kernel: ``powers`` (A near Mamba's initialisation
    −(n + 1): one exponential per step), ``exps`` (A anywhere: one per state and step),
    ``slow`` (Δ so small that the ring's start state is carried around the whole ring)."""
    g = torch.Generator().manual_seed(7)
    u, delta, A, Bm, Cm, D = inputs(2, E, L, N, seed=11, dtype=torch.float64)
    if kind == "powers":
        A = A + 0.2 * torch.rand(A.shape, generator=g, dtype=A.dtype) - 0.1
    elif kind == "exps":
        A = -torch.exp(torch.randn(A.shape, generator=g, dtype=A.dtype))
        delta = delta * 5
    elif kind == "slow":
        delta = torch.full_like(delta, 1e-4)
    return u, delta, A, Bm, Cm, D


@pytest.mark.parametrize("kind", ["powers", "exps", "slow"])
@pytest.mark.parametrize("circular", [False, True])
def test_each_path_of_the_served_kernel_matches_float64(kind, circular):
    """The served kernel's own exponential (a polynomial, or powers of exp(−Δ) times a
    quartic) and the ring's start added as a decaying correction, against the plain loop in
    float64: within float32 rounding of the result."""
    from overlapmamba.core.scan_kernel import scan_forward

    args = _served_inputs(kind)
    ref = selective_scan_ref(*args, circular=circular).numpy()
    y = scan_forward(*(x.float().numpy() for x in args), circular=circular, threads=2)
    scale = float(abs(ref).max())
    assert float(abs(y - ref).max()) <= 2e-6 * scale, (kind, float(abs(y - ref).max()), scale)


@pytest.mark.parametrize("threads", [1, 2])
def test_a_ring_with_fast_and_slow_lanes_is_exact_and_leaves_the_callers_floats_alone(threads):
    """A block of channels whose lanes decay slowly (carried around the whole ring) beside
    lanes that decay fast, whose decayed start state then falls below float32's smallest
    normal: the kernel flushes those subnormals to zero for its call (on some processors
    each multiply with one costs a hundred cycles: benchmarks/scan_subnormals.py), gives the
    float64 loop's numbers as before, and puts the calling threads' float mode back."""
    import numpy as np

    from overlapmamba.core.scan_kernel import _pools, load, scan_forward

    u, delta, A, Bm, Cm, D = inputs(2, 16, 240, 16, seed=5, dtype=torch.float64)
    delta[:, ::2] = 1e-4  # every other channel slow: each 8-lane block mixes both
    delta[:, 1::2] = 2.0
    args = (u, delta, A, Bm, Cm, D)
    ref = selective_scan_ref(*args, circular=True).numpy()
    lib = load()
    try:
        outs = {}
        for flush in (1, 0):
            lib.scan_set_flush(flush)
            outs[flush] = scan_forward(*(x.float().numpy() for x in args), True, threads)
    finally:
        lib.scan_set_flush(1)
    scale = float(abs(ref).max())
    for y in outs.values():
        assert float(abs(y - ref).max()) <= 2e-6 * scale
    np.testing.assert_allclose(outs[1], outs[0], rtol=0, atol=1e-7 * scale)

    def keeps_subnormals() -> bool:
        return float(np.float32(1e-30) * np.float32(1e-10)) != 0.0

    assert keeps_subnormals()  # the calling thread, after the kernel ran on it
    for pool in list(_pools.values()):  # and the kernel's other threads
        assert all(f.result() for f in [pool.submit(keeps_subnormals) for _ in range(4)])


@pytest.mark.parametrize("loud", [1e3, 1e5])
def test_each_channels_ring_correction_is_exact_to_its_own_scale(loud):
    """Found in review: the ring's correction left a state once it was small against the
    largest start state of its block of 8 channels, so a quiet, slowly decaying channel beside
    a loud, fast one lost its correction while it still mattered (2e-3 of its scale with a
    neighbour 1e3× louder, 0.26 at 1e5×); and a start state past √FLT_MAX squared to inf and
    dropped every correction (the wrong sign). Each channel is now held to its own scale."""
    from overlapmamba.core.scan_kernel import scan_forward

    u, delta, A, Bm, Cm, D = inputs(1, 8, 600, 16, seed=3, dtype=torch.float64)
    delta = torch.full_like(delta, 0.05)
    u[..., 0] *= loud  # channel 0 loud and fast, channel 1 quiet and slow, one block
    delta[..., 0] = 2.0
    delta[..., 1] = 1e-3
    huge = (u / loud * 1e21, torch.full_like(delta, 1e-3))  # a start state ≈ 1e21
    for uu, dd in ((u, delta), huge):
        args = (uu, dd, A, Bm, Cm, D)
        ref = selective_scan_ref(*args, circular=True).numpy()
        y = scan_forward(*(x.float().numpy() for x in args), True, 1)
        for c in range(8):
            scale = float(abs(ref[..., c]).max())
            assert float(abs(y[..., c] - ref[..., c]).max()) <= 2e-5 * scale, (loud, c)


def test_the_served_kernel_for_older_processors_gives_the_same_numbers(tmp_path):
    """The Docker image builds for x86-64-v2 (4 lanes, SSE): the same scan as this machine's
    build, on every path."""
    import os
    import platform
    import subprocess
    import sys

    import numpy as np

    if platform.machine() not in ("x86_64", "AMD64"):
        pytest.skip("x86-64-v2 is an x86 target")
    arrays = {}
    for kind in ("powers", "exps", "slow"):
        for i, x in enumerate(_served_inputs(kind)):
            arrays[f"{kind}{i}"] = x.float().numpy()
    np.savez(tmp_path / "in.npz", **arrays)
    code = (
        "import numpy as np, sys; from overlapmamba.core.scan_kernel import scan_forward;"
        "z = np.load(sys.argv[1]);"
        "np.savez(sys.argv[2], **{k + str(c): scan_forward(*(z[k + str(i)] for i in range(6)),"
        " circular=bool(c), threads=2) for k in ('powers', 'exps', 'slow') for c in (0, 1)})"
    )
    env = os.environ | {
        "OVERLAPMAMBA_KERNEL_MARCH": "x86-64-v2",
        "OVERLAPMAMBA_CACHE": str(tmp_path / "cache"),
    }
    out = tmp_path / "out.npz"
    subprocess.run(
        [sys.executable, "-c", code, str(tmp_path / "in.npz"), str(out)], env=env, check=True
    )
    from overlapmamba.core.scan_kernel import scan_forward

    old = np.load(out)
    for kind in ("powers", "exps", "slow"):
        for c in (0, 1):
            here = scan_forward(*(arrays[f"{kind}{i}"] for i in range(6)), bool(c), 2)
            scale = float(np.abs(here).max())
            np.testing.assert_allclose(old[f"{kind}{c}"], here, rtol=0, atol=2e-6 * scale)


@pytest.mark.skipif(not PROC_STATM, reason="reads Linux's /proc")
@pytest.mark.parametrize("threads", [1, 2])
def test_the_served_kernel_gives_back_what_it_allocates(threads):
    """The service runs the kernel on every scan it encodes, for as long as it is up: a ring
    scan's per-call buffers (L · N vectors, ≈ 0.5 MB at 900 columns) must be freed, or the
    service's memory grows by that much per scan node per batch until it is killed."""
    from overlapmamba.core.scan_kernel import scan_forward

    arrays = [x.numpy() for x in inputs(1, 8, 900, 16, seed=3, dtype=torch.float32)]
    for _ in range(20):  # the allocator's and the thread pool's first blocks
        scan_forward(*arrays, circular=True, threads=threads)
    before = resident_bytes()
    calls = 400
    for _ in range(calls):
        scan_forward(*arrays, circular=True, threads=threads)
    grown = resident_bytes() - before
    per_call = 900 * 16 * 32  # what one call's ring buffer is, with 8-lane vectors
    assert grown < calls * per_call / 10, f"resident memory grew {grown / 1e6:.1f} MB"


def test_a_split_waits_for_every_part_even_when_one_fails():
    """The parts write into buffers only the caller keeps alive: when one part fails, the
    split must not return (and let the caller free them) while another still runs."""
    import threading
    import time

    from overlapmamba.core.scan_kernel import run_split

    ended: list[int] = []
    lock = threading.Lock()

    def part(r0: int, r1: int) -> None:
        if r0 == 1:  # the first part handed to the pool fails at once
            raise RuntimeError("part 1 failed")
        if r0 > 1:  # the caller's own part (0) ends at once, the pool's others later
            time.sleep(0.3)
        with lock:
            ended.append(r0)

    with pytest.raises(RuntimeError, match="part 1 failed"):
        run_split(part, 4, 4)
    assert sorted(ended) == [0, 2, 3]  # all the others ran to their end first


def test_the_fused_scan_refuses_tensors_it_would_read_out_of_bounds():
    """The kernel reads raw memory as u's dtype and the legend's shapes: a mismatch is an
    error naming the tensor, never a read past a buffer."""
    u, delta, A, Bm, Cm, D = inputs(2, 4, 9, 3)
    with pytest.raises(TypeError, match=r"u's torch.float64; got A torch.float32"):
        scan_fused.selective_scan_fused(u, delta, A.float(), Bm, Cm, D)
    with pytest.raises(ValueError, match=r"B \(2, 9, 2\).*want"):
        scan_fused.selective_scan_fused(u, delta, A, Bm[..., :2], Cm, D)
    with pytest.raises(ValueError, match=r"D \(3,\)"):
        scan_fused.selective_scan_fused(u, delta, A, Bm, Cm, D[:3])
    with pytest.raises(ValueError, match="u must be"):
        scan_fused.selective_scan_fused(u[0], delta, A, Bm, Cm, D)
    with pytest.raises(ValueError, match="CPU tensors; got C on meta"):
        scan_fused.selective_scan_fused(u, delta, A, Bm, Cm.to("meta"), D)


def test_the_served_kernel_refuses_a_malformed_state_matrix():
    """A broken file's A (not E × N) is a ValueError the encoder falls back on, not an
    IndexError it does not expect."""
    from overlapmamba.core.scan_kernel import scan_forward

    u, delta, A, Bm, Cm, D = (x.numpy() for x in inputs(1, 8, 5, 4, dtype=torch.float32))
    with pytest.raises(ValueError, match="A \\(E, N\\)"):
        scan_forward(u, delta, A[0], Bm, Cm, D, circular=True)


def test_the_processor_is_named_with_its_family_and_model_where_linux_says():
    """Reports name the processor beside their figures (the kernel's cost depends on it): a
    cloud machine's generic name is completed by /proc/cpuinfo's vendor, family and model."""
    import platform

    from overlapmamba.core.scan_kernel import processor

    p = processor()
    assert isinstance(p["name"], str) and p["name"]
    if PROC_STATM and platform.machine() == "x86_64":  # Linux on x86 gives all of them
        assert {"vendor_id", "cpu family", "model"} <= p.keys()
        assert isinstance(p["avx512f"], bool)
