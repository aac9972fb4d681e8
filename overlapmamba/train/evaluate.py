"""Evaluation: descriptors of a sequence, loop-closure metrics split by revisit direction,
and place recognition across sessions (the real-scan checks of ``eval-real`` are
:mod:`overlapmamba.train.realscans`).

Loop closure follows overlapmamba.core.metrics' protocol (OverlapTransformer's): query i searches
frames 0 … i − 101, top-1 by squared L2, PR over the top-1 distance; Recall@1% uses
N = max(1, ⌈1 % of the query's database⌉). Queries are split by the direction of their
best-overlap loop: same direction (|yaw| ≤ 90°) or reverse.
"""

from __future__ import annotations

import copy
import hashlib
import json
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from overlapmamba.core.anatomy import errors_at_f1max
from overlapmamba.core.datasets.base import Sequence
from overlapmamba.core.errors import DatasetError
from overlapmamba.core.metrics import (
    LoopClosureResult,
    evaluate_loop_closure,
    evaluate_retrieval,
    nearest,
)
from overlapmamba.core.overlap import (
    LoopGroundTruth,
    LoopParams,
    loop_ground_truth,
    loop_params,
    table_matches,
)
from overlapmamba.core.rerank import OFF, Rerank, two_stage
from overlapmamba.core.scancontext import ScanContextParams, scan_context
from overlapmamba.core.scancontext import retrieve as sc_retrieve
from overlapmamba.core.sensors import SensorProfile, get_profile
from overlapmamba.core.views import combine_views, unshift_features
from overlapmamba.train.checkpoint import (
    ExportedNetwork,
    Network,
    aligned_of,
    input_of,
    views_of,
)
from overlapmamba.train.model import OverlapMamba

SUBSETS = ("all", "same", "reverse")
# The label suffix of a network's two-stage rows (descriptor shortlist, yaw re-rank).
RERANKED = " + yaw re-rank"


def channels_last(model: Network) -> Network:
    """A copy of an OverlapMamba with its 4-d weights in channels-last layout; an exported
    network (onnxruntime's, which lays out its own tensors) as it is. Fed channels-last
    images, the backbone's convolutions run faster on CPU for the tests' small network and
    no slower for ``narrow`` and the reference width (benchmarks/describe_layout.py)."""
    if not isinstance(model, OverlapMamba):
        return model
    return copy.deepcopy(model).to(memory_format=torch.channels_last)  # type: ignore[call-overload]


@torch.no_grad()
def describe(
    model: Network,
    images: np.ndarray,
    *,
    batch: int | None = None,
    device: str = "cpu",
    offsets: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(N, H, W) range images → descriptors (N, D) float32, yaw features (N, C, W) float32.
    (N, V, H, W) are V sub-column views of each scan (:mod:`overlapmamba.core.views`): a scan's
    descriptor is then the unit-norm mean of its views', its yaw features view 0's; or, for a
    network with ``token_views``, what it makes of them together.

    Batches of 8 scans: the backbone's activations then stay in cache. On 2 CPU cores 8 took
    0.65× the time per scan of 32 (reference config) and 0.57× (the tests' small one), with
    bit-identical descriptors. On a GPU (``device`` not ``cpu``) the default is 64: a
    batch of 8 would leave it idle between launches.

    A PyTorch network runs as a channels-last copy (:func:`channels_last`), the original left
    as it was: the descriptors differ from the plain layout's by float rounding only.

    ``offsets`` (N,): the images' column offsets (aligned columns,
    :mod:`overlapmamba.core.views`); the yaw features are shifted back by them."""
    views = images.shape[1] if images.ndim == 4 else 1
    meet = model.cfg.token_views  # views the network averages itself (its tokens)
    if views != meet and meet > 1:
        raise ValueError(
            f"the network averages {meet} views of a scan itself (token_views); "
            f"got {views} image(s) a scan"
        )
    batch = batch or (8 if device == "cpu" else 64)
    was_training = model.training
    model.eval()
    net = channels_last(model)
    descs, yaws = [], []
    for s in range(0, len(images), batch):
        x = np.asarray(images[s : s + batch], dtype=np.float32)
        x_t = torch.from_numpy(x.reshape(-1, 1, *x.shape[-2:])).to(device)
        d, y = net(x_t.contiguous(memory_format=torch.channels_last))
        d, y = combine_views(d.cpu().numpy(), y.cpu().numpy(), views // meet)
        if offsets is not None:
            y = unshift_features(y, offsets[s : s + batch])
        descs.append(d)
        yaws.append(y)
    model.train(was_training)
    return np.concatenate(descs), np.concatenate(yaws)


def describe_sequence(
    model: Network, seq: Sequence, profile: SensorProfile, *, progress: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Every scan of ``seq`` described as the model describes a scan: its cached range
    images, from the sequence's sensor (:func:`~overlapmamba.train.checkpoint.input_of`), with as
    many sub-column views as the model takes (:func:`views_of`). An exported file that carries
    a map for the sequence's sensor (:mod:`overlapmamba.core.sensormaps`) gives its mapped
    descriptors, as the service answers them; the yaw features stay as the network gives them."""
    from overlapmamba.train.rangecache import range_images, range_offsets

    views, sensor, aligned = views_of(model), input_of(model, profile, seq), aligned_of(model)
    images = range_images(
        seq, profile, views=views, sensor=sensor, progress=progress, aligned=aligned
    )
    offsets = range_offsets(seq, profile, views=views, sensor=sensor) if aligned else None
    desc, yaw = describe(model, images, offsets=offsets)
    meta = getattr(model, "meta", None)  # an ExportedNetwork's file metadata
    sensor_map = None if meta is None else meta.sensor_maps.get(sensor.sensor.name)
    return (desc, yaw) if sensor_map is None else (sensor_map.apply(desc), yaw)


def sequence_loops(
    seq: Sequence, fallback: SensorProfile | None = None, progress: bool = False
) -> LoopGroundTruth:
    """The loop table of a sequence: the one its writer shipped (``ground_truth/loops.npz``,
    with that table's own radius and thresholds) when it matches the sequence, else the
    default protocol's table (computed once, then cached). Overlap is measured in the
    sequence's own sensor's profile (the one its table was written with), whatever model is
    evaluated; a sequence that names no sensor in ``fallback`` (the model's profile, as its
    scans are then projected), else KITTI's."""
    shipped = shipped_loops(seq, fallback)
    if shipped is not None and table_matches(shipped[0], shipped[1], seq):
        return shipped[0]
    return loop_ground_truth(seq, _loop_profile(seq, fallback), progress=progress)


def require_loops(gt: LoopGroundTruth, seq: Sequence, what_to_do: str) -> None:
    """Refuse a sequence no scan of which revisits a place seen earlier: every score of it
    would be NaN (tables of nothing, exit 0). ``what_to_do``: the caller's way out."""
    if not gt.has_loop().any():
        raise DatasetError(
            f"{seq.root} has no loop closure (no scan revisits a place seen earlier): "
            f"nothing to score; {what_to_do}"
        )


def _loop_profile(seq: Sequence, fallback: SensorProfile | None) -> SensorProfile:
    return get_profile(seq.sensor) if seq.sensor else fallback or get_profile("kitti-hdl64")


def shipped_loops(
    seq: Sequence, fallback: SensorProfile | None = None
) -> tuple[LoopGroundTruth, str] | None:
    """The loop table a sequence's writer shipped (``ground_truth/loops.npz``), and the
    fingerprint its scans give that table's parameters here (in the profile
    :func:`sequence_loops` measures overlap in): the table stands for the scans when the two
    agree. None without a table."""
    path = seq.root / "ground_truth" / "loops.npz"
    if not path.is_file():
        return None
    gt = LoopGroundTruth.load(path)
    params = loop_params(seq, _loop_profile(seq, fallback), LoopParams.of(gt.params))
    return gt, str(params["fingerprint"])


def loop_closure(
    desc: np.ndarray,
    gt: LoopGroundTruth,
    yaw: np.ndarray | None = None,
    rerank: Rerank = OFF,
) -> dict[str, LoopClosureResult]:
    """Loop-closure results over all queries and over same-/reverse-direction revisits.

    A subset keeps every query that is *not* a revisit of the other direction, so its
    precision still pays for false alarms on non-revisiting scans.

    With ``rerank`` on, retrieval has two stages (:mod:`overlapmamba.core.rerank`): each query's
    ``rerank.shortlist`` nearest descriptors are re-ordered by the score d² − weight · aligned
    yaw-feature correlation (``yaw``: (N, C, W)), and the top-1's score is what the PR curve
    thresholds.
    """
    if not rerank.on:
        return _by_direction(gt, lambda pos, **kw: evaluate_loop_closure(desc, pos, **kw))
    if yaw is None or len(yaw) != len(desc):
        raise ValueError("re-ranking needs the yaw features of every scan")
    retrieve = two_stage(desc, yaw, rerank)
    return _by_direction(gt, lambda pos, **kw: evaluate_retrieval(retrieve, len(desc), pos, **kw))


def cross_loop_closure(
    queries: np.ndarray, database: np.ndarray, gt: LoopGroundTruth
) -> dict[str, Any]:
    """Loop closure with query i's descriptor from one rendering and the database (frames
    0 … i − 101) from another of the same drive."""
    if queries.shape != database.shape:
        raise ValueError(
            f"renderings of one drive differ in shape: {queries.shape}, {database.shape}"
        )

    def retrieve(q: np.ndarray, db_size: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        allowed = np.arange(len(database))[None, :] < db_size[:, None]
        return nearest(queries[q], database, k, allowed=allowed)

    return summary(
        _by_direction(gt, lambda pos, **kw: evaluate_retrieval(retrieve, len(database), pos, **kw))
    )


def _by_direction(
    gt: LoopGroundTruth, score: Callable[..., LoopClosureResult]
) -> dict[str, LoopClosureResult]:
    """``score(positives, exclude_recent_frames=, query_mask=)`` over all, same and reverse."""
    positives = gt.positives()
    same, reverse = gt.direction_masks()
    exclude = int(gt.params.get("exclude_recent", 100))
    masks = {"all": None, "same": ~reverse, "reverse": ~same}
    return {
        name: score(positives, exclude_recent_frames=exclude, query_mask=m)
        for name, m in masks.items()
    }


def scan_contexts(
    seq: Sequence, params: ScanContextParams | None = None, progress: bool = False
) -> np.ndarray:
    """(N, rings, sectors) Scan Context of every frame of a sequence."""
    from tqdm.auto import tqdm

    p = params or ScanContextParams()
    frames = tqdm(range(len(seq)), desc="scan context", disable=not progress, unit="scan")
    return np.stack([scan_context(seq.points(i).xyz, p) for i in frames])


def scancontext_loop_closure(
    contexts: np.ndarray, gt: LoopGroundTruth, params: ScanContextParams | None = None
) -> dict[str, LoopClosureResult]:
    """:func:`loop_closure` for Scan Context: ring-key pre-selection, then shift distance."""
    p = params or ScanContextParams()

    def retrieve_sc(
        queries: np.ndarray, db_size: np.ndarray, k: int
    ) -> tuple[np.ndarray, np.ndarray]:
        return sc_retrieve(contexts, queries, db_size, k, p.candidates)

    return _by_direction(
        gt, lambda pos, **kw: evaluate_retrieval(retrieve_sc, len(contexts), pos, **kw)
    )


def summary(results: dict[str, LoopClosureResult]) -> dict[str, dict[str, Any]]:
    return {k: r.summary() for k, r in results.items()}


def loop_errors(
    results: dict[str, LoopClosureResult], gt: LoopGroundTruth, seq: Sequence
) -> dict[str, dict[str, Any]]:
    """Per subset, where the result goes wrong at its F1max threshold
    (:func:`overlapmamba.core.anatomy.errors_at_f1max`, positions from the sequence's poses)."""
    positions = np.asarray(seq.poses)[:, :3, 3]
    return {k: errors_at_f1max(r, gt, positions) for k, r in results.items()}


def plot_pr(results: dict[str, LoopClosureResult], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 4.2), dpi=120)
    for name, r in results.items():
        ax.plot(r.recall, r.precision, label=f"{name} (F1max {r.f1max:.3f}, AUC {r.auc:.3f})")
    ax.set(xlabel="recall", ylabel="precision", xlim=(0, 1), ylim=(0, 1.02), title=title)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def network_digest(model: Network) -> str:
    """sha256 of the architecture and every weight: the same network reached under two names
    (a run reported in two rows) is described once."""
    if isinstance(model, ExportedNetwork):  # its model id hashes its graph and weights
        return model.digest
    h = hashlib.sha256(json.dumps(model.cfg.to_dict(), sort_keys=True).encode())
    for name, tensor in model.state_dict().items():
        h.update(name.encode())
        h.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def cross_session(
    networks: list[tuple[str, Network, SensorProfile]],
    database: Sequence,
    queries: Sequence,
    *,
    rerank: Rerank = OFF,
    rerank_labels: set[str] | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """AR@1/5/20 of a second session's scans against the first's (:mod:`.sessions`):
    ``{"scan_context": …, "networks": {label: …}}`` for Scan Context and every (label,
    model, profile), on the same queries. A network listed twice is described once. With
    ``rerank`` on, every network in ``rerank_labels`` (None: all) also gets a row
    ``label + RERANKED`` for its two-stage answers (:mod:`overlapmamba.core.rerank`)."""
    from overlapmamba.train.sessions import (
        check_sessions,
        descriptor_recall,
        scan_context_recall,
        town_positions,
    )

    check_sessions(database, queries)
    pos_db, pos_q = town_positions(database), town_positions(queries)
    done: dict[str, dict[str, Any]] = {}
    described: dict[str, tuple[np.ndarray, ...]] = {}  # (desc db, yaw db, desc q, yaw q)
    by_label: dict[str, dict[str, Any]] = {}
    for label, model, profile in networks:
        key = network_digest(model)
        if key not in described:
            db = describe_sequence(model, database, profile, progress=progress)
            q = describe_sequence(model, queries, profile, progress=progress)
            described[key] = (*db, *q)
            done[key] = descriptor_recall(db[0], pos_db, q[0], pos_q)
        by_label[label] = done[key]
        if rerank.on and (rerank_labels is None or label in rerank_labels):
            if key + RERANKED not in done:
                d_db, y_db, d_q, y_q = described[key]
                done[key + RERANKED] = descriptor_recall(
                    d_db, pos_db, d_q, pos_q, yaw=(y_db, y_q), rerank=rerank
                )
            by_label[label + RERANKED] = done[key + RERANKED]
    sc_db = scan_contexts(database, progress=progress)
    sc_q = scan_contexts(queries, progress=progress)
    return {
        "scan_context": scan_context_recall(sc_db, pos_db, sc_q, pos_q),
        "networks": by_label,
    }


@dataclass
class SequenceEvaluation:
    """What ``overlapmamba eval`` reports: ``record`` (checkpoint, sequence, metrics by
    subset, and with a database the cross-session recall of the model and Scan Context),
    the PR ``results`` by subset (for :func:`plot_pr`), and the sequences' names and sizes."""

    record: dict[str, Any]
    results: dict[str, LoopClosureResult]
    sequence: tuple[str, int]
    database: tuple[str, int] | None = None


def evaluate_checkpoint(
    checkpoint: Path,
    sequence: Path,
    open_sequence: Callable[[Path], Sequence],
    *,
    database: Path | None = None,
    rerank: Rerank = OFF,
    scan_context: bool = False,
    progress: bool = False,
) -> SequenceEvaluation:
    """Loop closure of ``checkpoint`` on ``sequence`` (all, same and reverse direction) and,
    with a ``database`` (another session of the same town, of any sensor), place
    recognition of the sequence's scans against it. ``open_sequence`` opens a path (a folder
    or a recording). Each sequence is described as its own sensor's scans
    (:func:`~overlapmamba.train.checkpoint.input_of`). A query drive without a loop table (a
    session made only to be queried: ``pair_table="none"``) is evaluated across sessions
    only.

    With ``rerank`` on, the record also holds the two-stage answers (``metrics_reranked``,
    ``errors_reranked``, the cross-session ``model_reranked``) and ``results`` are those.
    With ``scan_context``, Scan Context's loop closure on the same protocol too
    (``metrics_scan_context``)."""
    from overlapmamba.train.checkpoint import load_model
    from overlapmamba.train.sessions import check_sessions

    model, profile, _ = load_model(checkpoint)
    seq = open_sequence(sequence)
    db = open_sequence(database) if database is not None else None
    if db is not None:  # refuse a wrong pair before the long part
        check_sessions(db, seq)
    record: dict[str, Any] = {
        "checkpoint": str(checkpoint),
        "sequence": str(sequence),
        "sensor": _input_record(model, profile, seq),
    }
    results: dict[str, LoopClosureResult] = {}
    if db is None or (seq.root / "ground_truth" / "loops.npz").is_file():
        gt = sequence_loops(seq, profile, progress=progress)
        if db is None:
            require_loops(
                gt,
                seq,
                "evaluate a sequence with revisits, or give --database for places across sessions",
            )
        desc, yaw = describe_sequence(model, seq, profile, progress=progress)
        results = loop_closure(desc, gt)
        record["metrics"] = summary(results)
        record["errors"] = loop_errors(results, gt, seq)
        if rerank.on:
            results = loop_closure(desc, gt, yaw, rerank)
            record["rerank"] = asdict(rerank)
            record["metrics_reranked"] = summary(results)
            record["errors_reranked"] = loop_errors(results, gt, seq)
        if scan_context:
            contexts = scan_contexts(seq, progress=progress)
            record["metrics_scan_context"] = summary(scancontext_loop_closure(contexts, gt))
    if db is None:
        return SequenceEvaluation(record, results, (seq.name, len(seq)))
    both = cross_session([("model", model, profile)], db, seq, rerank=rerank, progress=progress)
    record["database"] = str(database)
    record["database_sensor"] = _input_record(model, profile, db)
    record["cross_session"] = {
        "model": both["networks"]["model"],
        **({"model_reranked": both["networks"]["model" + RERANKED]} if rerank.on else {}),
        "scan_context": both["scan_context"],
    }
    return SequenceEvaluation(record, results, (seq.name, len(seq)), (db.name, len(db)))


def _input_record(model: Network, profile: SensorProfile, seq: Sequence) -> dict[str, str]:
    inp = input_of(model, profile, seq)
    return {"sensor": inp.sensor.name, "input": inp.kind}
