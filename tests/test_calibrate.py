"""Batch-norm recalibration: statistics from data, nothing else touched."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from torch import nn  # noqa: E402

from overlapmamba.train.calibrate import recalibrate_batchnorm  # noqa: E402


def net() -> nn.Module:
    torch.manual_seed(0)
    return nn.Sequential(nn.Conv1d(2, 3, 1), nn.BatchNorm1d(3), nn.ReLU(), nn.Linear(5, 1))


def test_statistics_are_the_average_over_the_batches_and_the_rest_is_kept():
    model = net().eval()
    weights = {k: v.clone() for k, v in model.state_dict().items() if "running" not in k}
    weights.pop("1.num_batches_tracked")
    g = torch.Generator().manual_seed(1)
    batches = [torch.randn(4, 2, 5, generator=g) * 3 + 2 for _ in range(3)]
    assert recalibrate_batchnorm(model, batches) == 3
    bn = model[1]
    with torch.no_grad():
        feats = [model[0](x) for x in batches]
    expected = torch.stack([f.mean((0, 2)) for f in feats]).mean(0)
    torch.testing.assert_close(bn.running_mean, expected)
    assert int(bn.num_batches_tracked) == 3 and bn.momentum == 0.1
    assert not model.training  # the mode it had
    for k, v in model.state_dict().items():
        if k in weights:
            torch.testing.assert_close(v, weights[k], rtol=0, atol=0, msg=k)


def test_no_batch_norm_runs_nothing_and_no_batches_touch_nothing():
    assert recalibrate_batchnorm(nn.Linear(2, 2), iter([])) == 0
    model = net()
    before = model[1].running_var.clone()
    with pytest.raises(ValueError, match="at least one batch"):
        recalibrate_batchnorm(model, [])
    torch.testing.assert_close(model[1].running_var, before)
