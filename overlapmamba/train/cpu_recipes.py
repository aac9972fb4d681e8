"""The bird's-eye recipe from scratch on two CPU cores in one working session (issue 40: the
recipe must train from scratch on 2 cores in ≤ 2 h; the long runs are for a lent GPU).

``bev-span-thin-cpu`` is ``bev-span-thin-long`` (the ``bev-span`` input, the all-rows
backbone, the sparser-sensor term at weight 1 on 8 scans a batch, hard negatives, train-b and
the four drawn towns, selected on ``val-kitti-hdl64`` and its four renderings) planned for 10
epochs of 6,000 scans instead of 40. The learning-rate schedule steps by epoch, so its epochs
are the long run's first ten. Sized from a probe here (``overlapmamba train --preset
bev-span-thin-long --epochs 1 --epoch-scans 640``): ≈ 17 scans/s of training, ≈ 24 s of
mining and ≈ 105 s of validation an epoch, ≈ 8 min an epoch in all. ``bev-span-cpu`` is the
same without the term (its control at an equal budget); both have a ``-s1`` twin.
"""

from __future__ import annotations

from overlapmamba.train.recipes import TrainPreset
from overlapmamba.train.sensor_recipes import (
    BEV_LONG,
    BEV_SPAN_MODEL,
    BEV_SPAN_THIN_LONG,
    COMMON_DATA,
    SENSOR_VAL,
)

CPU_BUDGET = {"epochs": 10, "epoch_scans": 6000}
BEV_SPAN_THIN_CPU = {**BEV_SPAN_THIN_LONG, **CPU_BUDGET}
BEV_SPAN_CPU = {**BEV_LONG, **CPU_BUDGET}

CPU_PRESETS: tuple[TrainPreset, ...] = tuple(
    TrainPreset(
        name, description, model=BEV_SPAN_MODEL, train=train, data=COMMON_DATA, val=SENSOR_VAL
    )
    for name, train, description in (
        (
            "bev-span-thin-cpu",
            BEV_SPAN_THIN_CPU,
            "bev-span-thin-long from scratch at a 2-core budget (10 epochs of 6,000 scans)",
        ),
        (
            "bev-span-cpu",
            BEV_SPAN_CPU,
            "bev-span-thin-cpu without the sparser-sensor term (its control)",
        ),
    )
)
