"""The ``elevation-fill`` and ``elevation-reach`` continuations (issue 40; the inputs:
:mod:`overlapmamba.core.sensors.input`, the gaps: :mod:`overlapmamba.core.sensors.gaps`).

Served as they are, both inputs lift the 128-beam Ousters' scans across sensors: their
one-column gaps (1,024 firings a turn into 900 columns) are what the network never saw
(``benchmarks/fill_gaps.py``). The towns of those sensors did not teach it them either
(``lerp-towns-pilot-control``: the same continuation by the shipped ``elevation`` input, so
it is both presets' control at an equal budget). ``fill-towns-pilot`` continues the shipped
network on the same five towns with other sensors' gaps filled; ``reach-towns-pilot`` also
cuts every scan, the model's own too, at 50 m. Data, validation, selection, rate, frozen
batch norm and budget are ``lerp-towns-pilot``'s: two epochs of 3,000 scans.
"""

from __future__ import annotations

from typing import Any

from overlapmamba.train.lerp_recipes import LERP_TOWNS
from overlapmamba.train.recipes import NARROW, TrainPreset
from overlapmamba.train.sensor_recipes import COMMON_DATA, SENSOR_VAL

CUT_TOWNS: dict[str, Any] = {
    **LERP_TOWNS,
    "augment": {"range_cut": 0.5, "range_cut_min_m": 40.0},
}
FILL_PRESETS: tuple[TrainPreset, ...] = tuple(
    TrainPreset(
        name,
        description,
        model={**NARROW, "sensor_input": mode},
        train=train,
        data=COMMON_DATA,
        val=SENSOR_VAL,
    )
    for name, mode, train, description in (
        (
            "fill-towns-pilot",
            "elevation-fill",
            LERP_TOWNS,
            "the shipped network continued on five towns, other sensors' one-column gaps filled",
        ),
        (
            "reach-towns-pilot",
            "elevation-reach",
            LERP_TOWNS,
            "the same continuation, gaps filled and every scan cut at 50 m",
        ),
        (
            "cut-towns-pilot",
            "elevation-fill",
            CUT_TOWNS,
            "fill-towns-pilot with half the scans cut at a range drawn in 40-80 m (range_cut)",
        ),
    )
)
