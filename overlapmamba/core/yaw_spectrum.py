"""A first stage that does not turn with the scan: the yaw features' magnitude spectrum.

The model's per-column yaw features (C channels over W azimuth columns) keep where along
the ring each structure is; the descriptor pools that away. A turn of the scan by whole
columns rolls the features, which changes no channel's magnitude spectrum over azimuth
(|rfft|), and a turn by part of a column changes it little. Each channel's magnitudes at
frequencies 0 … ``bins`` − 1 (the channel mean included), compressed by a square root and
taken together at unit length, are a place descriptor by themselves; ``mixed`` joins it to
the network's descriptor so that a squared distance between two scans is
(1 − a) · d²(descriptor) + a · d²(spectrum).

``benchmarks/yaw_spectrum.py`` measures it across sensors (a map by one sensor, queries by
another) against the descriptor alone; the variant is chosen there on ``val``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

COMPRESSIONS = ("none", "sqrt")
_CHUNK = 256  # scans a FFT call: a 2,000-scan drive's features are 100 MB in float32


@dataclass(frozen=True)
class FirstStage:
    """What a query's shortlist is ranked by: the descriptor (``mix`` 0), the spectrum
    (``mix`` 1) or both (0 < ``mix`` < 1), the spectrum of ``bins`` frequencies."""

    mix: float = 0.0
    bins: int = 32
    compress: str = "sqrt"

    def __post_init__(self) -> None:
        if not 0.0 <= self.mix <= 1.0:
            raise ValueError(f"first-stage mix must be in [0, 1]; got {self.mix}")
        if self.bins < 1:
            raise ValueError(f"spectrum bins must be ≥ 1; got {self.bins}")
        if self.compress not in COMPRESSIONS:
            raise ValueError(
                f"spectrum compression {self.compress!r} is not one of {', '.join(COMPRESSIONS)}"
            )

    @classmethod
    def parse(cls, text: str) -> FirstStage:
        """``descriptor``, ``spectrum:BINS:COMPRESS`` or ``mixed:A:BINS:COMPRESS`` (e.g.
        ``mixed:0.75:32:sqrt``)."""
        parts = text.strip().lower().split(":")
        try:
            if parts == ["descriptor"]:
                return cls()
            if parts[0] == "spectrum" and len(parts) == 3:
                return cls(1.0, int(parts[1]), parts[2])
            if parts[0] == "mixed" and len(parts) == 4:
                return cls(float(parts[1]), int(parts[2]), parts[3])
        except ValueError as e:
            raise ValueError(f"first stage {text!r}: {e}") from None
        raise ValueError(
            f"first stage {text!r} is not descriptor, spectrum:BINS:COMPRESS or "
            "mixed:A:BINS:COMPRESS (e.g. mixed:0.75:32:sqrt)"
        )

    @property
    def name(self) -> str:
        if self.mix == 0.0:
            return "descriptor"
        if self.mix == 1.0:
            return f"spectrum:{self.bins}:{self.compress}"
        return f"mixed:{self.mix:g}:{self.bins}:{self.compress}"

    def vectors(self, desc: np.ndarray, yaw: np.ndarray) -> np.ndarray:
        """(N, D) descriptors and (N, C, W) yaw features → the (N, ·) rows whose squared
        L2 distances rank a shortlist."""
        if self.mix == 0.0:
            return unit(desc)
        spec = spectrum(yaw, self.bins, self.compress)
        if self.mix == 1.0:
            return spec
        return np.concatenate(
            [unit(desc) * np.sqrt(1.0 - self.mix), spec * np.sqrt(self.mix)], axis=1
        )


SCORES = ("stage", "network")  # what a second stage's d² is measured between (score_part)


def score_part(stage: FirstStage, dim: int, channels: int, score: str) -> int | None:
    """How many leading floats of ``stage``'s ``dim``-float vectors (:meth:`FirstStage.vectors`
    of a file with ``channels`` yaw channels) a second stage scores by
    (:attr:`overlapmamba.core.rerank.Rerank.part`): None — the whole vector — for ``stage``
    and for a stage that is the network's descriptor; for ``network`` and a mixed stage, the
    network's descriptor ahead of the spectrum. A spectrum alone holds no network descriptor.
    ``benchmarks/rerank.py --score network`` measures it."""
    if score not in SCORES:
        raise ValueError(f"second-stage score {score!r} is not one of {', '.join(SCORES)}")
    if score == "stage" or stage.mix == 0.0:
        return None
    if stage.mix == 1.0:
        raise ValueError(
            f"first stage {stage.name} holds no network descriptor to score by; allowed: "
            "score 'stage' (or a file whose first stage is descriptor or mixed)"
        )
    d = dim - channels * stage.bins
    if d < 1:
        raise ValueError(
            f"{dim} floats a row hold no descriptor beside {channels} channels × "
            f"{stage.bins} bins of {stage.name}"
        )
    return d


def unit(x: np.ndarray) -> np.ndarray:
    """Rows of ``x`` at unit L2 length (float32; a zero row stays zero)."""
    x = np.asarray(x, np.float32)
    return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)


def spectrum(yaw: np.ndarray, bins: int, compress: str = "sqrt") -> np.ndarray:
    """(N, C, W) yaw features → (N, C · bins) unit rows: each channel's |rfft| over azimuth
    at frequencies 0 … bins − 1, square-rooted with ``compress`` ``sqrt``. A circular shift
    of the columns changes none of them."""
    yaw = np.asarray(yaw)
    if yaw.ndim != 3:
        raise ValueError(f"yaw features must be (N, C, W); got shape {yaw.shape}")
    n, c, w = yaw.shape
    if bins > w // 2 + 1:
        raise ValueError(f"{bins} bins but {w} columns have {w // 2 + 1} frequencies")
    out = np.empty((n, c * bins), dtype=np.float32)
    for s in range(0, n, _CHUNK):
        mag = np.abs(np.fft.rfft(np.asarray(yaw[s : s + _CHUNK], np.float32), axis=-1))
        mag = mag[..., :bins]
        if compress == "sqrt":
            mag = np.sqrt(mag)
        out[s : s + _CHUNK] = unit(mag.reshape(len(mag), -1))
    return out
