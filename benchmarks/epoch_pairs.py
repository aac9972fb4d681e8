"""Which epoch of a run to keep, chosen on the calibration town's pairs across sensors.

A run's trainer keeps as ``best.pt`` the epoch of best validation score (``val``, or the
mean over its sensor renderings: ``select_on``). Across sensors that score has ranked runs
the other way from the test town, while the calibration town's pairs ranked them as the test
town does (Training › "From scratch on two CPU cores"). This measures the same thing epoch
by epoch: every ``epoch-NNN.pt`` of ``--run`` is exported as ``overlapmamba export`` writes
it (one view, int8, into ``--scratch``), and its descriptor alone is asked, for every
ordered pair among the issue's five sensors on the calibration town ``cal-x00`` (queries of
a second drive against a first drive's map, ``benchmarks/across_pairs.py``'s ``val``), for
the top-1 answer within 5 m (AR@1). The epoch of best mean AR@1 over the 25 pairs is chosen
(ties to the earlier epoch), beside the trainer's own choice.

With ``--test`` every epoch is also measured on the sensor test town's 25 pairs, to see how
well each score ranks the epochs as the test town does (Spearman's rank correlation over the
epochs, the trainer's score and the calibration pairs' each against the test town's mean
AR@1 across sensors). That is a check of the two ways to choose, never a way to choose: the
test town is reported on only.

    python benchmarks/epoch_pairs.py --run runs/NAME [--test] \\
        --out reports/model/epoch-pairs-NAME.json

≈ 1 min an epoch on 2 cores (5,000 scans), ≈ 3 min with ``--test`` (25,000 scans): ≈ 32 min
for a run of 11 epochs.

A run continued in a copy of its folder (``overlapmamba train --out COPY --resume --epochs
N``) shares its first epochs' checkpoints with the original: ``--reuse REPORT`` (that
original's epoch-pairs report) takes the rows of those epochs from it instead of measuring
them again, each only where the two folders' ``epoch-NNN.pt`` are the same bytes and the
report measured every split asked for; the rest are measured.
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from across_pairs import SENSORS, Drives, split_towns
from reports_kit import REPORTS, ROOT, shown_path, write_report
from rich.console import Console

from overlapmamba.core.datasets import open_sequence
from overlapmamba.service.encoder import Encoder
from overlapmamba.train.sessions import check_sessions, descriptor_recall, town_positions
from overlapmamba.train.valsensors import selection_score


def trainer_scores(run: Path) -> tuple[dict[int, float], int]:
    """Each epoch's score as the run's trainer chose by it, and the epoch it kept."""
    m = json.loads((run / "metrics.json").read_text())
    by_sensors = m["train_config"].get("select_on") == "sensors"
    scores = {
        h["epoch"]: (
            selection_score(h["val"], h.get("val_sensors"))
            if by_sensors
            else h["val"]["all"]["f1max"]
        )
        for h in m["history"]
    }
    return scores, int(m["best"]["epoch"])


def epoch_files(run: Path) -> dict[int, Path]:
    found = {int(p.stem.split("-")[1]): p for p in sorted(run.glob("epoch-[0-9][0-9][0-9].pt"))}
    if not found:
        raise SystemExit(f"{run}: no epoch-NNN.pt checkpoints (a run's folder, as train writes)")
    return found


def _digest(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


FRAMES = 500  # scans a val drive, the default (reports before it was recorded used it)


def reusable_rows(
    report: Path, files: dict[int, Path], splits: tuple[str, ...], frames: int = FRAMES
) -> dict[int, dict[str, Any]]:
    """The rows of ``report`` (an epoch-pairs report of another run folder) that stand for
    this run's epochs: those whose checkpoint in the report's run folder has the same bytes
    as this run's and that measured every split in ``splits``. A report whose run folder is
    gone is refused by name (nothing would show the checkpoints are the same), and so is one
    measured on another number of scans a drive (reports before ``frames`` was recorded
    used the default, 500)."""
    r = json.loads(report.read_text())
    theirs_frames = r.get("frames", FRAMES)
    if theirs_frames != frames:
        raise SystemExit(
            f"--reuse {report}: measured on {theirs_frames} scans a drive, this run on "
            f"{frames} (--frames): its rows would not compare"
        )
    source = Path(r["run"])
    source = source if source.is_absolute() else ROOT / source
    if not source.is_dir():
        raise SystemExit(f"--reuse {report}: its run folder {source} is not here to compare")
    theirs = {int(p.stem.split("-")[1]): p for p in source.glob("epoch-[0-9][0-9][0-9].pt")}
    rows = {}
    for row in r["epochs"]:
        epoch = row["epoch"]
        if epoch not in files or epoch not in theirs or not all(s in row for s in splits):
            continue
        if _digest(files[epoch]) == _digest(theirs[epoch]):
            rows[epoch] = {k: row[k] for k in ("epoch", "trainer_score", *splits)}
    return rows


def export(checkpoint: Path, out: Path) -> None:
    """The checkpoint as ``overlapmamba export`` writes it by default."""
    out.parent.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "overlapmamba", "export", str(checkpoint), "--out", str(out)]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"export of {checkpoint} failed:\n{done.stdout}\n{done.stderr}")


def pair_ar1(enc: Encoder, scratch: Path, towns: dict[tuple[str, int], Path]) -> dict[str, Any]:
    """AR@1 of the file's descriptor on every ordered pair of ``towns``, and its means."""
    drives = Drives(enc, scratch)
    rows = []
    for m, q in itertools.product(SENSORS, SENSORS):
        db_town, q_town = towns[(m, 0)], towns[(q, 1)]
        db_seq, q_seq = open_sequence(db_town), open_sequence(q_town)
        check_sessions(db_seq, q_seq)
        pos_db, pos_q = town_positions(db_seq), town_positions(q_seq)
        r = descriptor_recall(drives.model(db_town)[0], pos_db, drives.model(q_town)[0], pos_q)
        rows.append({"queries": q, "map": m, "ar@1": float(r["ar@1"])})
    across = [r["ar@1"] for r in rows if r["queries"] != r["map"]]
    return {
        "mean_ar@1": float(np.mean([r["ar@1"] for r in rows])),
        "across_mean_ar@1": float(np.mean(across)),
        "across_min_ar@1": float(np.min(across)),
        "pairs": rows,
    }


def spearman(a: list[float], b: list[float]) -> float:
    """Spearman's rank correlation of two equally long lists (average ranks for ties)."""

    def ranks(x: list[float]) -> np.ndarray:
        v = np.asarray(x, dtype=float)
        order = v.argsort(kind="stable")
        r = np.empty(len(v))
        r[order] = np.arange(len(v), dtype=float)
        for value in np.unique(v):  # ties share their mean rank
            tied = v == value
            r[tied] = r[tied].mean()
        return r

    ra, rb = ranks(a), ranks(b)
    if ra.std() == 0 or rb.std() == 0:
        return float("nan")
    return float(np.corrcoef(ra, rb)[0, 1])


def choose(rows: list[dict[str, Any]]) -> int:
    """The epoch of best mean AR@1 over the calibration pairs; ties to the earlier one."""
    return int(max(rows, key=lambda r: (r["val"]["mean_ar@1"], -r["epoch"]))["epoch"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", type=Path, required=True, help="a training run's folder")
    ap.add_argument("--test", action="store_true", help="also measure every epoch on test")
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "synth")
    ap.add_argument("--scratch", type=Path, default=ROOT / "data" / "common-beams")
    ap.add_argument("--frames", type=int, default=FRAMES, help="scans a val drive")
    ap.add_argument("--out", type=Path, default=None, help="default reports/model/epoch-pairs-RUN")
    ap.add_argument(
        "--reuse",
        type=Path,
        default=None,
        help="an epoch-pairs report of the run this one continues: its rows of the same "
        "checkpoints are taken, not measured again",
    )
    args = ap.parse_args()
    files = epoch_files(args.run)
    out = args.out or REPORTS / "model" / f"epoch-pairs-{args.run.name}.json"
    console = Console(width=120)
    t0 = time.perf_counter()
    splits = ("val", "test") if args.test else ("val",)
    towns = {s: split_towns(s, args.data, args.scratch, args.frames) for s in splits}
    scores, trainer_best = trainer_scores(args.run)
    reused = reusable_rows(args.reuse, files, splits, args.frames) if args.reuse else {}
    rows = []
    for epoch, ckpt in files.items():
        if epoch in reused:
            rows.append({**reused[epoch], "trainer_score": scores.get(epoch)})
            continue
        onnx = args.scratch / "epochs" / f"{args.run.name}-{epoch:03d}.onnx"
        export(ckpt, onnx)
        row: dict[str, Any] = {"epoch": epoch, "trainer_score": scores.get(epoch)}
        for split in splits:
            row[split] = pair_ar1(Encoder(onnx), args.scratch, towns[split])
        onnx.unlink()
        rows.append(row)
        console.print(
            f"epoch {epoch:3d}: trainer {row['trainer_score']:.3f} | "
            + " | ".join(
                f"{s} mean {row[s]['mean_ar@1']:.3f}, across {row[s]['across_mean_ar@1']:.3f}"
                for s in splits
            )
            + f" ({time.perf_counter() - t0:.0f} s)",
            highlight=False,
        )
    chosen = choose(rows)
    record: dict[str, Any] = {
        "run": shown_path(args.run),
        "sensors": list(SENSORS),
        "chosen_by": "mean AR@1 of the descriptor over the 25 cal-x00 pairs",
        "radius_m": 5.0,
        "frames": args.frames,
        "trainer_best": trainer_best,
        "chosen": chosen,
        "epochs": rows,
    }
    if reused:
        record["reused"] = {"report": shown_path(args.reuse), "epochs": sorted(reused)}
    if args.test:
        target = [r["test"]["across_mean_ar@1"] for r in rows]
        record["rank_correlation_with_test_across"] = {
            "trainer_score": spearman([r["trainer_score"] for r in rows], target),
            "pairs_mean_ar@1": spearman([r["val"]["mean_ar@1"] for r in rows], target),
        }
    record["seconds"] = round(time.perf_counter() - t0, 1)
    console.print({k: v for k, v in record.items() if k != "epochs"})
    write_report(out, record)
    console.print(f"wrote {out}")


if __name__ == "__main__":
    main()
