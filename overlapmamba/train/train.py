"""Training: cached range images → batches from the overlap table → OverlapMamba → batch loss.

    overlapmamba train --data data/synth/train --val data/synth/val --out runs/NAME

The recipe is a :class:`~overlapmamba.train.train_config.TrainConfig`.

**Epoch 0** is the initial network with its batch-norm statistics recalibrated on training
scans (:mod:`overlapmamba.train.calibrate`), validated like every epoch: every curve starts from a
fair untrained model, and selection may keep it.

**Epochs 1…** draw ``epoch_scans`` scans in batches (:mod:`overlapmamba.train.batches`; with
``hard_negatives`` > 0 a share of the groups get a negative mined by the epoch's starting
weights, :mod:`overlapmamba.train.mining`), augment them (:mod:`overlapmamba.train.augment`) and
step Adam; the learning rate warms up linearly over
``warmup_steps`` and then falls × ``gamma`` every ``step_size`` epochs. From
``band_from_epoch`` on, with ``band_weight`` / ``band_share`` > 0, the loss also ranks each
anchor's ambiguous band below its positives and a share of the groups bring a band scan
(:class:`~overlapmamba.train.losses.BandRanking`). Every step records the
training health (:mod:`overlapmamba.train.health`: d(q,p), d(q,n), spread, active hinges), shown in
the progress bar and kept every ``log_every`` steps; a spread that falls below a quarter of
where the run started prints a warning.

After each epoch (0 included) it validates on the loop-closure protocol (F1max and Recall@1
over all, same- and reverse-direction revisits), checks turned copies of real scans
(``real``: how far a continuous turn moves a descriptor against a 1 m step), and writes,
atomically:

    runs/NAME/last.pt          everything to resume (optimiser and scheduler included)
    runs/NAME/best.pt          the epoch with the best validation F1max (weights, no optimiser)
    runs/NAME/epoch-NNN.pt     every epoch (weights, no optimiser); epoch-000.pt: the start
    runs/NAME/metrics.json     per-epoch history with the health records
    runs/NAME/curves.png       loss, health per step, validation per epoch

**A trained start** (``init``): a checkpoint or an exported encoder
(:mod:`overlapmamba.train.recover`) replaces the seed's weights, and its network config is the
run's; with ``freeze_bn`` every batch norm stays in eval mode (no recalibration at epoch 0,
no statistics updated after). With ``turn_weight`` or ``look_weight`` > 0, copies of some
of each batch's scans, turned or seen as another sensor
(:func:`~overlapmamba.train.train_inputs.batch_copies`), are fed too, and
:func:`~overlapmamba.train.losses.consistency` of each scan and its copy joins the loss.

**Reproducible and resumable.** The weights start from ``seed``; epoch k draws its batches,
augmentation and shifts from generators seeded by (seed, k) alone, and the learning rate is a
function of the global step. So ``--resume`` after any epoch continues exactly as an
uninterrupted run would (tested).
"""

from __future__ import annotations

import contextlib
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from overlapmamba.core.errors import DatasetError
from overlapmamba.core.sensors.input import BEV_MODES, check_mode
from overlapmamba.train.augment import Augmenter
from overlapmamba.train.batches import BatchPlan, BatchSampler, PairIndex
from overlapmamba.train.calibrate import recalibrate_batchnorm
from overlapmamba.train.checkpoint import save_checkpoint
from overlapmamba.train.curves import plot_curves
from overlapmamba.train.errors import ConfigError, DivergedError
from overlapmamba.train.evaluate import describe, sequence_loops
from overlapmamba.train.health import HealthLog, batch_distances, epoch_line, json_safe
from overlapmamba.train.losses import pair_masks, with_copy_terms
from overlapmamba.train.mining import HardNegatives, mine
from overlapmamba.train.model import OverlapMamba, OverlapMambaConfig, channels_last
from overlapmamba.train.rangecache import cache_key, range_images
from overlapmamba.train.realscans import turn_check
from overlapmamba.train.runfolder import (
    RunLock,
    data_record,
    read_run,
    remove_stale_writes,
    same_data,
)
from overlapmamba.train.train_config import SCHEDULE, TrainConfig, load_config_file
from overlapmamba.train.train_inputs import (
    Images,
    batch_copies,
    model_profile,
    open_split,
    real_turn_scans,
    start_config,
    start_weights,
    training_input,
)
from overlapmamba.train.valsensors import open_renderings, selection_score, validation_fields

__all__ = ["TrainConfig", "load_config_file", "train"]


def train(
    data: list[Path],
    val: Path | None,
    out: Path,
    model_cfg: OverlapMambaConfig | None = None,
    train_cfg: TrainConfig | None = None,
    *,
    resume: bool = False,
    epochs: int | None = None,
    move_to: str | None = None,
    progress: bool = True,
) -> list[dict[str, Any]]:
    """Train (or resume) a run in ``out``; returns the per-epoch history.

    Resuming reads the model and training config and the data paths from ``out/last.pt``;
    ``epochs`` may extend the run, ``move_to`` move it to another device (cpu, cuda). The
    run folder is locked for the call (:class:`~overlapmamba.train.runfolder.RunLock`)."""
    with contextlib.ExitStack() as held:
        return _train(held, data, val, out, model_cfg, train_cfg, resume, epochs, move_to, progress)


def _train(
    held: contextlib.ExitStack,
    data: list[Path],
    val: Path | None,
    out: Path,
    model_cfg: OverlapMambaConfig | None,
    train_cfg: TrainConfig | None,
    resume: bool,
    epochs: int | None,
    move_to: str | None,
    progress: bool,
) -> list[dict[str, Any]]:
    out = Path(out)
    last = out / "last.pt"
    state, data, val, model_cfg, train_cfg = read_run(out, resume, data, val, model_cfg, train_cfg)
    held.enter_context(RunLock(out))  # released when train() returns or raises
    if resume:
        remove_stale_writes(out)  # a killed run's half-written checkpoints
    train_cfg = train_cfg or TrainConfig()
    if state is None and train_cfg.init:
        model_cfg = start_config(train_cfg, model_cfg)
    model_cfg = model_cfg or OverlapMambaConfig()
    if model_cfg.token_views != 1:
        raise ConfigError(
            f"token_views {model_cfg.token_views}: training takes one image a scan "
            "(token_views 1); a scan's views meet at export: "
            "`overlapmamba export RUN/best.pt --views V --meet tokens`"
        )
    if epochs is not None:
        train_cfg.epochs = epochs
    if move_to is not None:  # checked as a config's device is
        train_cfg = TrainConfig.from_dict({**train_cfg.to_dict(), "device": move_to})
    if train_cfg.device == "cuda" and not torch.cuda.is_available():
        raise ConfigError("--device cuda: no CUDA device is visible to PyTorch here")
    device = torch.device(train_cfg.device)
    profile = model_profile(model_cfg)

    if not data or val is None:
        raise ConfigError("training needs at least one training sequence and a validation one")
    seqs = [open_split(p, model_cfg, "training", train_cfg.any_sensor) for p in data]
    val_seq = open_split(val, model_cfg, "validation")
    if any(s.root.resolve() == val_seq.root.resolve() for s in seqs):
        raise ConfigError(f"{val} is both training and validation data")
    mode = check_mode(model_cfg.sensor_input)
    aligned = model_cfg.column_phase == "aligned"
    if aligned and train_cfg.turn_weight > 0:
        raise ConfigError(
            "turn_weight > 0 with column_phase aligned: a turned scan's aligned image is the "
            "plain one rolled by whole columns, which the circular network does not see, so "
            "the turn term has nothing to teach; set turn_weight 0"
        )
    val_input = training_input(profile, val_seq, mode)
    inputs = [training_input(profile, s, mode) for s in seqs]
    fingerprints = data_record(
        seqs,
        [
            cache_key(s, profile, sensor=inp, aligned=aligned)
            for s, inp in zip(seqs, inputs, strict=True)
        ],
        val_seq,
        cache_key(val_seq, profile, sensor=val_input, aligned=aligned),
    )
    images = Images(seqs, profile, progress, mode, aligned)
    val_images = range_images(
        val_seq, profile, progress=progress, sensor=val_input, aligned=aligned
    )
    val_gt = sequence_loops(val_seq, profile, progress=progress)
    if not val_gt.has_loop().any():
        raise DatasetError(
            f"{val}: the validation sequence has no loop closure, so F1max and Recall@1 "
            "would mean nothing; validate on a sequence with revisits (e.g. the val preset)"
        )
    renderings = open_renderings(train_cfg.val_sensors, val_seq, profile, progress, mode, aligned)
    trained_on = {s.root.resolve() for s in seqs}
    for rendering in renderings:
        if Path(rendering.path).resolve() in trained_on:
            raise ConfigError(f"{rendering.path} is both training data and a validation rendering")
    if renderings:  # runs without them keep their fingerprints (and --resume)
        fingerprints["val_sensors"] = [{"path": r.path, "key": r.key} for r in renderings]
    if state is not None and not same_data(state["train"]["data"], fingerprints):
        raise ConfigError("--resume with other data than the run was started on")
    pairs = PairIndex.from_sequences(seqs)
    sampler = BatchSampler(
        pairs,
        BatchPlan(
            train_cfg.batch_size,
            train_cfg.positive_threshold,
            train_cfg.revisit_fraction,
            negative_threshold=train_cfg.negative_threshold,
            positives=train_cfg.group_positives,
            negatives=train_cfg.group_negatives,
        ),
    )
    augment = Augmenter(train_cfg.augment_config(), profile, model_cfg.circular)
    if train_cfg.look_weight > 0 and not augment.looks and model_cfg.sensor_input not in BEV_MODES:
        raise ConfigError(
            "look_weight > 0 needs another sensor to see scans as: augment.sensor_like_names "
            f"names only the model's own ({profile.name})"
        )
    steps_per_epoch = sampler.steps(train_cfg.epoch_scans)

    torch.manual_seed(train_cfg.seed)
    model = OverlapMamba(model_cfg)
    if state is None and train_cfg.init:
        model.load_state_dict(start_weights(train_cfg, progress))
    model = channels_last(model.to(device))
    opt = torch.optim.Adam(model.parameters(), lr=train_cfg.lr)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda step: train_cfg.lr_factor(step, steps_per_epoch)
    )
    history: list[dict[str, Any]] = []
    best: dict[str, Any] = {"epoch": -1, "f1max": -1.0}
    if state is not None:
        model.load_state_dict(state["state_dict"])
        opt.load_state_dict(state["train"]["optimizer"])
        sched.load_state_dict(state["train"]["scheduler"])
        history, best = list(state["train"]["history"]), dict(state["train"]["best"])

    def payload(with_optimizer: bool, metrics: dict) -> dict[str, Any]:
        train_state: dict[str, Any] = {
            "config": train_cfg.to_dict(),
            "schedule": SCHEDULE,
            "epochs_done": history[-1]["epoch"] if history else 0,
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

    turns = real_turn_scans(train_cfg.real_path(), profile, progress, mode, aligned)

    start = (
        f"{train_cfg.init}'s weights"
        if train_cfg.init
        else "initial weights"
        + (
            ", batch norm recalibrated"
            if train_cfg.recalibrate_batches and not train_cfg.freeze_bn
            else ""
        )
    )

    def finish_epoch(entry: dict[str, Any]) -> None:
        """Record an epoch; write its checkpoint, best.pt, last.pt, metrics and curves."""
        nonlocal best
        history.append(entry)
        epoch, val_metrics = entry["epoch"], entry["val"]
        f1 = val_metrics["all"]["f1max"]
        score = f1
        if train_cfg.select_on == "sensors":
            score = selection_score(val_metrics, entry.get("val_sensors"))
        is_best = not math.isnan(score) and score > best.get("score", best["f1max"])
        if is_best:
            best = {"epoch": epoch, "f1max": f1}
            if train_cfg.select_on == "sensors":
                best |= {"score": score, "select_on": "sensors"}
        weights_only = payload(False, val_metrics)
        save_checkpoint(out / f"epoch-{epoch:03d}.pt", weights_only)
        if is_best:
            save_checkpoint(out / "best.pt", weights_only)
        save_checkpoint(last, payload(True, val_metrics))
        record = {
            "model_config": model_cfg.to_dict(),
            "train_config": train_cfg.to_dict(),
            "best": best,
            "history": history,
        }
        tmp = out / ".metrics.json.tmp"
        tmp.write_text(json.dumps(json_safe(record), indent=1, allow_nan=False) + "\n")
        tmp.replace(out / "metrics.json")
        plot_curves(history, out / "curves.png")
        if progress:
            tqdm.write(epoch_line(entry, start))

    if not history and (train_cfg.recalibrate_batches or train_cfg.init):
        # Epoch 0: the initial weights, validated like every epoch; fresh ones with
        # batch-norm statistics from training scans (they start as 0/1 and eval mode would
        # use them as such), unless batch norm is frozen.
        rng = np.random.default_rng([train_cfg.seed, 0])
        t0 = time.perf_counter()
        if train_cfg.recalibrate_batches and not train_cfg.freeze_bn:
            batches = [sampler.batch(rng) for _ in range(train_cfg.recalibrate_batches)]
            recalibrate_batchnorm(
                model,
                (
                    torch.from_numpy(images[i].astype(np.float32))[:, None].to(device)
                    for i in batches
                ),
            )
        calib_s = time.perf_counter() - t0
        finish_epoch(
            {
                "epoch": 0,
                "loss": None,
                "lr": 0.0,
                "calibrate_s": calib_s,
                **validation_fields(model, val_images, val_gt, renderings, str(device)),
                "real": turn_check(model, turns, str(device)),
            }
        )

    reference_spread = next(
        (h["health_log"][0]["spread"] for h in history if h.get("health_log")), math.nan
    )
    first = history[-1]["epoch"] + 1 if history else 1
    for epoch in range(first, train_cfg.epochs + 1):
        rng = np.random.default_rng([train_cfg.seed, epoch])
        torch.manual_seed(int(rng.integers(2**31)))  # the shifted branch's draws
        hard: HardNegatives | None = None
        mine_s = 0.0
        if train_cfg.hard_negatives > 0:
            tm = time.perf_counter()
            size = min(train_cfg.mine_pool, len(pairs))
            pool = np.sort(rng.choice(len(pairs), size=size, replace=False))
            pool_desc, _ = describe(model, images[pool], device=str(device))
            hard = mine(
                pool, pool_desc, lambda a: sampler.related[a], sampler.anchors, train_cfg.mine_top
            )
            mine_s = time.perf_counter() - tm
        band = train_cfg.band_share if train_cfg.band_on(epoch) else 0.0
        batches = sampler.epoch(rng, train_cfg.epoch_scans, hard, train_cfg.hard_negatives, band)
        loss_fn = train_cfg.loss_fn(epoch)
        model.train()
        if train_cfg.freeze_bn:
            for m in model.modules():
                if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
                    m.eval()
        health = HealthLog(
            every=train_cfg.log_every,
            step0=(epoch - 1) * steps_per_epoch,
            reference_spread=reference_spread,
        )
        warned = False
        t0 = time.perf_counter()
        data_s = 0.0
        bar = tqdm(batches, desc=f"epoch {epoch}/{train_cfg.epochs}", disable=not progress)
        for idx in bar:
            td = time.perf_counter()
            x = augment(images[idx], rng, images.native(idx))
            turn_k = train_cfg.turn_scans if train_cfg.turn_weight > 0 else 0
            look_k = train_cfg.look_scans if train_cfg.look_weight > 0 else 0
            turned, looked_at, looked = batch_copies(images, idx, rng, augment, turn_k, look_k)
            x = np.concatenate([x, turned, looked])
            data_s += time.perf_counter() - td
            desc, _ = model(torch.from_numpy(x)[:, None].to(device))
            B, T = len(idx), len(turned)
            desc, turned_d, looked_d = desc[:B], desc[B : B + T], desc[B + T :]
            overlap = torch.from_numpy(pairs.submatrix(idx)).to(device)
            out_loss = loss_fn(desc, overlap)
            value, d_turn, d_look = with_copy_terms(
                out_loss.value,
                desc,
                turned_d,
                looked_at,
                looked_d,
                (train_cfg.turn_weight, train_cfg.turn_allowance),
                train_cfg.look_weight,
            )
            if not math.isfinite(loss := value.item()):  # else NaN weights, epoch after epoch
                raise DivergedError(
                    f"epoch {epoch}, step {health.step0 + len(health.steps) + 1}: the loss is "
                    f"{loss} at learning rate {opt.param_groups[0]['lr']:.3g}; lower lr (or "
                    f"warm up longer). {last.name} still holds the last whole epoch"
                )
            opt.zero_grad(set_to_none=True)
            value.backward()
            opt.step()
            sched.step()
            masks = pair_masks(overlap, train_cfg.positive_threshold, train_cfg.negative_threshold)
            health.add(
                {
                    "loss": loss,
                    "d_turn": d_turn,
                    "d_look": d_look,
                    "active": out_loss.active,
                    "margin": out_loss.margin,
                    "band_active": out_loss.band_active,
                    **batch_distances(desc, *masks),
                }
            )
            reference_spread = health.reference_spread
            if health.collapsing() and not warned and progress:
                warned = True
                tqdm.write(
                    f"warning: epoch {epoch}: the descriptors' spread fell below a quarter of "
                    f"where the run started ({health.logged[-1]['spread']:.4g} against "
                    f"{reference_spread:.4g}): the run is collapsing"
                )
            r = health.recent()
            done = len(health.steps) * train_cfg.batch_size
            bar.set_postfix(
                loss=f"{r['loss']:.4f}",
                sep=f"{r['separation']:.2f}",
                spread=f"{r['spread']:.4f}",
                active=f"{r['active']:.0%}",
                scans_s=f"{done / (time.perf_counter() - t0):.2f}",
            )
        health.flush()  # the steps after the last full window
        train_s = time.perf_counter() - t0
        steps = health.steps
        finish_epoch(
            {
                "epoch": epoch,
                "loss": float(np.mean([s["loss"] for s in steps])),
                "step_losses": [s["loss"] for s in steps],
                "health": health.summary(),
                "health_log": health.logged,
                "collapsing": health.collapsing(),
                "lr": opt.param_groups[0]["lr"],
                "train_s": train_s,
                "data_s": data_s,
                "mining": None if hard is None else {**hard.stats, "mine_s": mine_s},
                "scans_per_s": len(steps) * train_cfg.batch_size / train_s,
                **validation_fields(model, val_images, val_gt, renderings, str(device)),
                "real": turn_check(model, turns, str(device)),
            }
        )
    return history
