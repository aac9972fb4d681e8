"""The selective scan (Mamba's S6 recurrence): a plain reference, a chunked path, one dispatch.

Shapes (one legend for both functions):

    u:     (B, L, E)   inputs: L steps (image columns) of E channels, token-major
    delta: (B, L, E)   step sizes Δ, positive (after softplus)
    A:     (E, N)      continuous-time decay rates, negative
    Bm:    (B, L, N)   input projection per step
    Cm:    (B, L, N)   output projection per step
    D:     (E,)        skip connection
    → y:   (B, L, E)

Token-major is the layout the projections produce and the output projection consumes, so
no backend needs a transpose of an (E × L) tensor around the scan (in onnxruntime such a
transpose cost more than the rest of the block).

Zero-order hold discretisation, as in Mamba:

    h_t = exp(Δ_t A) ⊙ h_{t−1} + Δ_t B_t u_t        h: (B, E, N)
    y_t = Σ_n C_t,n h_t,n + D u_t

**Circular mode.** Over a ring of columns (a 360° range image) there is no first column.
The recurrence is linear and diagonal, so its periodic steady state has a closed form: run
from h = 0 to get h_L and the product of all decays P = Π_t exp(Δ_t A); the state entering
the ring is h_L / (1 − P) elementwise. Starting from it, rolling the inputs by k columns
rolls every output by exactly k columns (up to float rounding).

The chunked path splits the sequence into chunks of T steps and runs (a) the T steps of every
chunk at once from a zero state, (b) a carry pass over the L/T chunk boundaries, and (c) a
correction pass that adds each chunk's incoming state. That is 2T + L/T small steps instead
of L, and no tensor of shape (B, E, L, N) is ever materialised: peak extra memory is
(B, E, L/T, N).
"""

from __future__ import annotations

import torch
from torch import Tensor


def _ring_start(h_end: Tensor, log_p: Tensor) -> Tensor:
    """State entering the ring: h_L / (1 − P), P = exp(log_p) < 1 elementwise."""
    # 1 − P ≥ 1e-6 keeps a ring with almost no decay (Δ·A ≈ 0) finite.
    return h_end / (-torch.expm1(log_p)).clamp_min(1e-6)


def selective_scan_ref(
    u: Tensor, delta: Tensor, A: Tensor, Bm: Tensor, Cm: Tensor, D: Tensor, circular: bool = False
) -> Tensor:
    """Step by step, exactly as the equations read. Slow; the yardstick for the fast paths."""
    Bsz, L, E = u.shape
    h = u.new_zeros(Bsz, E, A.shape[1])
    if circular:
        log_p = u.new_zeros(Bsz, E, A.shape[1])
        for t in range(L):
            dA = delta[:, t, :, None] * A  # (B, E, N)
            h = torch.exp(dA) * h + (delta[:, t] * u[:, t])[..., None] * Bm[:, t, None, :]
            log_p = log_p + dA
        h = _ring_start(h, log_p)
    ys = []
    for t in range(L):
        dA = delta[:, t, :, None] * A
        h = torch.exp(dA) * h + (delta[:, t] * u[:, t])[..., None] * Bm[:, t, None, :]
        ys.append((h * Cm[:, t, None, :]).sum(-1))
    return torch.stack(ys, dim=1) + D * u


def selective_scan(
    u: Tensor,
    delta: Tensor,
    A: Tensor,
    Bm: Tensor,
    Cm: Tensor,
    D: Tensor,
    circular: bool = False,
    chunk: int | None = None,
) -> Tensor:
    """Same result as :func:`selective_scan_ref` (to float rounding), in 2T + L/T steps."""
    # The chunk views below walk channel-major rows; y comes back token-major.
    u, delta, Bm, Cm = (x.transpose(1, 2) for x in (u, delta, Bm, Cm))
    Bsz, E, L = u.shape
    N = A.shape[1]
    T = chunk or max(1, round(L**0.5))
    pad = (-L) % T
    if pad:  # pad with Δ = 0 (no decay, no input): the state passes through unchanged
        u, delta = (torch.nn.functional.pad(x, (0, pad)) for x in (u, delta))
        Bm, Cm = (torch.nn.functional.pad(x, (0, pad)) for x in (Bm, Cm))
    K = (L + pad) // T  # chunks
    # Step t of chunk k is column k·T + t: view as (…, K, T) and walk t.
    du = (delta * u).reshape(Bsz, E, K, T)
    dl = delta.reshape(Bsz, E, K, T)
    Bv = Bm.reshape(Bsz, N, K, T)
    Cv = Cm.reshape(Bsz, N, K, T)

    # (a) every chunk from a zero state; keep only the outputs and the chunk-end state.
    h = u.new_zeros(Bsz, E, K, N)
    log_p = u.new_zeros(Bsz, E, K, N)  # Σ Δ·A within the chunk, so far
    y0 = []
    for t in range(T):
        dA = dl[..., t, None] * A[:, None, :]  # (B, E, K, N)
        h = torch.exp(dA) * h + du[..., t, None] * Bv[..., t].transpose(1, 2)[:, None]
        log_p = log_p + dA
        y0.append((h * Cv[..., t].transpose(1, 2)[:, None]).sum(-1))  # (B, E, K)

    # (b) carry across chunk boundaries: state entering chunk k.
    def carry(start: Tensor) -> list[Tensor]:
        enter, state = [], start
        for k in range(K):
            enter.append(state)
            state = torch.exp(log_p[:, :, k]) * state + h[:, :, k]
        enter.append(state)
        return enter

    enter = carry(u.new_zeros(Bsz, E, N))
    if circular:
        enter = carry(_ring_start(enter[-1], log_p.sum(2)))
    h_in = torch.stack(enter[:K], dim=2)  # (B, E, K, N)

    # (c) add each chunk's incoming state, decayed to every step of the chunk.
    ys = []
    cum = u.new_zeros(Bsz, E, K, N)
    for t in range(T):
        cum = cum + dl[..., t, None] * A[:, None, :]
        corr = (torch.exp(cum) * h_in * Cv[..., t].transpose(1, 2)[:, None]).sum(-1)
        ys.append(y0[t] + corr)
    y = torch.stack(ys, dim=-1).reshape(Bsz, E, K * T)[..., :L]
    return (y + D[:, None] * u[..., :L]).transpose(1, 2)


def selective_scan_loop(
    u: Tensor,
    delta: Tensor,
    A: Tensor,
    Bm: Tensor,
    Cm: Tensor,
    D: Tensor,
    circular: bool = False,
    chunk: int | None = None,
) -> Tensor:
    """The chunked algorithm written as three loops (``torch``'s ``scan`` operator).

    This is the form the ONNX export uses: each loop becomes one ONNX ``Scan`` node whose
    body updates only an (M, N, E) state, M = B · L/T rows. The K = L/T chunks of every
    sequence run side by side on the batch axis, so a loop takes T steps instead of L, and
    onnxruntime sees (M, N, E) tensors, large enough to vectorise and to split over threads:

    1. T steps: every chunk from a zero state → outputs y⁰ and chunk-end states;
    2. K steps: carry the chunk-end states across chunks (twice for the ring: from zero,
       which gives h_L, then from the ring's start state h_L / (1 − P));
    3. T steps: decay each chunk's entering state through the chunk → the correction of y.

    The state is laid out (N, E): E, the long axis, is innermost, so every broadcast in the
    loop body runs over contiguous rows of E. The time-major inputs come from token-major
    tensors by moving blocks of E contiguous floats, never single elements.
    """
    Bsz, L, E = u.shape
    N = A.shape[1]
    T = chunk or max(1, round(L**0.5))
    pad = (-L) % T
    if pad:  # Δ = 0 past the end: no decay, no input; the state passes through unchanged
        u, delta, Bm, Cm = (torch.nn.functional.pad(x, (0, 0, 0, pad)) for x in (u, delta, Bm, Cm))
    K = (L + pad) // T
    M = Bsz * K
    At = A.t().contiguous()  # (N, E)

    def by_step(x: Tensor) -> Tensor:  # (B, K·T, C) → (T, B·K, C): step t of every chunk
        C = x.shape[-1]
        return x.reshape(Bsz, K, T, C).permute(2, 0, 1, 3).reshape(T, M, C)

    dl = by_step(delta).unsqueeze(2)  # (T, M, 1, E)
    du = by_step(delta * u).unsqueeze(2)  # (T, M, 1, E)
    Bs = by_step(Bm).unsqueeze(3)  # (T, M, N, 1)
    Cs = by_step(Cm).unsqueeze(2)  # (T, M, 1, N)

    def chunk_step(h: Tensor, x: tuple[Tensor, ...]) -> tuple[Tensor, Tensor]:
        d, bu, b, c = x
        h = torch.exp(d * At) * h + b * bu
        return h, c @ h

    h_end, y0 = _loop(chunk_step, u.new_zeros(M, N, E), (dl, du, Bs, Cs))
    decay = torch.exp(dl.sum(0) * At)  # (M, N, E): each chunk's total decay

    def across(x: Tensor) -> Tensor:  # (B·K, N, E) → (K, B, N, E)
        return x.reshape(Bsz, K, N, E).transpose(0, 1)

    def carry_step(h: Tensor, x: tuple[Tensor, Tensor]) -> tuple[Tensor, Tensor]:
        p, e = x
        return p * h + e, h.clone()  # (the loop operator forbids returning its input)

    carried = (across(decay), across(h_end))
    h_L, enter = _loop(carry_step, u.new_zeros(Bsz, N, E), carried)
    if circular:
        log_p = delta.sum(1)[:, None, :] * At  # (B, N, E): log of the whole ring's decay
        _, enter = _loop(carry_step, _ring_start(h_L, log_p), carried)
    enter = enter.transpose(0, 1).reshape(M, N, E)

    def correct_step(g: Tensor, x: tuple[Tensor, Tensor]) -> tuple[Tensor, Tensor]:
        d, c = x
        g = torch.exp(d * At) * g
        return g, c @ g

    _, y1 = _loop(correct_step, enter, (dl, Cs))
    y = (y0 + y1).reshape(T, Bsz, K, E).permute(1, 2, 0, 3).reshape(Bsz, K * T, E)
    return y[:, :L] + D * u[:, :L]


def _loop(fn, init, xs):
    """torch's scan operator: exported as an ONNX ``Scan`` node, run as a loop in eager."""
    from torch._higher_order_ops.scan import scan as scan_op

    return scan_op(fn, init, xs)
