"""Renderings of one drive share its pair table: the same places seen by several sensors.

``gen-data --preset P --sensor S --mount … --no-ground-truth`` renders the drive of preset P
again with another sensor or mounting: the seed, session, frame count, world, drive and
dynamics fix the poses, and the sensor and its mounting do not move them (every catalogue
sensor turns at 10 Hz; a mount's height and tilt change only z and the rotation). So frame i
of every rendering is the same place, and the pair table of the one rendering that has it
(``ground_truth/overlaps.npz``, the costly part of a town) labels every pair across
renderings too: overlap((a, i), (b, j)) = table(i, j), and the same frame in two renderings
overlaps fully. Without that, training would take the same place seen by another sensor for
a negative (a pair absent from the table is one) and for its favourite mined look-alike.

A rendering joins its drive only when its scans lie where the reference's do (in the town's
frame, ``world_from_sequence``); sequences without a manifest are drives of their own.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from overlapmamba.core.datasets.base import Sequence
from overlapmamba.core.errors import DatasetError
from overlapmamba.train.sessions import town_positions

# what fixes a drive's poses in the generator's config (the sensor and mounting do not)
DRIVE_KEYS = ("seed", "session", "frames", "world", "drive", "dynamics")
SAME_PLACE_M = 0.05  # a rendering's scans lie within this of the reference's (town frame)


def drive_key(seq: Sequence) -> str:
    """The drive a sequence renders: its generator config's pose-fixing fields, or its own
    folder when it has no manifest."""
    path = seq.root / "manifest.json"
    if not path.is_file():
        return f"folder:{seq.root.resolve()}"
    cfg = json.loads(path.read_text()).get("config", {})
    return json.dumps({k: cfg.get(k) for k in DRIVE_KEYS}, sort_keys=True, default=str)


@dataclass(frozen=True)
class Drive:
    """The sequences (by position in the training list) that render one drive, and the one
    whose pair table labels them all."""

    members: tuple[int, ...]
    reference: int


def group_drives(seqs: list[Sequence], has_table: Callable[[Sequence], bool]) -> list[Drive]:
    """The drives of ``seqs`` in first-seen order. Refused: a drive none of whose renderings
    has a pair table, and a rendering whose frames differ in number or place from its
    reference's."""
    groups: dict[str, list[int]] = {}
    for k, seq in enumerate(seqs):
        groups.setdefault(drive_key(seq), []).append(k)
    drives = []
    for members in groups.values():
        ref = next((k for k in members if has_table(seqs[k])), None)
        if ref is None:
            names = ", ".join(str(seqs[k].root) for k in members)
            raise DatasetError(
                f"{names}: no ground_truth/overlaps.npz in any rendering of this drive; "
                "training needs the pairwise overlap table that `overlapmamba gen-data` writes "
                "beside a synthetic sequence (render one of the drive without "
                "--no-ground-truth)"
            )
        if len(members) > 1:
            xy = town_positions(seqs[ref])[:, :2]
            for k in members:
                if len(seqs[k]) != len(seqs[ref]):
                    raise DatasetError(
                        f"{seqs[k].root} has {len(seqs[k])} scans where {seqs[ref].root}, "
                        f"the same drive, has {len(seqs[ref])}: not a rendering of it"
                    )
                gap = float(np.abs(town_positions(seqs[k])[:, :2] - xy).max())
                if gap > SAME_PLACE_M:
                    raise DatasetError(
                        f"{seqs[k].root}'s scans lie up to {gap:.2f} m from {seqs[ref].root}'s "
                        f"(allowed {SAME_PLACE_M} m): not a rendering of the same drive"
                    )
        drives.append(Drive(tuple(members), ref))
    return drives


def drive_pairs(
    drive: Drive,
    table: dict[str, np.ndarray],
    offsets: np.ndarray,
    frames: int,
) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """(rows, cols, values) over global scan indices: the reference's table for every pair
    of renderings, both orders, and overlap 1 for one frame in two renderings."""
    q, r = table["query"], table["reference"]
    o = table["overlap"].astype(np.float32)
    rows: list[np.ndarray] = []
    cols: list[np.ndarray] = []
    vals: list[np.ndarray] = []
    same = np.arange(frames)
    for a in drive.members:
        for b in drive.members:
            rows += [q + offsets[a], r + offsets[a]]
            cols += [r + offsets[b], q + offsets[b]]
            vals += [o, o]
            if a != b:
                rows.append(same + offsets[a])
                cols.append(same + offsets[b])
                vals.append(np.ones(frames, np.float32))
    return rows, cols, vals
