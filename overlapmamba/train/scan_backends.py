"""One entry point for every implementation of the selective scan (:func:`scan`): the
reference, chunked and loop forms of :mod:`overlapmamba.train.scan`, the C kernel of
:mod:`overlapmamba.train.scan_fused`, and the exported operator of
:mod:`overlapmamba.train.scan_onnx`
(the last two imported only when chosen)."""

from __future__ import annotations

import torch
from torch import Tensor

from overlapmamba.train.scan import selective_scan, selective_scan_loop, selective_scan_ref

BACKENDS = ("auto", "fused", "chunked", "loop", "onnx", "ref")


def scan(
    u: Tensor,
    delta: Tensor,
    A: Tensor,
    Bm: Tensor,
    Cm: Tensor,
    D: Tensor,
    circular: bool = False,
    *,
    backend: str = "auto",
    chunk: int | None = None,
) -> Tensor:
    """One entry point for every implementation; all give the same result to float rounding.

    - ``fused``: the C kernel of :mod:`overlapmamba.train.scan_fused` (CPU, fastest there);
    - ``chunked``: :func:`selective_scan` (any device, autograd through PyTorch ops);
    - ``loop``: :func:`selective_scan_loop` (the algorithm of the exported graph; no autograd);
    - ``onnx``: the same as one ``overlapmamba::selective_scan`` operator, which the ONNX
      export turns into one node with the loop as its function (:mod:`.scan_onnx`);
    - ``ref``: :func:`selective_scan_ref` (slow, obvious);
    - ``auto``: fused on CPU when the kernel builds, chunked otherwise (GPU, no compiler).
    """
    if backend not in BACKENDS:
        raise ValueError(f"unknown scan backend {backend!r}; allowed: {', '.join(BACKENDS)}")
    if backend == "auto":
        from overlapmamba.train import scan_fused

        on_cpu = u.device.type == "cpu" and u.dtype in (torch.float32, torch.float64)
        backend = "fused" if on_cpu and scan_fused.available() else "chunked"
    if backend == "fused":
        from overlapmamba.train.scan_fused import selective_scan_fused

        return selective_scan_fused(u, delta, A, Bm, Cm, D, circular)
    if backend == "chunked":
        return selective_scan(u, delta, A, Bm, Cm, D, circular, chunk)
    if backend == "loop":
        return selective_scan_loop(u, delta, A, Bm, Cm, D, circular, chunk)
    if backend == "onnx":
        from overlapmamba.train.scan_onnx import selective_scan_op

        return selective_scan_op(u, delta, A, Bm, Cm, D, circular, chunk)
    return selective_scan_ref(u, delta, A, Bm, Cm, D, circular)
