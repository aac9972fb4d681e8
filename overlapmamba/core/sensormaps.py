"""Descriptors of other sensors moved into the model sensor's: one map a sensor, fitted for
one model and carried in its file.

The same place seen by two sensors gets descriptors that differ partly by a pattern each
sensor shares across all its scans. Drives rendered by every sensor scan for scan pair each
sensor's descriptors with the model sensor's of the same places, and a map is fitted on
those pairs:

    shift   d − m_sensor + m_model (the two sensors' mean descriptors: one vector a sensor)
    linear  (d − m_sensor) W + m_model, W the ridge regression of the model sensor's
            centred descriptors on the sensor's (one D × D matrix a sensor)

each renormalised to unit length. The model sensor's own descriptors are never mapped, so
every map the model sensor made stays as it is; a scan of a sensor without a map keeps its
raw descriptor. A model file that carries maps (``EncoderMetadata.sensor_maps``) has its own
model id: the descriptors it gives other sensors' scans are not the raw file's.

Arrays travel as base64 of little-endian float32 in the file's JSON metadata.
"""

from __future__ import annotations

import base64
import hashlib
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

HOWS = ("shift", "linear")


def _encode(a: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(a, dtype="<f4").tobytes()).decode("ascii")


def _decode(s: str) -> np.ndarray:
    return np.frombuffer(base64.b64decode(s.encode("ascii"), validate=True), dtype="<f4")


class SensorMap(BaseModel):
    """One sensor's map into the model sensor's descriptor space, and where it came from."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    how: Literal["shift", "linear"]
    dim: int = Field(gt=0, description="descriptor dimension D")
    mean_in: str = Field(description="the sensor's mean descriptor (base64 float32, D)")
    mean_out: str = Field(description="the model sensor's mean descriptor (base64 float32, D)")
    matrix: str | None = Field(
        default=None, description="linear: W (base64 float32, D × D, row-major); shift: none"
    )
    ridge: float | None = Field(default=None, ge=0, description="linear: the ridge per frame")
    pairs: int = Field(gt=0, description="paired frames it was fitted on")
    chosen_by: str = Field(min_length=1, description="the command that fitted it")
    data: str = Field(min_length=1, description="what it was fitted and chosen on")
    at: str = Field(description="UTC time, ISO 8601")

    @field_validator("mean_in", "mean_out", "matrix")
    @classmethod
    def _base64(cls, v: str | None) -> str | None:
        if v is not None:
            try:
                base64.b64decode(v.encode("ascii"), validate=True)
            except (ValueError, UnicodeEncodeError) as err:
                raise ValueError(f"not base64: {err}") from None
        return v

    @model_validator(mode="after")
    def _shapes(self) -> SensorMap:
        for name in ("mean_in", "mean_out"):
            n = len(_decode(getattr(self, name)))
            if n != self.dim:
                raise ValueError(f"{name} holds {n} values; the descriptor has {self.dim}")
        if self.how == "linear":
            if self.matrix is None:
                raise ValueError("a linear map needs its matrix")
            n = len(_decode(self.matrix))
            if n != self.dim * self.dim:
                raise ValueError(f"matrix holds {n} values; a {self.dim}² map needs {self.dim**2}")
        elif self.matrix is not None:
            raise ValueError("a shift map has no matrix")
        return self

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """(mean_in, mean_out, W or None) as float32 arrays."""
        w = None if self.matrix is None else _decode(self.matrix).reshape(self.dim, self.dim)
        return _decode(self.mean_in), _decode(self.mean_out), w

    def apply(self, desc: np.ndarray) -> np.ndarray:
        """(N, D) or (D,) descriptors of this sensor → unit-norm float32 descriptors in the
        model sensor's space."""
        d = np.asarray(desc, dtype=np.float32)
        if d.shape[-1] != self.dim:
            raise ValueError(f"descriptors of dimension {d.shape[-1]}; this map takes {self.dim}")
        m_in, m_out, w = self.arrays()
        out = (d - m_in) @ w + m_out if w is not None else d - m_in + m_out
        norm = np.linalg.norm(out, axis=-1, keepdims=True)
        return (out / np.maximum(norm, 1e-12)).astype(np.float32)


def fit_map(
    q: np.ndarray,
    m: np.ndarray,
    how: str,
    *,
    ridge: float = 0.0,
    chosen_by: str,
    data: str,
    at: str,
) -> SensorMap:
    """The map fitted on paired descriptors: ``q`` (N, D) the sensor's, ``m`` (N, D) the model
    sensor's of the same places; ``ridge`` per frame (the weight is ``ridge`` × N)."""
    if how not in HOWS:
        raise ValueError(f"unknown sensor map {how!r}; allowed: {', '.join(HOWS)}")
    q, m = np.asarray(q, np.float64), np.asarray(m, np.float64)
    if q.ndim != 2 or q.shape != m.shape or len(q) < 2:
        raise ValueError(
            f"paired descriptors must be two (N ≥ 2, D) arrays; got {q.shape}, {m.shape}"
        )
    mq, mm = q.mean(0), m.mean(0)
    matrix = None
    if how == "linear":
        a, b = q - mq, m - mm
        w = np.linalg.solve(a.T @ a + ridge * len(a) * np.eye(a.shape[1]), a.T @ b)
        matrix = _encode(w)
    return SensorMap(
        how=how,  # type: ignore[arg-type]
        dim=q.shape[1],
        mean_in=_encode(mq),
        mean_out=_encode(mm),
        matrix=matrix,
        ridge=ridge if how == "linear" else None,
        pairs=len(q),
        chosen_by=chosen_by,
        data=data,
        at=at,
    )


def maps_digest(maps: dict[str, SensorMap]) -> str:
    """A short content hash of the maps (names and arrays), for the model id."""
    h = hashlib.sha256()
    for name in sorted(maps):
        x = maps[name]
        h.update(f"{name}:{x.how}:{x.dim}:".encode())
        for part in (x.mean_in, x.mean_out, x.matrix or ""):
            h.update(part.encode("ascii"))
    return h.hexdigest()[:16]
