"""Training health numbers: distances by hand, logging windows, the collapse warning."""

from __future__ import annotations

import math

import pytest

torch = pytest.importorskip("torch")

from overlapmamba.train.health import KEYS, HealthLog, batch_distances  # noqa: E402


def test_batch_distances_by_hand():
    desc = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 2.0]])
    pos = torch.tensor([[0, 1, 0], [1, 0, 0], [0, 0, 0]], dtype=torch.bool)
    neg = torch.tensor([[0, 0, 1], [0, 0, 1], [1, 1, 0]], dtype=torch.bool)
    d = batch_distances(desc, pos, neg)
    assert d["d_pos"] == pytest.approx(1.0)  # |(0,0) − (1,0)|²
    assert d["d_neg"] == pytest.approx((4 + 5 + 4 + 5) / 4)
    assert d["spread"] == pytest.approx((1 + 4 + 5) * 2 / 6)
    assert d["gap"] == pytest.approx(d["d_neg"] - d["d_pos"])
    assert d["separation"] == pytest.approx(d["gap"] / d["spread"])
    none = batch_distances(desc, torch.zeros(3, 3, dtype=torch.bool), neg)
    assert math.isnan(none["d_pos"]) and math.isnan(none["gap"])


def step(spread: float, **kw) -> dict[str, float]:
    return {k: 0.5 for k in KEYS} | {"spread": spread} | kw


def test_log_windows_summary_and_collapse_warning():
    log = HealthLog(every=2, step0=10)
    assert log.add(step(0.02)) is None
    first = log.add(step(0.04, active=float("nan")))
    assert first is not None and first["step"] == 12
    assert first["spread"] == pytest.approx(0.03) and first["active"] == 0.5  # NaN skipped
    assert not log.collapsing()
    for s in (0.02, 0.01, 0.006, 0.005):
        log.add(step(s))
    assert [r["step"] for r in log.logged] == [12, 14, 16]
    assert log.logged[-1]["spread"] == pytest.approx(0.0055)
    assert log.collapsing()  # below a quarter of the run's first record (0.03)
    assert log.summary()["spread"] == pytest.approx((0.02 + 0.04 + 0.02 + 0.01 + 0.011) / 6)
    # the next epoch compares against the run's start, not its own
    nxt = HealthLog(every=1, step0=16, reference_spread=log.reference_spread)
    nxt.add(step(0.006))
    assert nxt.collapsing()


def test_the_steps_after_the_last_full_window_are_logged_at_the_end():
    log = HealthLog(every=4)
    for s in (0.1, 0.2, 0.3, 0.4, 0.5, 0.6):
        log.add(step(s))
    tail = log.flush()
    assert tail is not None and tail["step"] == 6 and tail["spread"] == pytest.approx(0.55)
    assert log.flush() is None and len(log.logged) == 2
    short = HealthLog(every=10)  # fewer steps than a window: still one record
    short.add(step(0.3))
    assert short.flush()["spread"] == pytest.approx(0.3)


def test_json_safe_turns_nan_into_null():
    import json

    from overlapmamba.train.health import json_safe

    text = json.dumps(json_safe({"a": [1.0, float("nan")], "b": {"c": float("inf")}}))
    assert json.loads(text) == {"a": [1.0, None], "b": {"c": None}}
