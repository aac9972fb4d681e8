"""A run's curves.png: loss per epoch, training health per logged step, validation per
epoch."""

from __future__ import annotations

import math
from pathlib import Path


def plot_curves(history: list[dict], path: Path) -> None:
    """Loss per epoch; health per logged step (distances, spread, active hinges); validation
    per epoch (epoch 0: the initial weights with recalibrated batch norm)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    trained = [h for h in history if h["epoch"] > 0]
    fig, (a, b, c) = plt.subplots(1, 3, figsize=(13, 3.6), dpi=110)
    a.plot([h["epoch"] for h in trained], [h["loss"] for h in trained], "o-")
    a.set(xlabel="epoch", ylabel="training loss", title="loss")
    log = [r for h in trained for r in h.get("health_log", [])]
    steps = [r["step"] for r in log]
    for key, style in (("d_pos", "g-"), ("d_neg", "r-"), ("spread", "k--"), ("margin", "b:")):
        b.plot(steps, [r[key] for r in log], style, label=key)
    band = [math.nan if r.get("d_band") is None else r["d_band"] for r in log]
    if any(math.isfinite(x) for x in band):  # runs from before the band was logged lack it
        b.plot(steps, band, "c-", label="d_band (neighbours)")
    for key, style, label in (
        ("d_turn", "m-", "d_turn (turned copy)"),  # the turn term's runs
        ("d_look", "y-", "d_look (as another sensor)"),  # the sensor term's runs
    ):
        copy = [math.nan if r.get(key) is None else r[key] for r in log]
        if any(math.isfinite(x) for x in copy):
            b.plot(steps, copy, style, label=label)
    b.set(xlabel="step", ylabel="squared distance", title="health", yscale="log")
    b.legend(fontsize=7, loc="upper left")
    twin = b.twinx()
    twin.plot(steps, [r["active"] for r in log], color="tab:orange", alpha=0.6, label="active")
    sep = [r["separation"] for r in log]
    twin.plot(steps, sep, color="tab:purple", label="separation (gap ÷ spread)")
    top = max([1.05, *[x * 1.05 for x in sep if x is not None and math.isfinite(x)]])
    twin.set(ylim=(0, top), ylabel="active share · separation")
    twin.legend(fontsize=7, loc="upper right")
    ep = [h["epoch"] for h in history]
    for sub in ("all", "same", "reverse"):
        c.plot(ep, [h["val"][sub]["f1max"] for h in history], "o-", label=f"F1max {sub}")
    c.plot(ep, [h["val"]["all"]["recall@1"] for h in history], "ks--", label="R@1 all")
    c.set(xlabel="epoch (0: initial weights)", ylim=(0, 1), title="validation")
    c.legend(fontsize=7)
    for ax in (a, b, c):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
