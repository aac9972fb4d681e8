"""Batch-norm statistics recalibrated from data, without a gradient step.

A freshly built network's batch-norm layers hold running statistics of 0 and 1. In eval
mode they normalise with those, not with what the layer actually sees, so the "untrained"
network is evaluated with a distorted SPP block. Measured on the tiny validation town
(narrow network, 136 revisiting scans): F1max 0.620 as built, 0.729 after 20 forward passes
in train mode. Training's epoch 0, and Table I's "untrained" row, are that model.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable

import torch
from torch import Tensor, nn


@torch.no_grad()
def recalibrate_batchnorm(model: nn.Module, batches: Iterable[Tensor]) -> int:
    """Replace every batch-norm layer's running mean and variance with their average over
    ``batches`` (inputs to ``model``; forward passes in train mode, no gradient). The
    weights, the model's mode and the layers' momentum are left as they were. Returns the
    number of batches seen (0 when the model has no batch norm: nothing runs)."""
    norms = [m for m in model.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)]
    if not norms:
        return 0
    it = iter(batches)
    first = next(it, None)
    if first is None:  # checked before any statistic is touched
        raise ValueError("recalibrating batch norm needs at least one batch; got none")
    was_training = model.training
    momenta = [m.momentum for m in norms]
    for m in norms:
        m.reset_running_stats()
        m.momentum = None  # cumulative average over the batches below
    model.train()
    seen = 0
    try:
        for x in itertools.chain([first], it):
            model(x)
            seen += 1
    finally:
        for m, momentum in zip(norms, momenta, strict=True):
            m.momentum = momentum
        model.train(was_training)
    return seen
