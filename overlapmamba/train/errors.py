"""Errors of training, evaluation and export, in overlapmamba.core's exception tree.

    LidarCoreError (overlapmamba.core.errors)
     └── ModelError                 (ValueError)
          ├── CheckpointError        a file that is not a usable checkpoint
          ├── ExportError            an export, or a model file's metadata, that failed
          ├── ConfigError            a model or training configuration that is not allowed
          │                          (also a overlapmamba.core.errors.ConfigError)
          └── DivergedError          a training step whose loss is not finite

Like overlapmamba.core's errors each carries a stable ``code`` and a ``detail`` dict, and the CLI
prints their message instead of a traceback.
"""

from __future__ import annotations

from overlapmamba.core import errors
from overlapmamba.core.errors import LidarCoreError


class ModelError(LidarCoreError, ValueError):
    code = "model_error"


class CheckpointError(ModelError):
    code = "invalid_checkpoint"


class ExportError(ModelError):
    code = "export_failed"


class ConfigError(ModelError, errors.ConfigError):
    code = "invalid_config"


class DivergedError(ModelError):
    code = "training_diverged"
