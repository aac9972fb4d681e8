"""Fixed, documented data presets. Each split is a different town (its own seed), so the
test towns are never seen in training; ``split`` travels in every manifest so a trainer
can refuse test data.

| preset | seed | scans | sensor      | town           | use                      |
|--------|------|-------|-------------|----------------|--------------------------|
| train  | 1001 | 4000  | kitti-hdl64 | 6 × 6 nodes    | training                 |
| val    | 2002 | 1500  | kitti-hdl64 | 5 × 5 nodes    | model selection          |
| test   | 3003 | 2500  | kitti-hdl64 | 6 × 6 nodes    | reported numbers only    |
| tiny   | 5    | 600   | kitti-hdl64 | 4 × 3, small   | tests: fast, both-direction loops |
| tiny-val | 24 | 600   | kitti-hdl64 | 4 × 3, small   | tests: validation of tiny runs |

The tiny presets revisit after every 30–60 m of exploring in a small town (blocks of
50–65 m), so 600 scans can hold loops in both directions; their pair tables stop at 12 m.
Their seeds follow the same kind of rule: the first seed counting up from 5 (tiny) and from
6 (tiny-val) whose 600-scan drive has at least 10 same- and 10 opposite-direction scans
within 6 m of a scan more than 100 frames older (tiny: 88 and 82; tiny-val: 11 and 90).

How the seeds were chosen: for each split, the first seed counting up from 1001, 2002 and
3003 whose planned drive has at least 40 % opposite-direction revisits among the scans that
pass within 6 m of a scan more than 100 frames older, at least 100 same-direction ones, and
(train, test) some revisits more than 1,000 scans later. Chance decides how often a drive
crosses its own path, so a fixed seed is checked once here rather than hoped for.
"""

from __future__ import annotations

from model_export.synth.generate import GenConfig

_TINY: dict = {
    "world": {"nx": 4, "ny": 3, "block_min": 50.0, "block_max": 65.0},
    "drive": {"revisit_every": [30, 60], "revisit_min_age": 70, "old_age": 150},
    "gt_radius": 12.0,
}

PRESETS: dict[str, GenConfig] = {
    "train": GenConfig(seed=1001, frames=4000, preset="train", split="train"),
    "val": GenConfig(seed=2002, frames=1500, preset="val", split="val", world={"nx": 5, "ny": 5}),
    "test": GenConfig(seed=3003, frames=2500, preset="test", split="test"),
    "tiny": GenConfig(seed=5, frames=600, preset="tiny", split="train", **_TINY),
    "tiny-val": GenConfig(seed=24, frames=600, preset="tiny-val", split="val", **_TINY),
}


def preset(name: str) -> GenConfig:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; allowed: {', '.join(PRESETS)}")
    return PRESETS[name]
