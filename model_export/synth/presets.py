"""Fixed, documented data presets. Each split is a different town (its own seed), so the
test towns are never seen in training; ``split`` travels in every manifest so a trainer
can refuse test data.

| preset | seed | scans | sensor      | town           | use                      |
|--------|------|-------|-------------|----------------|--------------------------|
| train  | 1001 | 4000  | kitti-hdl64 | 6 × 6 nodes    | training                 |
| val    | 2002 | 1500  | kitti-hdl64 | 5 × 5 nodes    | model selection          |
| test   | 3003 | 2500  | kitti-hdl64 | 6 × 6 nodes    | reported numbers only    |
"""

from __future__ import annotations

from model_export.synth.generate import GenConfig

PRESETS: dict[str, GenConfig] = {
    "train": GenConfig(seed=1001, frames=4000, preset="train", split="train"),
    "val": GenConfig(seed=2002, frames=1500, preset="val", split="val", world={"nx": 5, "ny": 5}),
    "test": GenConfig(seed=3003, frames=2500, preset="test", split="test"),
}


def preset(name: str) -> GenConfig:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; allowed: {', '.join(PRESETS)}")
    return PRESETS[name]
