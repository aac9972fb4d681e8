"""The model card's accuracy tables, from trained runs and the synthetic test preset.

    overlapmamba report [--runs runs] [--test data/synth/test] [--out reports/model]

- **Table I**: loop closure on the test preset (AUC, F1max, Recall@1, Recall@1 %), overall and
  for same- and reverse-direction revisits, for Scan Context and every trained network found
  among the runs (``default``, ``ot``, ``abl-full``, ``abl-ot``), one evaluation path for all
  (:mod:`overlapmamba.train.evaluate`); PR curves as PNG.
- **Table II** (ablation) and **Table III** (1 vs 2 blocks): the ``abl-*`` runs' validation
  metrics after their last epoch, with parameter counts and the measured forward time.
- **Table IV**: loss and validation F1max per epoch, ImTrihard vs triplet (and the default run).
- **Real scans**: ``eval_real`` on KITTI 00 (HDL-64) and on nuScenes (HDL-32E, hdl32 profile).

Everything lands in ``OUT/report.json``, ``OUT/tables.md`` and the PNGs beside them. Search
and extraction times (Table V) are a benchmark: ``benchmarks/place_recognition.py``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.metrics import LoopClosureResult
from overlapmamba.core.rerank import Rerank, with_score
from overlapmamba.train.checkpoint import load_model
from overlapmamba.train.evaluate import (
    RERANKED,
    SUBSETS,
    cross_session,
    describe_sequence,
    loop_closure,
    loop_errors,
    network_digest,
    require_loops,
    scan_contexts,
    scancontext_loop_closure,
    sequence_loops,
    summary,
)
from overlapmamba.train.health import strict_json
from overlapmamba.train.model import OverlapMamba, OverlapMambaConfig
from overlapmamba.train.presets import SHIPPED
from overlapmamba.train.report_tables import markdown
from overlapmamba.train.sessions import check_sessions

UNTRAINED_LABEL = (
    "OverlapMamba, untrained (default run's epoch 0: initial weights, BN recalibrated)"
)
NARROW_UNTRAINED_LABEL = (
    "OverlapMamba narrow, untrained (the narrow runs' common epoch 0: initial weights, BN "
    "recalibrated)"
)
# The narrow runs share seed, data and epoch 0; the row reads the first of them present.
# (narrow-hn-b64-long is not among them: its epoch 0 recalibrates on batches of 64.)
NARROW_RUNS = ("narrow-hn", "narrow-hn-long", "narrow-hn-aug", "narrow-hn-band", "narrow")
# Table I rows: label → (run folder, checkpoint), in display order; Scan Context comes first.
# A run's epoch-000.pt is its starting point: the seed's initial weights with batch-norm
# statistics recalibrated on training scans, before any gradient step. The row of the
# shipped run's best.pt (presets.SHIPPED) gets " (shipped)" appended.
NETWORKS = {
    UNTRAINED_LABEL: ("default", "epoch-000.pt"),
    NARROW_UNTRAINED_LABEL: ("narrow-hn", "epoch-000.pt"),
    "OT-style narrow, ablation budget": ("abl-ot", "best.pt"),
    "OverlapMamba narrow, ablation budget": ("abl-full", "best.pt"),
    "OT-style, default recipe": ("ot", "best.pt"),
    "OverlapMamba, default recipe on one training town": ("one-town", "best.pt"),
    "OverlapMamba, default recipe with augmentation": ("robust", "best.pt"),
    "OverlapMamba narrow, default recipe's wall time": ("narrow", "best.pt"),
    "OverlapMamba narrow, mined hard negatives": ("narrow-hn", "best.pt"),
    "OverlapMamba narrow, mined hard negatives, augmented": ("narrow-hn-aug", "best.pt"),
    "OverlapMamba narrow, mined hard negatives, trained longer": ("narrow-hn-long", "best.pt"),
    "OverlapMamba narrow, mined hard negatives, batch 64, trained longer": (
        "narrow-hn-b64-long",
        "best.pt",
    ),
    "OverlapMamba narrow, augmented, neighbours ranked from epoch 7": ("narrow-hn-band", "best.pt"),
    "OverlapMamba, default recipe": ("default", "best.pt"),
}


SHIPPED_SUFFIX = " (shipped)"


def row_label(label: str) -> str:
    """The Table I label as printed: the shipped run's row says so."""
    return label + SHIPPED_SUFFIX if NETWORKS[label] == (SHIPPED, "best.pt") else label


ABLATIONS = {
    label + seed: run + suffix
    for label, run in (
        ("full", "abl-full"),
        ("recipe before issue 20 (absolute margin 0.5, λ 0.1)", "abl-oldloss"),
        ("triplet instead of ImTrihard", "abl-triplet"),
        ("without shift", "abl-noshift"),
        ("without SPP", "abl-nospp"),
        ("non-circular scan", "abl-open"),
        ("2 blocks", "abl-2blocks"),
        ("OT-style (transformer mixer, no SPP)", "abl-ot"),
    )
    for seed, suffix in (("", ""), (" (seed 1)", "-s1"))
}
# The shipped encoder: Table I's shipped row and the real-scan checks read it when the run's
# best.pt is not under runs/ (a fresh machine has the .onnx, not the checkpoint).
SHIPPED_ONNX = Path(__file__).resolve().parents[2] / "models" / "overlapmamba-hdl64.onnx"
# The service's second stage where a model file carries none of its own
# (overlapmamba.core.rerank's defaults): the shipped row also appears with the second stage
# (label + evaluate.RERANKED) in Table I, across sessions and in the real-scan checks.
SERVICE_RERANK = Rerank()
REAL = {
    "kitti00": ("../shared/data/kitti00_0000-0100", None, 3.0),
    # nuScenes keyframes are ≈ 4.5 m apart at 2 Hz: a hit is the adjacent keyframe.
    "nuscenes-hdl32": ("../shared/data/nuscenes_scene0061", "hdl32", 6.0),  # its sensor
}


def service_rerank(model: Any) -> Rerank:
    """The second stage the service applies with ``model``: an exported file's calibrated
    ``rerank`` (chosen on val by ``benchmarks/rerank.py --write-calibration``, its score
    included), else the defaults (a checkpoint, or a file calibrated without one)."""
    meta = getattr(model, "meta", None)
    calibration = getattr(meta, "calibration", None) or {}
    entry = calibration.get("rerank")
    if meta is None or entry is None:
        return SERVICE_RERANK
    p = Rerank(int(entry.values["shortlist"]), float(entry.values["weight"]))
    return with_score(p, str(entry.values.get("score", "stage")), meta)


def shipped_model(runs: Path, onnx: Path | None = SHIPPED_ONNX) -> Path | None:
    """The shipped run's best.pt when it is under ``runs``, else the exported ``onnx`` when it
    exists, else None."""
    ckpt = runs / SHIPPED / "best.pt"
    if ckpt.is_file():
        return ckpt
    return onnx if onnx is not None and onnx.is_file() else None


def _networks(runs: Path, onnx: Path | None = SHIPPED_ONNX):
    """(label, model, profile) of every Table I network found among the runs, in order; the
    shipped row from ``onnx`` when its run's best.pt is absent (:func:`shipped_model`)."""
    for label, (run, name) in NETWORKS.items():
        if label == NARROW_UNTRAINED_LABEL:
            run = next((r for r in NARROW_RUNS if (runs / r / name).is_file()), run)
        ckpt: Path | None = runs / run / name
        if (run, name) == (SHIPPED, "best.pt"):
            ckpt = shipped_model(runs, onnx)
        if ckpt is not None and ckpt.is_file():
            model, profile, _ = load_model(ckpt)
            yield row_label(label), model, profile


def table_one(
    runs: Path, test: Path, progress: bool = True, onnx: Path | None = SHIPPED_ONNX
) -> tuple[dict, dict, dict]:
    """One test town → (metrics per method and subset, raw results for the PR plot, where
    each method goes wrong at its F1max threshold per subset: :func:`loop_errors`)."""
    seq = open_sequence(test)
    results: dict[str, dict[str, LoopClosureResult]] = {}
    by_weights: dict[str, dict[str, LoopClosureResult]] = {}  # one network, described once
    gt = None
    described: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for label, model, profile in _networks(runs, onnx):
        if gt is None:
            gt = sequence_loops(seq, profile, progress=progress)
            require_loops(gt, seq, "give a test town with revisits (--test)")
        key = network_digest(model)
        if key not in described:
            described[key] = describe_sequence(model, seq, profile, progress=progress)
            by_weights[key] = loop_closure(described[key][0], gt)
        results[label] = by_weights[key]
        if label.endswith(SHIPPED_SUFFIX):  # the service's answer: two stages
            if key + RERANKED not in by_weights:
                desc, yaw = described[key]
                by_weights[key + RERANKED] = loop_closure(desc, gt, yaw, service_rerank(model))
            results[label + RERANKED] = by_weights[key + RERANKED]
    if gt is None:
        raise FileNotFoundError(f"no trained run under {runs} (expected e.g. {runs}/default)")
    sc = scan_contexts(seq, progress=progress)
    results = {"Scan Context": scancontext_loop_closure(sc, gt), **results}
    errors = {k: loop_errors(v, gt, seq) for k, v in results.items()}
    return {k: summary(v) for k, v in results.items()}, results, errors


def mean_over_towns(towns: dict[str, dict]) -> dict[str, dict]:
    """Per method and subset: every rate averaged over the towns (NaN-aware), counts summed."""
    first = next(iter(towns.values()))
    out: dict[str, dict] = {}
    for method in first:
        out[method] = {}
        for sub in first[method]:
            rows = [t[method][sub] for t in towns.values() if method in t]
            out[method][sub] = {
                k: int(sum(r[k] for r in rows))
                if isinstance(rows[0][k], int)
                else float(np.nanmean([r[k] for r in rows]))
                for k in rows[0]
            }
    return out


def cross_sessions(
    runs: Path,
    database: Path,
    queries: Path,
    progress: bool = True,
    onnx: Path | None = SHIPPED_ONNX,
) -> dict:
    """AR@1/5/20 of a second session's scans against the first (:mod:`.sessions`), for
    Scan Context and every Table I network."""
    nets = list(_networks(runs, onnx))
    shipped = {label for label, _, _ in nets if label.endswith(SHIPPED_SUFFIX)}
    models = [model for label, model, _ in nets if label in shipped]
    cross = cross_session(
        nets,
        open_sequence(database),
        open_sequence(queries),
        rerank=service_rerank(models[0]) if models else SERVICE_RERANK,
        rerank_labels=shipped,
        progress=progress,
    )
    return {"Scan Context": cross["scan_context"], **cross["networks"]}


def plot_pr_methods(results: dict[str, dict[str, LoopClosureResult]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 4.4), dpi=110, sharey=True)
    for ax, sub in zip(axes, SUBSETS, strict=True):
        for label, res in results.items():
            r = res[sub]
            ax.plot(r.recall, r.precision, label=f"{label} ({r.f1max:.3f})")
        ax.set(xlabel="recall", xlim=(0, 1), ylim=(0, 1.02), title=f"test preset: {sub}")
        ax.grid(alpha=0.3)
        ax.legend(loc="lower left", fontsize=7, title="F1max", title_fontsize=7)
    axes[0].set_ylabel("precision")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


@torch.no_grad()
def forward_ms(model: OverlapMamba, reps: int = 5) -> float:
    """Median eval-mode forward time of one 64×900 image (B = 1)."""
    model.eval()
    x = torch.rand(1, 1, model.cfg.height, model.cfg.width) * 50
    model(x)
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        model(x)
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def run_rows(runs: Path, names: dict[str, str], timing: bool = True) -> dict[str, dict]:
    """Per run: config, parameters, forward ms, and validation metrics after the last epoch."""
    rows: dict[str, dict] = {}
    for label, run in names.items():
        f = runs / run / "metrics.json"
        if not f.is_file():
            continue
        rec = json.loads(f.read_text())
        last = rec["history"][-1]
        model = OverlapMamba(OverlapMambaConfig.from_dict(rec["model_config"]))
        rows[label] = {
            "run": run,
            "epochs": last["epoch"],
            "scans_seen": last["epoch"] * rec["train_config"]["epoch_scans"],
            "loss": rec["train_config"]["loss"],
            "params": sum(p.numel() for p in model.parameters()),
            "forward_ms": forward_ms(model) if timing else None,  # random weights
            "train_scans_per_s": float(
                np.mean([h["scans_per_s"] for h in rec["history"] if h["epoch"] > 0])
            ),
            "val": last["val"],
            "history": [
                {
                    "epoch": h["epoch"],
                    "loss": h["loss"],
                    "f1max": h["val"]["all"]["f1max"],
                    "recall@1": h["val"]["all"]["recall@1"],
                }
                for h in rec["history"]
            ],
        }
    return rows


def plot_epochs(rows: dict[str, dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.4), dpi=110)
    for label, row in rows.items():
        ep = [h["epoch"] for h in row["history"]]
        trained = [h for h in row["history"] if h["loss"] is not None]  # epoch 0 has no loss
        a.plot([h["epoch"] for h in trained], [h["loss"] for h in trained], "o-", label=label)
        b.plot(ep, [h["f1max"] for h in row["history"]], "o-", label=label)
    a.set(xlabel="epoch", ylabel="training loss (own scale per loss)", title="loss")
    b.set(
        xlabel="epoch (0: initial weights)",
        ylabel="val F1max",
        ylim=(0, 1),
        title="validation F1max",
    )
    for ax in (a, b):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def real_checks(runs: Path, onnx: Path | None = SHIPPED_ONNX) -> dict[str, Any]:
    from overlapmamba.train.realscans import eval_real

    ckpt = shipped_model(runs, onnx)
    if ckpt is None:
        return {}
    model, profile, _ = load_model(ckpt)
    out: dict[str, Any] = {}
    for name, (folder, sensor, radius) in REAL.items():
        if not Path(folder).is_dir():
            out[name] = {"skipped": f"{folder} is absent"}
            continue
        seq = open_sequence(folder, **({"sensor": sensor} if sensor else {}))
        out[name] = eval_real(model, profile, seq, hit_radius=radius, rerank=service_rerank(model))
    return out


def build_report(
    runs: Path,
    test: Path | list[Path],
    out: Path,
    progress: bool = True,
    *,
    sessions: tuple[Path, Path] | None = None,
    shipped_onnx: Path | None = SHIPPED_ONNX,
) -> dict[str, Any]:
    """Tables I–IV (Table I on every test town, and their mean), the cross-session table
    when ``sessions`` = (first session, second session) is given, and the real-scan checks.
    The shipped row is the shipped run's best.pt, or ``shipped_onnx`` without it (noted)."""
    out.mkdir(parents=True, exist_ok=True)
    tests = [test] if isinstance(test, Path) else list(test)
    if len({t.name for t in tests}) < len(tests):
        raise ValueError(
            f"test towns must have distinct folder names (they label the rows): {tests}"
        )
    if sessions:  # refuse a pair with nothing to recall before the long part
        check_sessions(open_sequence(sessions[0]), open_sequence(sessions[1]))
    towns: dict[str, dict] = {}
    errors: dict[str, dict] = {}
    for i, town in enumerate(tests):
        towns[town.name], results, errors[town.name] = table_one(runs, town, progress, shipped_onnx)
        if i == 0:
            plot_pr_methods(results, out / "pr_test.png")
    t1 = mean_over_towns(towns)
    ablation = run_rows(runs, ABLATIONS)
    epoch_runs = {"ImTrihard (abl-full)": "abl-full", "triplet (abl-triplet)": "abl-triplet"}
    epoch_runs["ImTrihard (default)"] = "default"
    epoch_runs["ImTrihard (narrow)"] = "narrow"
    epoch_runs["ImTrihard (narrow, mined negatives)"] = "narrow-hn"
    epoch_runs["ImTrihard (narrow, mined negatives, augmented)"] = "narrow-hn-aug"
    epoch_runs["ImTrihard (narrow, mined negatives, longer)"] = "narrow-hn-long"
    epoch_runs["ImTrihard (narrow, mined negatives, batch 64, longer)"] = "narrow-hn-b64-long"
    epoch_runs["ImTrihard (narrow, augmented, neighbours ranked from epoch 7)"] = "narrow-hn-band"
    epochs = run_rows(runs, epoch_runs, timing=False)
    if epochs:
        plot_epochs(epochs, out / "epochs.png")
    notes = []
    if (runs / SHIPPED / "best.pt").is_file() and not (runs / SHIPPED / "epoch-000.pt").is_file():
        notes.append(
            f"{runs}/{SHIPPED} has no epoch-000.pt (trained before epoch 0 existed, or with "
            "recalibrate_batches = 0): Table I has no untrained row for the shipped network"
        )
    shipped = shipped_model(runs, shipped_onnx)
    model: dict[str, Any] | None = None
    if shipped is not None and shipped.suffix == ".onnx":
        from overlapmamba.train.modelfile import read_metadata

        meta = read_metadata(shipped)
        views, phase = meta.views, meta.column_phase
        model = {"path": str(shipped), "model_id": meta.model_id, "views": views}
        model |= {"column_phase": phase, "sensor_input": meta.sensor_input}
        notes.append(
            f"{runs}/{SHIPPED}/best.pt is absent: the shipped row and the real-scan checks are "
            f"the exported encoder {shipped.name} (onnxruntime, its own scan and weight "
            f"storage; {views} sub-column view{'s' if views > 1 else ''} a scan"
            + (", aligned columns" if phase == "aligned" else "")
            + ")"
        )
    cross = None
    if sessions:
        first, second = sessions
        cross = {"database": str(first), "queries": str(second)} | cross_sessions(
            runs, first, second, progress=progress, onnx=shipped_onnx
        )
    report = {
        "notes": notes,
        "model": model,
        "test": [str(t) for t in tests],
        "table1": t1,
        "table1_towns": towns,
        "errors": errors,
        "cross_session": cross,
        "ablation": ablation,
        "epochs": epochs,
        "real": real_checks(runs, shipped_onnx),
        "torch_threads": torch.get_num_threads(),
    }
    # strict JSON: a town without revisits one way scores NaN, and -inf thresholds
    (out / "report.json").write_text(strict_json(report) + "\n")
    (out / "tables.md").write_text(markdown(report))
    return report
