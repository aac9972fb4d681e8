"""The ``elevation-lerp`` continuations (issue 40; the input:
:mod:`overlapmamba.core.sensors.input`).

Served as it is, ``elevation-lerp`` ties with the shipped ``elevation`` input over the sensor
renderings (``benchmarks/lerp_input.py``), though the network never saw a lerp image of
another sensor. ``lerp-towns-pilot`` continues the shipped network on train-b and the four
drawn towns of the across-sensor bars' sensors (VLP-16, OS0-128, XT32 and OS1-128 on drawn
mountings), every other sensor's scans made into the HDL-64E's beams by ``elevation-lerp``;
``lerp-towns-pilot-control`` is the same continuation by the shipped ``elevation`` input.
Both validate on the sensor validation drive and its renderings by those four sensors, each
rendering taken through the run's own input, and keep the epoch with the best mean over
them (``select_on = "sensors"``). The rate and frozen batch norm are a continuation's
(``common-towns-slow``'s), two epochs of 3,000 scans: ≈ 25 min each on 2 CPU cores.
"""

from __future__ import annotations

from overlapmamba.train.recipes import NARROW, TrainPreset
from overlapmamba.train.sensor_recipes import COMMON_DATA, COMMON_SLOW, SENSOR_VAL

LERP_MODEL = {**NARROW, "sensor_input": "elevation-lerp"}
LERP_TOWNS = {**COMMON_SLOW, "epochs": 2, "epoch_scans": 3000}

LERP_PRESETS: tuple[TrainPreset, ...] = (
    TrainPreset(
        "lerp-towns-pilot",
        "the shipped network continued on five towns, other sensors' scans by elevation-lerp",
        model=LERP_MODEL,
        train=LERP_TOWNS,
        data=COMMON_DATA,
        val=SENSOR_VAL,
    ),
    TrainPreset(
        "lerp-towns-pilot-control",
        "the same continuation by the shipped elevation input",
        model=NARROW,
        train=LERP_TOWNS,
        data=COMMON_DATA,
        val=SENSOR_VAL,
    ),
)
