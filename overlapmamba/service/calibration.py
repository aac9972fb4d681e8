"""The thresholds a service answers with: its model's calibration, unless a setting says
otherwise.

Each calibrated threshold (:data:`overlapmamba.core.calibration.CALIBRATED`) comes from, in order:

1. a setting given explicitly (a TOML file, an ``OVERLAPMAMBA_*`` variable): the operator's;
2. the model file's own calibration (``EncoderMetadata.calibration``), written by the
   benchmark that chose it on the validation town;
3. the settings' defaults, which were calibrated for the shipped model: used for another
   model only with a warning, since they were not chosen for it.

:func:`resolve` returns the settings the service runs with and where each threshold came
from; the start-up log and ``/readyz`` show it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from overlapmamba.core.calibration import CALIBRATED
from overlapmamba.core.modelmeta import EncoderMetadata
from overlapmamba.service.ranking import rerank_params
from overlapmamba.service.settings import Settings

log = logging.getLogger("overlapmamba.service")


@dataclass(frozen=True)
class Threshold:
    value: Any
    source: str  # "setting", "model" or "default"
    chosen_by: str | None = None  # the benchmark, for "model"

    def public(self) -> dict[str, Any]:
        out = {"value": self.value, "source": self.source}
        if self.chosen_by:
            out["chosen_by"] = self.chosen_by
        return out


def resolve(settings: Settings, meta: EncoderMetadata) -> tuple[Settings, dict[str, Threshold]]:
    """``settings`` with every threshold the model calibrated and no setting overrides taken
    from the model; and, per ``section.field``, the value and its source."""
    updates: dict[str, dict[str, Any]] = {}
    used: dict[str, Threshold] = {}
    for section, fields in CALIBRATED.items():
        current = getattr(settings, section)
        entry = meta.calibration.get(section)
        for name in fields:
            key = f"{section}.{name}"
            if name in current.model_fields_set:
                used[key] = Threshold(getattr(current, name), "setting")
            elif entry is not None and name in entry.values:
                value = entry.values[name]
                updates.setdefault(section, {})[name] = value
                used[key] = Threshold(value, "model", f"{entry.chosen_by} on {entry.data}")
            elif key == "rerank.score" and not _scores_its_network(meta):
                # nothing to choose: "stage" is the only score its first stage gives
                used[key] = Threshold(getattr(current, name), "model", "its first stage")
            else:
                used[key] = Threshold(getattr(current, name), "default")
    sections = {}
    for section, values in updates.items():
        current = getattr(settings, section)
        try:  # validated like a setting: a model file's bad value stops the service here
            sections[section] = type(current).model_validate(
                {**current.model_dump(exclude_unset=True), **values}
            )
        except ValidationError as err:
            raise ValueError(
                f"model {meta.model_id}: its calibration of {section} is not valid "
                f"({err.errors()[0]['loc']}: {err.errors()[0]['msg']}); recalibrate it, or set "
                f"[{section}] explicitly"
            ) from None
    out = settings.model_copy(update=sections)
    rerank_params(out.rerank, meta)  # a second-stage score this model cannot give stops here
    return out, used


def _scores_its_network(meta: EncoderMetadata) -> bool:
    """Whether the model's first stage holds its network's descriptor apart (a mixed or a
    split-reduced one), so that rerank.score has a choice to calibrate; where its first
    stage is its descriptor both scores are one."""
    from overlapmamba.core.rerank import Rerank, with_score

    try:
        network = with_score(Rerank(), "network", meta)
    except ValueError:
        return False
    return network != with_score(Rerank(), "stage", meta)  # else both score alike


def read_model_metadata(path: Path) -> EncoderMetadata:
    """A model file's metadata, read without building an inference session (onnx only)."""
    import onnx

    proto = onnx.load(str(path), load_external_data=False)
    return EncoderMetadata.from_props({p.key: p.value for p in proto.metadata_props})


def log_thresholds(model_id: str, used: dict[str, Threshold]) -> None:
    """One line with every threshold and its source; a warning when a model runs on
    defaults that were calibrated for another model."""
    log.info(
        "thresholds for %s: %s",
        model_id,
        ", ".join(f"{k}={t.value} ({t.source})" for k, t in used.items()),
        extra={"thresholds": {k: t.public() for k, t in used.items()}},
    )
    # a default of null is a check left off (verify.ambiguity_margin), not another
    # model's threshold: a file calibrated before the check serves as it did
    defaults = sorted(k for k, t in used.items() if t.source == "default" and t.value is not None)
    if defaults:
        log.warning(
            "model %s carries no calibration for %s: the built-in defaults serve, which were "
            "calibrated for the shipped model, not this one. Calibrate it on a validation town "
            "(benchmarks/rerank.py, loop_threshold.py, verify_threshold.py --calibrate, each "
            "with --write-calibration) or set them explicitly",
            model_id,
            ", ".join(defaults),
        )
