"""Which rows of the range image a model file's descriptor depends on, measured on the file as
the service runs it (onnxruntime, its views).

A real KITTI 00 scan is projected as the service projects it; then, one row at a time, that
row is emptied (``empty_value`` in every view) and the scan described again. A row reaches
the descriptor when the descriptor changes by more than ``ROUNDING`` (1e-5: batches of
other sizes round differently by about 1e-7; a row the network never reads changes nothing
beyond that, a row it reads changes the descriptor by 1e-3 or more on this scan). Reported per
file: the rows that reach the descriptor and the yaw features, the elevations they cover
(the model's profile), the largest change a row makes, and for every catalogue sensor how
many of its beams the rows that count show (as ``overlapmamba.core.sensors.input`` projects
its scans, ``elevation`` mode).

The reference backbone (``OverlapMambaConfig.backbone = "reference"``) finishes the image's
height with strided 1 × 1 convolutions that keep only their first row; ``all-rows`` does not
(``overlapmamba.train.model._backbone``).

    python benchmarks/receptive_rows.py [--model FILE ...] [--frame 0]

Writes reports/model/receptive-rows.json. A few seconds a file.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np
from reports_kit import REPORTS, ROOT, shown_path, write_report
from rich.console import Console

from overlapmamba.core.datasets import open_sequence
from overlapmamba.core.sensors.beams import row_beams
from overlapmamba.core.sensors.catalogue import CATALOGUE
from overlapmamba.core.sensors.profile import SensorProfile
from overlapmamba.service.encoder import Encoder

KITTI = ROOT.parent / "shared" / "data" / "kitti00_0000-0100"
MODELS = (
    ROOT / "models" / "overlapmamba-hdl64.onnx",
    ROOT / "models" / "overlapmamba-hdl64-tokens.onnx",
)


ROUNDING = 1e-5


def row_effects(
    enc: Encoder, views: np.ndarray, offset: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """(H,) largest absolute change of the descriptor and of the yaw features when each row
    of ``views`` ((V, H, W) at column ``offset``, from ``Encoder.project_offset``) is
    emptied in every view."""
    empty = np.float32(enc.meta.profile.empty_value)
    H = views.shape[1]
    batch = np.repeat(views[None], H, axis=0)  # (H, V, H, W): row r emptied in scan r
    for r in range(H):
        batch[r, :, r] = empty
    d0, y0 = enc.encode(views[None], np.array([offset]))
    desc, yaw = [], []
    for lo in range(0, H, 8):
        d, y = enc.encode(batch[lo : lo + 8], np.full(len(batch[lo : lo + 8]), offset))
        desc.append(np.abs(d - d0).max(axis=1))
        yaw.append(np.abs(y - y0).reshape(len(y), -1).max(axis=1))
    return np.concatenate(desc), np.concatenate(yaw)


def spans(rows: np.ndarray) -> list[list[int]]:
    """Sorted row indices → [first, last] runs."""
    out: list[list[int]] = []
    for r in rows.tolist():
        if out and r == out[-1][1] + 1:
            out[-1][1] = r
        else:
            out.append([r, r])
    return out


def row_elevations(profile: SensorProfile) -> np.ndarray:
    """(H,) the elevation of each row's centre, degrees."""
    pitch = (profile.fov_up_deg - profile.fov_down_deg) / profile.height
    return profile.fov_up_deg - (np.arange(profile.height) + 0.5) * pitch


def measure(path: Path, frame: int) -> dict[str, Any]:
    enc = Encoder(path, intra_op_threads=2)
    profile = enc.meta.profile
    views, offset = enc.project_offset(open_sequence(KITTI).points(frame))
    desc, yaw = row_effects(enc, views, offset)
    seen = np.flatnonzero(desc > ROUNDING)
    unseen = np.flatnonzero(desc <= ROUNDING)
    el = row_elevations(profile)
    sensors = {}
    for name, sensor in CATALOGUE.items():
        rows = row_beams(profile, sensor, "elevation")
        shown = rows[seen]
        sensors[name] = {
            "beams": sensor.beams,
            "beams_in_image": int(np.unique(rows[rows >= 0]).size),
            "beams_reaching_descriptor": int(np.unique(shown[shown >= 0]).size),
        }
    return {
        "model": shown_path(path),
        "model_id": enc.meta.model_id,
        "views": enc.meta.views,
        "backbone": enc.meta.network.get("backbone", "reference"),
        "rows": profile.height,
        "rows_reaching_descriptor": int(seen.size),
        "descriptor_rows": spans(seen),
        "yaw_feature_rows": spans(np.flatnonzero(yaw > ROUNDING)),
        "smallest_change_of_a_row_reaching_it": float(desc[seen].min()) if seen.size else None,
        "largest_change_of_a_row_not_reaching_it": float(desc[unseen].max())
        if unseen.size
        else None,
        "elevation_deg_reaching_descriptor": (
            [round(float(el[seen[0]]), 2), round(float(el[seen[-1]]), 2)] if seen.size else []
        ),
        "image_elevation_deg": [profile.fov_up_deg, profile.fov_down_deg],
        "largest_change_per_row": [float(f"{x:.3g}") for x in desc],
        "sensors": sensors,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, action="append", help="model file (repeatable)")
    ap.add_argument("--frame", type=int, default=0, help="the KITTI 00 scan (0–100)")
    ap.add_argument("--out", type=Path, default=REPORTS / "model" / "receptive-rows.json")
    args = ap.parse_args()
    console = Console()
    models = [m.resolve() for m in args.model] if args.model else list(MODELS)
    measured = [measure(m, args.frame) for m in models]
    record = {"rounding": ROUNDING, "scan": f"kitti00/{args.frame:06d}", "models": measured}
    for m in measured:
        console.print(
            f"{m['model']} ({m['model_id']}): {m['rows_reaching_descriptor']} of {m['rows']} rows "
            f"reach the descriptor, rows {m['descriptor_rows']}, elevation "
            f"{m['elevation_deg_reaching_descriptor']}°"
        )
    write_report(args.out, record)
    console.print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
