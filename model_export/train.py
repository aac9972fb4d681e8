"""Training: cached range images → batches from the overlap table → OverlapMamba → batch loss.

    overlapmamba train --data data/synth/train --val data/synth/val --out runs/NAME

Each epoch draws ``epoch_scans`` scans in batches (:mod:`model_export.batches`), rolls every
range image by a random yaw, and steps Adam; the learning rate follows StepLR. After each
epoch it validates on the loop-closure protocol (F1max and Recall@1 over all, same- and
reverse-direction revisits) and writes, atomically:

    runs/NAME/last.pt          everything to resume (optimiser and scheduler included)
    runs/NAME/best.pt          the epoch with the best validation F1max (weights, no optimiser)
    runs/NAME/epoch-NNN.pt     every epoch (weights, no optimiser)
    runs/NAME/metrics.json     per-epoch history; runs/NAME/curves.png: loss and F1 per epoch

**Reproducible and resumable.** The weights start from ``seed``; epoch k draws its batches,
rolls and shifts from generators seeded by (seed, k) alone. So ``--resume`` after any epoch
continues exactly as an uninterrupted run would (tested).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from lidar_core.datasets import open_sequence
from lidar_core.datasets.base import Sequence
from lidar_core.errors import DatasetError
from lidar_core.sensors import SensorProfile, get_profile
from model_export.batches import BatchPlan, BatchSampler, PairIndex
from model_export.checkpoint import read_checkpoint, save_checkpoint
from model_export.errors import ConfigError, dataclass_from_dict
from model_export.evaluate import describe, loop_closure, sequence_loops, summary
from model_export.losses import BATCH_LOSSES, ImTrihardParams
from model_export.model import OverlapMamba, OverlapMambaConfig
from model_export.rangecache import cache_key, range_images


@dataclass
class TrainConfig:
    epochs: int = 10
    epoch_scans: int = 2000  # scans drawn per epoch
    batch_size: int = 16  # groups of 4: anchor, 2 positives, near miss
    lr: float = 1e-4  # Adam; the reference's 5e-6 barely moves a freshly initialised head
    step_size: int = 5  # StepLR: × gamma every step_size epochs (reference: 5, 0.9)
    gamma: float = 0.9
    loss: str = "imtrihard"  # imtrihard (paper eq. 13) or triplet (OverlapTransformer)
    alpha: float = 0.5  # ImTrihard margin α (see losses.ImTrihardParams for the reasons)
    lam: float = 0.1  # ImTrihard compression weight λ
    k_p: float = 1.0
    k_n: float = 1.0
    hinge: bool = True
    margin: float = 0.5  # triplet margin m
    positive_threshold: float = 0.3  # overlap above this: positive
    revisit_fraction: float = 0.5  # anchors whose first positive is an old pass
    seed: int = 0
    device: str = "cpu"  # cpu or cuda

    def __post_init__(self) -> None:
        if self.loss not in BATCH_LOSSES:
            raise ConfigError(f"unknown loss {self.loss!r}; allowed: {', '.join(BATCH_LOSSES)}")
        for name in ("epochs", "epoch_scans", "batch_size", "step_size"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be ≥ 1, got {getattr(self, name)}")
        if not (self.lr > 0 and 0 < self.gamma <= 1 and 0 <= self.positive_threshold < 1):
            raise ConfigError("need lr > 0, 0 < gamma ≤ 1 and 0 ≤ positive_threshold < 1")
        if self.device not in ("cpu", "cuda"):
            raise ConfigError(f"device {self.device!r} is not allowed; allowed: cpu, cuda")

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        cfg: TrainConfig = dataclass_from_dict(cls, d, "training")
        return cfg

    def loss_fn(self):
        fn = BATCH_LOSSES[self.loss]
        if self.loss == "imtrihard":
            p = ImTrihardParams(self.alpha, self.lam, self.k_p, self.k_n, self.hinge)
            return lambda d, ov: fn(d, ov, self.positive_threshold, p)
        return lambda d, ov: fn(d, ov, self.positive_threshold, self.margin)


def load_config_file(path: Path) -> tuple[dict, dict]:
    """``{"model": {...}, "train": {...}}`` from .json or .toml → (model dict, train dict)."""
    if not path.is_file():
        raise ConfigError(f"config file {path} does not exist")
    text = path.read_text()
    if path.suffix == ".json":
        raw = json.loads(text)
    elif path.suffix == ".toml":
        import tomllib

        raw = tomllib.loads(text)
    else:
        raise ConfigError(f"{path.name}: allowed config suffixes are .json and .toml")
    extra = sorted(set(raw) - {"model", "train"})
    if extra:
        raise ConfigError(f"{path}: unknown sections {extra}; allowed: model, train")
    return dict(raw.get("model", {})), dict(raw.get("train", {}))


class _Images:
    """Range images of several sequences behind global scan indices."""

    def __init__(self, seqs: list[Sequence], profile: SensorProfile, progress: bool) -> None:
        self.parts = [range_images(s, profile, progress=progress) for s in seqs]
        self.offsets = np.cumsum([0, *[len(p) for p in self.parts]])

    def __getitem__(self, idx: np.ndarray) -> np.ndarray:
        k = np.searchsorted(self.offsets, idx, side="right") - 1
        return np.stack([self.parts[s][i - self.offsets[s]] for s, i in zip(k, idx, strict=True)])


def _open(path: Path, cfg: OverlapMambaConfig, role: str) -> Sequence:
    seq = open_sequence(path)
    manifest = path / "manifest.json"
    if manifest.is_file():
        meta = json.loads(manifest.read_text()).get("config", {})
        if role == "training" and meta.get("split") == "test":
            raise DatasetError(f"{path} is a test split: it is never trained on")
        if meta.get("sensor", cfg.sensor) != cfg.sensor:
            raise DatasetError(
                f"{path} was recorded with {meta['sensor']}, the model expects {cfg.sensor}"
            )
    return seq


def _profile(cfg: OverlapMambaConfig) -> SensorProfile:
    profile = get_profile(cfg.sensor)
    if (profile.height, profile.width) != (cfg.height, cfg.width):
        raise ConfigError(
            f"model input {cfg.height}×{cfg.width} does not match sensor {cfg.sensor}'s "
            f"range images ({profile.height}×{profile.width})"
        )
    return profile


def _random_yaw(images: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(B, H, W) → float32, each image rolled by its own random number of columns: the sensor
    turned about z. (With the circular model this changes the descriptor by rounding only; it
    keeps mattering for the non-circular ablations.)"""
    shifts = rng.integers(images.shape[-1], size=len(images))
    return np.stack([np.roll(img, int(k), axis=-1) for img, k in zip(images, shifts, strict=True)])


def _plot_curves(history: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ep = [h["epoch"] for h in history]
    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.4), dpi=110)
    a.plot(ep, [h["loss"] for h in history], "o-")
    a.set(xlabel="epoch", ylabel="training loss", title="loss")
    for sub in ("all", "same", "reverse"):
        b.plot(ep, [h["val"][sub]["f1max"] for h in history], "o-", label=f"F1max {sub}")
    b.plot(ep, [h["val"]["all"]["recall@1"] for h in history], "ks--", label="R@1 all")
    b.set(xlabel="epoch", ylim=(0, 1), title="validation")
    b.legend(fontsize=7)
    for ax in (a, b):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def train(
    data: list[Path],
    val: Path | None,
    out: Path,
    model_cfg: OverlapMambaConfig | None = None,
    train_cfg: TrainConfig | None = None,
    *,
    resume: bool = False,
    epochs: int | None = None,
    progress: bool = True,
) -> list[dict[str, Any]]:
    """Train (or resume) a run in ``out``; returns the per-epoch history.

    Resuming reads the model and training config and the data paths from ``out/last.pt``;
    ``epochs`` may extend the run."""
    out = Path(out)
    last = out / "last.pt"
    state: dict[str, Any] | None = None
    if resume:
        if not last.is_file():
            raise ConfigError(f"nothing to resume: {last} does not exist")
        state = read_checkpoint(last)
        recorded = state["train"]["data"]
        data = data or [Path(d["path"]) for d in recorded["train"]]
        val = val or Path(recorded["val"]["path"])
        model_cfg = OverlapMambaConfig.from_dict(state["model_config"])
        train_cfg = TrainConfig.from_dict(state["train"]["config"])
    elif last.is_file():
        raise ConfigError(f"{out} already holds a run; pass --resume or choose a new --out")
    model_cfg = model_cfg or OverlapMambaConfig()
    train_cfg = train_cfg or TrainConfig()
    if epochs is not None:
        train_cfg.epochs = epochs
    if train_cfg.device == "cuda" and not torch.cuda.is_available():
        raise ConfigError("--device cuda: no CUDA device is visible to PyTorch here")
    device = torch.device(train_cfg.device)
    profile = _profile(model_cfg)

    if not data or val is None:
        raise ConfigError("training needs at least one training sequence and a validation one")
    seqs = [_open(p, model_cfg, "training") for p in data]
    val_seq = _open(val, model_cfg, "validation")
    if any(s.root.resolve() == val_seq.root.resolve() for s in seqs):
        raise ConfigError(f"{val} is both training and validation data")
    fingerprints = {
        "train": [{"path": str(s.root), "key": cache_key(s, profile)} for s in seqs],
        "val": {"path": str(val_seq.root), "key": cache_key(val_seq, profile)},
    }
    if state is not None and state["train"]["data"] != fingerprints:
        raise ConfigError("--resume with other data than the run was started on")
    images = _Images(seqs, profile, progress)
    val_images = range_images(val_seq, profile, progress=progress)
    val_gt = sequence_loops(val_seq, profile, progress=progress)
    if not val_gt.has_loop().any():
        raise DatasetError(
            f"{val}: the validation sequence has no loop closure, so F1max and Recall@1 "
            "would mean nothing; validate on a sequence with revisits (e.g. the val preset)"
        )
    pairs = PairIndex.from_sequences(seqs)
    sampler = BatchSampler(
        pairs,
        BatchPlan(train_cfg.batch_size, train_cfg.positive_threshold, train_cfg.revisit_fraction),
    )

    torch.manual_seed(train_cfg.seed)
    model = OverlapMamba(model_cfg).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=train_cfg.lr)
    sched = torch.optim.lr_scheduler.StepLR(opt, train_cfg.step_size, train_cfg.gamma)
    history: list[dict[str, Any]] = []
    best = {"epoch": 0, "f1max": -1.0}
    if state is not None:
        model.load_state_dict(state["state_dict"])
        opt.load_state_dict(state["train"]["optimizer"])
        sched.load_state_dict(state["train"]["scheduler"])
        history, best = list(state["train"]["history"]), dict(state["train"]["best"])
    loss_fn = train_cfg.loss_fn()

    def payload(with_optimizer: bool, metrics: dict) -> dict[str, Any]:
        train_state: dict[str, Any] = {
            "config": asdict(train_cfg),
            "epochs_done": len(history),
            "history": history,
            "best": best,
            "data": fingerprints,
        }
        if with_optimizer:
            train_state["optimizer"] = opt.state_dict()
            train_state["scheduler"] = sched.state_dict()
        return {
            "model_config": model_cfg.to_dict(),
            "profile": profile.model_dump(),
            "state_dict": model.state_dict(),
            "train": train_state,
            "metrics": metrics,
        }

    for epoch in range(len(history) + 1, train_cfg.epochs + 1):
        rng = np.random.default_rng([train_cfg.seed, epoch])
        torch.manual_seed(int(rng.integers(2**31)))  # the shifted branch's draws
        batches = sampler.epoch(rng, train_cfg.epoch_scans)
        model.train()
        losses: list[float] = []
        t0 = time.perf_counter()
        bar = tqdm(batches, desc=f"epoch {epoch}/{train_cfg.epochs}", disable=not progress)
        for idx in bar:
            x = _random_yaw(images[idx].astype(np.float32), rng)
            desc, _ = model(torch.from_numpy(x)[:, None].to(device))
            overlap = torch.from_numpy(pairs.submatrix(idx)).to(device)
            loss = loss_fn(desc, overlap)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            losses.append(loss.item())
            done = len(losses) * train_cfg.batch_size
            bar.set_postfix(
                loss=f"{np.mean(losses[-20:]):.4f}",
                scans_s=f"{done / (time.perf_counter() - t0):.2f}",
            )
        train_s = time.perf_counter() - t0
        sched.step()
        t1 = time.perf_counter()
        desc_val, _ = describe(model, val_images, device=str(device))
        val_metrics = summary(loop_closure(desc_val, val_gt))
        entry = {
            "epoch": epoch,
            "loss": float(np.mean(losses)),
            "step_losses": losses,
            "lr": opt.param_groups[0]["lr"],
            "train_s": train_s,
            "scans_per_s": len(losses) * train_cfg.batch_size / train_s,
            "val_s": time.perf_counter() - t1,
            "val": val_metrics,
        }
        history.append(entry)
        f1 = val_metrics["all"]["f1max"]
        is_best = not math.isnan(f1) and f1 > best["f1max"]
        if is_best:
            best = {"epoch": epoch, "f1max": f1}
        weights_only = payload(False, val_metrics)
        save_checkpoint(out / f"epoch-{epoch:03d}.pt", weights_only)
        if is_best:
            save_checkpoint(out / "best.pt", weights_only)
        save_checkpoint(last, payload(True, val_metrics))
        record = {
            "model_config": model_cfg.to_dict(),
            "train_config": asdict(train_cfg),
            "best": best,
            "history": history,
        }
        tmp = out / ".metrics.json.tmp"
        tmp.write_text(json.dumps(record, indent=1) + "\n")
        tmp.replace(out / "metrics.json")
        _plot_curves(history, out / "curves.png")
        if progress:
            v = val_metrics
            tqdm.write(
                f"epoch {epoch}: loss {entry['loss']:.4f}, {entry['scans_per_s']:.2f} scans/s; "
                f"val F1max {v['all']['f1max']:.3f} (same {v['same']['f1max']:.3f}, reverse "
                f"{v['reverse']['f1max']:.3f}), R@1 {v['all']['recall@1']:.3f}"
            )
    return history
