"""Training health: the numbers that show whether a metric-learning run learns or collapses.

Per step, from the batch's descriptors and its positive/negative pair masks:

    d_pos    mean squared distance over positive pairs     d(q, p)
    d_neg    mean squared distance over negative pairs     d(q, n)
    d_band   mean squared distance over the pairs that are neither (the ambiguous band:
             neighbouring places); where it sits between d_pos and d_neg is what the band
             term of the loss orders
    gap      d_neg − d_pos: what the loss is meant to grow
    spread   mean squared distance over all distinct pairs: the descriptors' scale
    separation  gap ÷ spread: the gap at the descriptors' own scale (what a loss with
             normalised distances grows; unit vectors may spread or gather freely)
    active   share of the loss's hinge terms that were > 0 (from :class:`~losses.BatchLoss`)
    margin   the margin the loss used (α, or α × spread with a relative margin)
    band_active  share of the band term's hinges that were > 0 (NaN when it is off)
    d_turn   mean squared distance between a scan and its turned copy (the turn term's;
             NaN when it is off)
    d_look   mean squared distance between a scan and its copy seen as another sensor (the
             sensor term's; NaN when it is off)

A collapse reads as: ``active`` near 1, ``spread`` falling towards 0 and the loss sitting at
its margin. :class:`HealthLog` keeps a record every ``every`` steps (means over those steps)
and an epoch mean; :meth:`HealthLog.collapsing` says when the spread has fallen below a
quarter of where the epoch, or the run, started.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

KEYS = (
    "loss",
    "d_pos",
    "d_neg",
    "d_band",
    "gap",
    "separation",
    "spread",
    "active",
    "margin",
    "band_active",
    "d_turn",
    "d_look",
)


@torch.no_grad()
def batch_distances(desc: Tensor, pos_mask: Tensor, neg_mask: Tensor) -> dict[str, float]:
    """desc (B, D); masks (B, B) over ordered pairs → d_pos, d_neg, d_band (pairs in neither
    mask), gap, separation, spread (NaN where a batch has no pair of that kind)."""
    d = torch.cdist(desc.detach().float(), desc.detach().float()).pow(2)
    B = d.shape[0]
    other = ~torch.eye(B, dtype=torch.bool, device=d.device)

    def mean(mask: Tensor) -> float:
        n = int(mask.sum())
        return float(d[mask].sum()) / n if n else math.nan

    d_pos, d_neg, spread = mean(pos_mask & other), mean(neg_mask & other), mean(other)
    d_band = mean(other & ~pos_mask & ~neg_mask)
    gap = d_neg - d_pos
    separation = gap / spread if spread > 0 else math.nan
    return {
        "d_pos": d_pos,
        "d_neg": d_neg,
        "d_band": d_band,
        "gap": gap,
        "separation": separation,
        "spread": spread,
    }


def _nanmean(values: list[float]) -> float:
    a = np.asarray(values, dtype=np.float64)
    a = a[np.isfinite(a)]
    return float(a.mean()) if len(a) else math.nan


@dataclass
class HealthLog:
    """Step records → one logged record every ``every`` steps and an epoch summary."""

    every: int = 10
    step0: int = 0  # global index of this epoch's first step
    steps: list[dict[str, float]] = field(default_factory=list)
    logged: list[dict[str, float]] = field(default_factory=list)
    reference_spread: float = math.nan  # the run's first logged spread (carried across epochs)

    def add(self, record: dict[str, float]) -> dict[str, float] | None:
        """Add one step; returns the new logged record when one is due."""
        self.steps.append({k: float(record.get(k, math.nan)) for k in KEYS})
        if len(self.steps) % self.every:
            return None
        return self._log(self.steps[-self.every :])

    def _log(self, window: list[dict[str, float]]) -> dict[str, float]:
        entry = {"step": self.step0 + len(self.steps)} | {
            k: _nanmean([s[k] for s in window]) for k in KEYS
        }
        self.logged.append(entry)
        if math.isnan(self.reference_spread):
            self.reference_spread = entry["spread"]
        return entry

    def flush(self) -> dict[str, float] | None:
        """Log the steps after the last full window (the end of an epoch)."""
        done = len(self.logged) * self.every
        if len(self.steps) <= done:
            return None
        return self._log(self.steps[done:])

    def recent(self, n: int = 20) -> dict[str, float]:
        return {k: _nanmean([s[k] for s in self.steps[-n:]]) for k in KEYS}

    def summary(self) -> dict[str, float]:
        """Means over the epoch's steps."""
        return {k: _nanmean([s[k] for s in self.steps]) for k in KEYS}

    def collapsing(self) -> bool:
        """The latest logged spread is below a quarter of the run's first."""
        if not self.logged or not math.isfinite(self.reference_spread):
            return False
        return self.logged[-1]["spread"] < 0.25 * self.reference_spread


def json_safe(obj: Any) -> Any:
    """A copy with every NaN or infinite float as None: strict JSON readers (browsers, jq)
    refuse Python's NaN. Used for ``metrics.json``."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [json_safe(v) for v in obj]
    return obj


def strict_json(obj: Any, indent: int = 1) -> str:
    """``obj`` as strict JSON: NaN and infinities (numpy's scalars too) as null, never the
    ``NaN`` Python writes and browsers, jq and other readers refuse."""
    return json.dumps(
        json_safe(obj), indent=indent, default=lambda x: json_safe(float(x)), allow_nan=False
    )


def epoch_line(entry: dict[str, Any], start: str) -> str:
    """The line a run prints after an epoch: its training health (epoch 0: where it
    started), the copies' distances, validation, the real-scan turn check and the
    renderings of other sensors."""
    v, h = entry["val"], entry.get("health")
    trained = (
        f"loss {entry['loss']:.4f}, {entry['scans_per_s']:.2f} scans/s, d(q,p) "
        f"{h['d_pos']:.4f} d(q,n) {h['d_neg']:.4f} spread {h['spread']:.4f} "
        f"separation {h['separation']:.2f} active {h['active']:.0%}; "
        if h
        else f"start: {start}; "
    )
    for key, what in (("d_turn", "turned copy"), ("d_look", "as another sensor")):
        if h and not math.isnan(h.get(key, math.nan)):
            trained += f"{what} {h[key]:.5f}; "
    real = entry.get("real")
    rest = (
        f"; real scans: turned copy {real['turned_over_one_metre_step']:.2f}× a 1 m step, "
        f"min cosine {real['cosine_min']:.5f}"
        if real
        else ""
    )
    for name, got in (entry.get("val_sensors") or {}).items():
        own, cross = got["own"]["all"], got["cross"]["all"]
        rest += (
            f"; {name} F1max {own['f1max']:.3f}, against the val scans "
            f"{cross['f1max']:.3f} (R@1 {cross['recall@1']:.3f})"
        )
    return (
        f"epoch {entry['epoch']}: {trained}val F1max {v['all']['f1max']:.3f} (same "
        f"{v['same']['f1max']:.3f}, reverse {v['reverse']['f1max']:.3f}), "
        f"R@1 {v['all']['recall@1']:.3f}{rest}"
    )
