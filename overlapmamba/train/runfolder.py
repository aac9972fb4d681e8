"""A run folder (``runs/NAME``): the lock that keeps one run in it, what a resumed run reads
back from its ``last.pt``, and the partial files a killed run left."""

from __future__ import annotations

import errno
import logging
import os
from pathlib import Path
from typing import Any

from overlapmamba.train.checkpoint import read_checkpoint
from overlapmamba.train.errors import ConfigError
from overlapmamba.train.model import OverlapMambaConfig
from overlapmamba.train.train_config import SCHEDULE, TrainConfig

log = logging.getLogger(__name__)


class RunLock:
    """An exclusive lock on a run folder (``out/.lock``), held until :meth:`close` (or the
    end of a ``with``, or the object is gone): a second run into the same ``--out`` would
    interleave its checkpoints with this one's (best.pt of one seed, last.pt and metrics of
    the other)."""

    def __init__(self, out: Path) -> None:
        import fcntl

        out.mkdir(parents=True, exist_ok=True)
        self.fd: int | None = os.open(out / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            if err.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):  # a mount without locks
                log.warning(
                    "%s cannot be locked (%s): two runs into it are not prevented", out, err
                )
                return
            self.close()
            raise ConfigError(
                f"{out} is in use by another training run; wait for it or choose another --out"
            ) from None

    def close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)  # and with it the lock
            self.fd = None

    def __enter__(self) -> RunLock:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def __del__(self) -> None:
        self.close()


def remove_stale_writes(folder: Path) -> list[Path]:
    """Temporary checkpoint files a killed run left in ``folder`` (``.NAME.tmpPID``), removed
    (they are never read: a checkpoint is renamed in only once whole)."""
    stale = [p for p in folder.glob(".*.pt.tmp*") if p.is_file()]
    for p in stale:
        p.unlink(missing_ok=True)
    return stale


def read_run(
    out: Path,
    resume: bool,
    data: list[Path],
    val: Path | None,
    model_cfg: OverlapMambaConfig | None,
    train_cfg: TrainConfig | None,
) -> tuple[dict[str, Any] | None, list[Path], Path | None, Any, Any]:
    """What a run in ``out`` starts from: with ``resume``, its ``last.pt`` (checked to be
    resumable) and the data and configs recorded there, else the ones given (refused where
    ``out`` already holds a run, or is a file). → (state or None, data, val, model config,
    training config)."""
    last = out / "last.pt"
    state: dict[str, Any] | None = None
    if resume:
        if not last.is_file():
            raise ConfigError(f"nothing to resume: {last} does not exist")
        state = read_checkpoint(last)
        if state["train"].get("schedule") != SCHEDULE:
            raise ConfigError(
                f"{last} was written by an older trainer (learning rate stepped per epoch, no "
                "warm-up); it cannot resume exactly here: start a new run"
            )
        recorded = state["train"]["data"]
        data = data or [Path(d["path"]) for d in recorded["train"]]
        val = val or Path(recorded["val"]["path"])
        model_cfg = OverlapMambaConfig.from_dict(state["model_config"])
        train_cfg = TrainConfig.from_dict(state["train"]["config"])
    elif last.is_file():
        raise ConfigError(f"{out} already holds a run; pass --resume or choose a new --out")
    if out.exists() and not out.is_dir():  # found at the first checkpoint, after the set-up
        raise ConfigError(f"--out {out} is a file; a run is written into a folder")
    return state, data, val, model_cfg, train_cfg


def data_record(seqs: list[Any], keys: list[str], val_seq: Any, val_key: str) -> dict[str, Any]:
    """What a run records of its data (``last.pt``'s ``train.data``): each training
    sequence's and the validation one's folder, resolved (a resume from another working
    directory finds them), with its range-image cache key."""
    return {
        "train": [
            {"path": str(s.root.resolve()), "key": k} for s, k in zip(seqs, keys, strict=True)
        ],
        "val": {"path": str(val_seq.root.resolve()), "key": val_key},
    }


def same_data(recorded: Any, now: Any) -> bool:
    """Whether a run's recorded data is the data given now, paths compared resolved: runs
    before 2026-12-04 recorded them as given (data/synth/…), since then absolute."""
    return bool(_resolved(recorded) == _resolved(now))


def _resolved(data: Any) -> Any:
    if isinstance(data, dict):
        return {k: str(Path(v).resolve()) if k == "path" else _resolved(v) for k, v in data.items()}
    if isinstance(data, list):
        return [_resolved(v) for v in data]
    return data
