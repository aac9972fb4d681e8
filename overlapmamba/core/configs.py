"""Configurations from plain dicts (JSON, TOML, checkpoints, presets, the CLI): the
:class:`Config` base that every configuration of the project derives from (the network,
training, augmentation, and the simulator's world, drive and dynamics parameters)."""

from __future__ import annotations

from typing import Any, ClassVar, Self

from pydantic import BaseModel, ConfigDict, ValidationError

from overlapmamba.core.errors import ConfigError


class Config(BaseModel):
    """Base of the project's configurations that cross a boundary (files, checkpoints, the
    CLI, presets): pydantic fields, unknown fields refused with the allowed ones, and any
    failed check raised as ``config_error`` (ConfigError unless a subclass says otherwise)
    with the check's own message — never as pydantic's ValidationError."""

    model_config = ConfigDict(extra="forbid", protected_namespaces=())
    config_name: ClassVar[str] = "config"  # how messages name it ("training", "augmentation")
    config_error: ClassVar[type[Exception]] = ConfigError

    def __init__(self, **data: Any) -> None:
        cls = type(self)
        fields = set(cls.model_fields)
        unknown = sorted(set(data) - fields)
        if unknown:
            raise cls.config_error(
                f"unknown {cls.config_name} fields {unknown}; allowed: {sorted(fields)}"
            )
        try:
            super().__init__(**data)
        except ValidationError as err:
            first = err.errors()[0]
            message = str(first["msg"]).removeprefix("Value error, ")
            if first["type"] != "value_error":  # a type or range pydantic checked itself
                message = f"{'.'.join(str(p) for p in first['loc'])}: {message}"
            raise cls.config_error(message) from None

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Self:
        """The inverse of :meth:`to_dict`; unknown keys are an error, missing ones default."""
        return cls(**d)

    def to_dict(self) -> dict[str, Any]:
        return self.model_dump()
