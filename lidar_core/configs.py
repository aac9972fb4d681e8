"""Configuration dataclasses from plain dicts (JSON, TOML, checkpoints, presets): one builder
for every config of the project."""

from __future__ import annotations

import dataclasses
from typing import Any

from lidar_core.errors import ConfigError


def dataclass_from_dict(
    cls: Any, d: dict[str, Any], what: str, *, error: type[Exception] = ConfigError
) -> Any:
    """``cls(**d)`` for a config dataclass: unknown keys refused (``error``, naming them and
    the allowed ones); lists become tuples (configs are frozen, their sequences tuples)."""
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(d) - known)
    if unknown:
        raise error(f"unknown {what} fields {unknown}; allowed: {sorted(known)}")
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})
