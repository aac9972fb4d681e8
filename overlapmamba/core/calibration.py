"""The thresholds calibrated for one model, carried in its file.

Four benchmarks choose them on the validation town, for the model they ran
(``benchmarks/rerank.py``, ``benchmarks/loop_threshold.py``, ``benchmarks/verify_threshold.py
--calibrate``, ``benchmarks/pose_covariance.py --calibrate``), and with
``--write-calibration`` write them into the model file's metadata
(``EncoderMetadata.calibration``; the graph and the model id stay as they are). The service
takes them from the model it loads: a threshold calibrated for one model never silently
serves another.

    section        values                               chosen by
    rerank         shortlist, weight, score              benchmarks/rerank.py
    loop_closure   accept_distance, max_score            benchmarks/loop_threshold.py
    verify         min_fitness, max_rmse_m, gate_distance,  benchmarks/verify_threshold.py
                   ambiguity_margin
    covariance     estimator, scale                     benchmarks/pose_covariance.py

Each section records what chose it (the command, the data, the date), so ``/readyz`` and
the start-up log can say where every threshold came from. A calibration written under the
old names (``k``, ``max_distance``: :mod:`overlapmamba.core.renamed`) is read under the new
ones, with a warning.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from overlapmamba.core.renamed import RENAMED, renamed

CALIBRATED: dict[str, tuple[str, ...]] = {
    "rerank": ("shortlist", "weight", "score"),
    "loop_closure": ("accept_distance", "max_score"),
    "verify": ("min_fitness", "max_rmse_m", "gate_distance", "ambiguity_margin"),
    "covariance": ("estimator", "scale"),
}


class Calibrated(BaseModel):
    """One section's thresholds, as a benchmark chose them."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    values: dict[str, float | int | str | None] = Field(min_length=1)
    chosen_by: str = Field(min_length=1, description="the command that chose them")
    data: str = Field(min_length=1, description="what they were chosen on")
    at: str = Field(description="UTC time, ISO 8601")


def check_calibration(calibration: dict[str, Any]) -> dict[str, Calibrated]:
    """Sections and fields known to :data:`CALIBRATED`, else a ValueError naming them."""
    out = {}
    for section, entry in calibration.items():
        if section not in CALIBRATED:
            raise ValueError(
                f"calibration section {section!r} is not known; allowed: {', '.join(CALIBRATED)}"
            )
        c = entry if isinstance(entry, Calibrated) else Calibrated.model_validate(entry)
        if set(c.values) & set(RENAMED.get(section, {})):
            c = c.model_copy(update={"values": renamed(c.values, section, stacklevel=4)})
        unknown = sorted(set(c.values) - set(CALIBRATED[section]))
        if unknown:
            raise ValueError(
                f"calibration {section}: {', '.join(unknown)} not calibrated here; allowed: "
                f"{', '.join(CALIBRATED[section])}"
            )
        out[section] = c
    return out


def calibrated(
    section: str, values: dict[str, float | int | str | None], chosen_by: str, data: str
) -> Calibrated:
    """A section's entry, stamped now (checked as :func:`check_calibration` does)."""
    entry = Calibrated(
        values=values, chosen_by=chosen_by, data=data, at=datetime.now(UTC).isoformat()
    )
    return check_calibration({section: entry})[section]
