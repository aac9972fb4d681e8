"""Named training recipes: ``overlapmamba train --preset NAME`` (writes ``runs/NAME``).

Every recipe trains on the synthetic training towns and selects on ``val`` (``make data``
writes them, and the ``test`` towns, which no recipe trains on). Paths are relative to the
repository root, where the command is meant to run. The loss, sampling, augmentation and
schedule are ``TrainConfig``'s defaults unless a preset says
otherwise.

- ``default`` is the reference architecture's recipe: 6 epochs of 3,500 scans from the four
  training towns (≈ 1 h 50 min on 2 CPU cores at ≈ 3.5 scans/s, with validation).
- ``narrow`` is a narrower network (d_model 64, convLast2 256, 32 clusters: ≈ 2.9× the
  reference's training speed here) on the same wall time: 6 epochs of 10,000 scans.
- ``narrow-hn`` (the shipped model's recipe: ``SHIPPED``) is ``narrow`` with mined hard
  negatives (:mod:`overlapmamba.train.mining`): half of the groups take a distant scan the current
  weights find alike as their negative. 6 epochs take ≈ 90 min here (12.5–13 scans/s).
- ``narrow-hn-aug`` is ``narrow-hn`` with augmentation (``NARROW_HN_AUG``: sub-column turns,
  dropped returns, range noise): whether the shipped recipe's open bars — the minimum
  cosine under a continuous turn, retrieval across sessions — respond to it at scale.
- ``narrow-hn-band`` is ``narrow-hn-aug`` for 8 epochs whose last two (from epoch 7) also
  rank each anchor's ambiguous band below its positives (``BAND``,
  :class:`~overlapmamba.train.losses.BandRanking`): aimed at same-direction false alarms, most of
  which are neighbouring places 15–50 m away. Its epochs 0–6 are ``narrow-hn-aug``'s, draw
  for draw (the band option draws nothing before its epoch), ≈ 100 min in all here.
- ``narrow-hn-turn`` continues the shipped network (``init``: its ``.onnx``, weights
  recovered exactly) with the turn term (``TURN``): each batch also holds 8 of its scans
  turned by a random continuous angle, and 100 × their squared distance to the unturned
  scans, in units of the batch's spread, joins the loss. Aimed at the minimum cosine under a
  continuous turn. ≈ 6 min an epoch here.
- ``aligned-pilot`` continues the one-view twin's network (the shipped weights; its file
  takes each scan's columns at its mean bearing, :mod:`overlapmamba.core.views`) on aligned
  images of train-b (``ALIGNED``), and ``aligned-pilot-control`` the same weights in the
  sensor's columns at an equal budget: whether training on aligned images closes the gap the
  alignment costs the descriptor alone (docs/results.md, the views table). Each with ``-s1``.
- ``drift-pilot`` is ``aligned-pilot`` on ``train-b-drift`` (train-b with each scan's firings
  a random fraction of a spacing later, as a real head's drift), and ``drift-pilot-control``
  ``aligned-pilot`` on train-b as it is; both validate on ``val-drift``: whether training on
  drifting firings helps the one-view twin where the firings drift (docs/results.md, where
  the firings fall). Each with ``-s1``.
- ``sensors-*``, ``common-*``, ``structure-*`` and ``bev-*`` are the runs on several sensors
  (issue 40), listed in :mod:`overlapmamba.train.sensor_recipes`.
- ``ot`` is the OverlapTransformer-style baseline on the default recipe.
- ``one-town`` is the default recipe on the first training town alone (the former data):
  what more places are worth at equal training time.
- ``robust`` is the default recipe with the full augmentation set: whether it pays at scale
  (at 120 steps on the tiny towns it did not).
- ``narrow-hn-long`` is ``narrow-hn`` unchanged but for its length (40 epochs), and
  ``narrow-hn-b64-long`` the same at batch 64 with 5,000 scans in the mining pool:
  whether the shipped recipe was stopped too early. Both were run on a GPU lent for one
  session (``--device cuda``), for as many epochs as its window allowed; an epoch of
  ``narrow-hn`` takes ≈ 12–14 min on 2 CPU cores.
- ``abl-*`` are the ablations (paper Tables II–IV) on the shipped width (``NARROW``) and an
  equal budget of 10,000 scans each (one epoch of the shipped recipe), spent as 2 epochs of
  5,000 so that the loss and F1 are recorded twice (Table IV): 6–13 min a row on 2 CPU
  cores. ``abl-oldloss`` is the former recipe (α 0.5 and λ 0.1 on absolute distances,
  negatives up to overlap 0.3, whole-column rolls only, no warm-up). Every row also runs
  with seed 1 (``-s1``).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from overlapmamba.train.augment import ROBUST
from overlapmamba.train.cpu_recipes import CPU_PRESETS
from overlapmamba.train.errors import ConfigError
from overlapmamba.train.fill_recipes import FILL_PRESETS
from overlapmamba.train.lerp_recipes import LERP_PRESETS
from overlapmamba.train.recipes import (
    ABLATION,
    ALIGNED,
    ALIGNED_DATA,
    BAND,
    DEFAULT,
    DRIFT_DATA,
    DRIFT_VAL,
    NARROW,
    NARROW_HN,
    NARROW_HN_AUG,
    OLD_LOSS,
    TURN,
    TrainPreset,
)
from overlapmamba.train.sensor_recipes import SENSOR_PRESETS

ONE_TOWN = ("data/synth/train",)
TEST_DATA = ("data/synth/test", "data/synth/test-b", "data/synth/test-c")
SECOND_SESSION = "data/synth/test-s1"  # a second drive through TEST_DATA[0]
# The run whose best.pt is exported to models/overlapmamba-hdl64.onnx (the model card says
# why); the report marks its row "(shipped)" and checks it on real scans.
SHIPPED = "narrow-hn"


_OT = {"mixer": "transformer", "spp": False}

PRESETS: dict[str, TrainPreset] = {
    p.name: p
    for p in (
        TrainPreset("default", "reference OverlapMamba, 6 × 3500 scans", train=DEFAULT),
        TrainPreset(
            "narrow",
            "narrower OverlapMamba (d 64, head 256, 32 clusters), the default's wall time",
            model=NARROW,
            train={"epochs": 6, "epoch_scans": 10000},
        ),
        TrainPreset(
            "narrow-hn",
            "narrow with mined hard negatives: half the groups meet a distant look-alike",
            model=NARROW,
            train=NARROW_HN,
        ),
        TrainPreset(
            "narrow-hn-long",
            "narrow-hn for 40 epochs (run on a lent GPU: --device cuda)",
            model=NARROW,
            train={**NARROW_HN, "epochs": 40},
        ),
        TrainPreset(
            "narrow-hn-b64-long",
            "narrow-hn for 40 epochs at batch 64, mining among 5,000 training scans",
            model=NARROW,
            train={**NARROW_HN, "epochs": 40, "batch_size": 64, "mine_pool": 5000},
        ),
        TrainPreset(
            "narrow-hn-aug",
            "narrow-hn with sub-column turns, up to 20 % of returns dropped and 3 cm of noise",
            model=NARROW,
            train={
                "epochs": 6,
                "epoch_scans": 10000,
                "hard_negatives": 0.5,
                "augment": NARROW_HN_AUG,
            },
        ),
        TrainPreset(
            "narrow-hn-band",
            "narrow-hn-aug for 8 epochs, the last two also ranking neighbours below positives",
            model=NARROW,
            train={
                "epochs": 8,
                "epoch_scans": 10000,
                "hard_negatives": 0.5,
                "augment": NARROW_HN_AUG,
                **BAND,
            },
        ),
        TrainPreset(
            "narrow-hn-turn",
            "the shipped network continued with the turn term (weight 100, 8 turned scans)",
            model=NARROW,
            train=TURN,
        ),
        TrainPreset(
            "aligned-pilot",
            "the one-view twin (aligned columns) continued on aligned images of train-b",
            model=NARROW,
            train=ALIGNED,
            data=ALIGNED_DATA,
        ),
        TrainPreset(
            "aligned-pilot-control",
            "the same continuation in the sensor's columns, from the same weights",
            model=NARROW,
            train={**ALIGNED, "init": "models/overlapmamba-hdl64.onnx"},
            data=ALIGNED_DATA,
        ),
        TrainPreset(
            "drift-pilot",
            "aligned-pilot on train-b with drifting firings, validated on val-drift",
            model=NARROW,
            train=ALIGNED,
            data=DRIFT_DATA,
            val=DRIFT_VAL,
        ),
        TrainPreset(
            "drift-pilot-control",
            "aligned-pilot on train-b as it is (locked firings), validated on val-drift",
            model=NARROW,
            train=ALIGNED,
            data=ALIGNED_DATA,
            val=DRIFT_VAL,
        ),
        *SENSOR_PRESETS,
        *LERP_PRESETS,
        *FILL_PRESETS,
        *CPU_PRESETS,
        TrainPreset(
            "ot",
            "OverlapTransformer-style baseline (1 transformer layer, no SPP), default recipe",
            model=_OT,
            train=DEFAULT,
        ),
        TrainPreset(
            "one-town", "the default recipe on one training town", train=DEFAULT, data=ONE_TOWN
        ),
        TrainPreset(
            "robust",
            "the default recipe with the full augmentation set (augment.ROBUST)",
            train={**DEFAULT, "augment": ROBUST},
        ),
    )
}

# The runs on several sensors, each also with seed 1 (its draws; the start is the same network).
for _name in (
    "aligned-pilot",
    "aligned-pilot-control",
    "drift-pilot",
    "drift-pilot-control",
    "sensors-pilot",
    "sensors-pilot-control",
    "sensors-seen",
    "sensors-seen-look",
    "sensors-seen-far",
    "sensors-towns",
    "sensors-towns-car",
    "bev-long",
    "bev-span-pilot",
    "bev-span-thin-pilot",
    "bev-span-thin-long",
    "bev-span-thin-cpu",
    "bev-span-cpu",
    "reach-towns-pilot",
    "lerp-towns-pilot-control",
    "cut-towns-pilot",
):
    _p = PRESETS[_name]  # every field the base's but these (a field added later follows too)
    PRESETS[_name + "-s1"] = replace(
        _p,
        name=_name + "-s1",
        description=_p.description + ", seed 1",
        train={**_p.train, "seed": 1},
    )

# The ablations (Tables II–IV): the shipped width, one budget, two seeds each.
_ABLATIONS: tuple[tuple[str, str, dict[str, Any], dict[str, Any]], ...] = (
    ("abl-full", "full OverlapMamba", {}, {}),
    ("abl-oldloss", "the recipe before issue 20 (absolute margin 0.5, λ 0.1, …)", {}, OLD_LOSS),
    ("abl-triplet", "triplet loss instead of ImTrihard", {}, {"loss": "triplet"}),
    ("abl-noshift", "no shift", {"shift": False}, {}),
    ("abl-nospp", "without SPP", {"spp": False}, {}),
    ("abl-open", "non-circular scan and padding", {"circular": False}, {}),
    ("abl-2blocks", "2 Mamba blocks", {"n_blocks": 2}, {}),
    ("abl-ot", "OverlapTransformer-style baseline", _OT, {}),
)
for _name, _what, _model, _train in _ABLATIONS:
    for _seed in (0, 1):
        _p = TrainPreset(
            _name + ("-s1" if _seed else ""),
            f"ablation budget: {_what}" + (", seed 1" if _seed else ""),
            model={**NARROW, **_model},
            train={**ABLATION, **_train, **({"seed": 1} if _seed else {})},
        )
        PRESETS[_p.name] = _p


def get_preset(name: str) -> TrainPreset:
    if name not in PRESETS:
        raise ConfigError(f"unknown training preset {name!r}; allowed: {', '.join(PRESETS)}")
    return PRESETS[name]
