"""Errors of training, evaluation and export, in lidar_core's exception tree.

    LidarCoreError (lidar_core.errors)
     └── ModelError                 (ValueError)
          ├── CheckpointError        a file that is not a usable checkpoint
          └── ConfigError            a model or training configuration that is not allowed

Like lidar_core's errors each carries a stable ``code`` and a ``detail`` dict, and the CLI
prints their message instead of a traceback.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from lidar_core.errors import LidarCoreError


class ModelError(LidarCoreError, ValueError):
    code = "model_error"


class CheckpointError(ModelError):
    code = "invalid_checkpoint"


class ConfigError(ModelError):
    code = "invalid_config"


def dataclass_from_dict(cls: Any, d: dict, what: str) -> Any:
    """``cls(**d)`` for a config dataclass, refusing unknown keys with the allowed ones."""
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(d) - known)
    if unknown:
        raise ConfigError(f"unknown {what} fields {unknown}; allowed: {sorted(known)}")
    return cls(**d)
