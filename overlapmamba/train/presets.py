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
- ``sensors-pilot`` continues the shipped network (as ``narrow-hn-turn`` does) on
  ``train-b`` and its renderings by a robot's VLP-16, an AMR's OS0-128 and a backpack's XT32
  (``gen-data data/synth/train-b-vlp16-robot --preset train-b-vlp16-robot`` and so on: no pair
  tables of their own, the drive's serves them all), taking every sensor's scans as the
  service does and emptying whole rows at random (``beam_dropout``); 3 epochs of 3,000
  scans. ``sensors-pilot-control`` is the same continuation on ``train-b`` alone: what the
  renderings add, at an equal budget. ``sensors-seen`` is the control with every sensor
  simulated instead of rendered: half of the scans are seen as another catalogue sensor
  would see them (``sensor_like``: its beams' rows of the image, its range limits), no
  ``beam_dropout``. ``sensors-seen-far`` adds ``far_loss`` (far returns lost first, as the
  other sensors' renderings lose them); ``sensors-seen-look`` adds the sensor term (each
  batch's scans pulled towards their copies seen as another sensor, ``look_weight``;
  ``sensors-seen-look-light`` at 0.3). Each but the last has a ``-s1`` twin: the same with
  seed 1.
  ``sensors-seen-turn`` adds the turn term (one pass a scan) and validates on
  ``val-kitti-hdl64`` and its renderings by five other sensors, keeping the epoch with the
  best mean over them all (``select_on = "sensors"``).
- ``common-towns`` continues the shipped network on the ``common`` input (every sensor's
  beams nearest the VLP-16's elevations, the HDL-64E's own too) on train-b and four drawn
  towns, selected as ``sensors-seen-turn`` is, on four renderings; ``common-towns-slow`` at
  a continuation's rate.
- ``structure-towns`` trains from scratch on the ``structure`` input (common beams, only
  what stands above the ground, within 50 m) on common-towns' towns, validation and
  selection, with the issue's augmentations.
- ``structure-long``, ``structure-many`` and ``structure-many-renders`` are
  ``structure-towns`` for a lent GPU's window (``benchmarks/lent_gpu.py``): 40 epochs
  planned, as many as the window allows run; on its five towns, on train-b and the twelve
  drawn towns, and on those with train-b's renderings by three other sensors.
  ``structure-all-rows-long`` is ``structure-long`` with every row reaching the descriptor
  (the ``all-rows`` backbone).
- ``bev-towns`` trains from scratch on the ``bev`` input (a polar bird's-eye occupancy of
  every scan: rings of range × height bands in the rows) on structure-towns' towns,
  validation and selection; ``bev-long`` (and ``bev-long-s1``, seed 1) for a lent GPU.
  ``bev-thin-pilot`` continues ``bev-long``'s network for one short epoch with the sensor
  term seeing scans through a sparser sensor's beams; ``bev-thin-pilot-control`` without it.
- ``bev-soft-pilot`` is that control on the ``bev-soft`` input (each return shared between
  its two nearest columns), ``bev-span-pilot`` on ``bev-span`` (each cell: how much of its
  column its returns' spans cover), ``bev-span-thin-pilot`` ``bev-thin-pilot`` on
  ``bev-span`` (these two also with seed 1, ``-s1``: whether the term's gain is more than
  a seed's), ``bev-span-heavy-pilot`` the same with the term four times as heavy,
  ``bev-span-renders-pilot`` with train-b's renderings by three other sensors in its data
  (the same places seen by other sensors, on other mounts, as positives),
  ``bev-span-thin-more`` ``bev-span-thin-pilot``'s pick continued for a second epoch;
  ``bev-span-thin-long`` (and ``-s1``) from scratch on it with the term, for a
  lent GPU.
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

from dataclasses import dataclass, field, replace
from typing import Any

from overlapmamba.train.augment import ROBUST
from overlapmamba.train.errors import ConfigError
from overlapmamba.train.recipes import (
    ABLATION,
    BAND,
    DEFAULT,
    NARROW,
    NARROW_HN,
    NARROW_HN_AUG,
    OLD_LOSS,
    TURN,
)
from overlapmamba.train.sensor_recipes import (
    BEV,
    BEV_HEAVY_PILOT,
    BEV_LONG,
    BEV_MODEL,
    BEV_SOFT_MODEL,
    BEV_SPAN_MODEL,
    BEV_SPAN_THIN_LONG,
    BEV_SPAN_THIN_MORE,
    BEV_THIN_PILOT,
    BEV_THIN_PILOT_CONTROL,
    COMMON,
    COMMON_DATA,
    COMMON_MODEL,
    COMMON_SLOW,
    MANY_TOWNS,
    SENSOR_VAL,
    SENSORS_PILOT,
    SENSORS_PILOT_DATA,
    SENSORS_SEEN,
    SENSORS_SEEN_FAR,
    SENSORS_SEEN_LOOK,
    SENSORS_SEEN_LOOK_LIGHT,
    SENSORS_SEEN_TURN,
    SENSORS_TOWNS,
    SENSORS_TOWNS_CAR_DATA,
    SENSORS_TOWNS_DATA,
    STRUCTURE,
    STRUCTURE_ALL_ROWS_MODEL,
    STRUCTURE_LONG,
    STRUCTURE_MODEL,
    TRAIN_B_RENDERINGS,
)

TRAIN_DATA = (
    "data/synth/train",
    "data/synth/train-b",
    "data/synth/train-c",
    "data/synth/train-d",
)
ONE_TOWN = ("data/synth/train",)
VAL_DATA = "data/synth/val"
TEST_DATA = ("data/synth/test", "data/synth/test-b", "data/synth/test-c")
SECOND_SESSION = "data/synth/test-s1"  # a second drive through TEST_DATA[0]
# The run whose best.pt is exported to models/overlapmamba-hdl64.onnx (the model card says
# why); the report marks its row "(shipped)" and checks it on real scans.
SHIPPED = "narrow-hn"


@dataclass(frozen=True)
class TrainPreset:
    name: str
    description: str
    model: dict[str, Any] = field(default_factory=dict)  # OverlapMambaConfig overrides
    train: dict[str, Any] = field(default_factory=dict)  # TrainConfig overrides
    data: tuple[str, ...] = TRAIN_DATA
    val: str = VAL_DATA


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
            "sensors-pilot",
            "the shipped network continued on train-b and three other sensors' renderings of it",
            model=NARROW,
            train=SENSORS_PILOT,
            data=SENSORS_PILOT_DATA,
        ),
        TrainPreset(
            "sensors-pilot-control",
            "the same continuation on train-b alone (its own sensor)",
            model=NARROW,
            train={**SENSORS_PILOT, "any_sensor": False},
            data=SENSORS_PILOT_DATA[:1],
        ),
        TrainPreset(
            "sensors-seen",
            "the same continuation on train-b alone, half its scans seen as another sensor",
            model=NARROW,
            train=SENSORS_SEEN,
            data=SENSORS_PILOT_DATA[:1],
        ),
        TrainPreset(
            "sensors-seen-look",
            "sensors-seen with the sensor term (8 scans a batch pulled to their copy seen as "
            "another sensor)",
            model=NARROW,
            train=SENSORS_SEEN_LOOK,
            data=SENSORS_PILOT_DATA[:1],
        ),
        TrainPreset(
            "sensors-seen-look-light",
            "sensors-seen-look at look_weight 0.3",
            model=NARROW,
            train=SENSORS_SEEN_LOOK_LIGHT,
            data=SENSORS_PILOT_DATA[:1],
        ),
        TrainPreset(
            "sensors-seen-far",
            "sensors-seen with far returns lost in proportion to range (far_loss 0.4)",
            model=NARROW,
            train=SENSORS_SEEN_FAR,
            data=SENSORS_PILOT_DATA[:1],
        ),
        TrainPreset(
            "sensors-towns",
            "sensors-seen's budget on train-b and six drawn towns of other sensors and mounts",
            model=NARROW,
            train=SENSORS_TOWNS,
            data=SENSORS_TOWNS_DATA,
        ),
        TrainPreset(
            "sensors-towns-car",
            "sensors-towns with every drawn town's sensor on a car's roof, level",
            model=NARROW,
            train=SENSORS_TOWNS,
            data=SENSORS_TOWNS_CAR_DATA,
        ),
        TrainPreset(
            "sensors-seen-turn",
            "sensors-seen with the turn term, selected on every sensor's validation drive",
            model=NARROW,
            train=SENSORS_SEEN_TURN,
            data=SENSORS_PILOT_DATA[:1],
            val=SENSOR_VAL,
        ),
        TrainPreset(
            "common-towns",
            "the shipped network continued on every sensor's common beams, five towns",
            model=COMMON_MODEL,
            train=COMMON,
            data=COMMON_DATA,
            val=SENSOR_VAL,
        ),
        TrainPreset(
            "common-towns-slow",
            "common-towns at a continuation's rate (3e-5)",
            model=COMMON_MODEL,
            train=COMMON_SLOW,
            data=COMMON_DATA,
            val=SENSOR_VAL,
        ),
        TrainPreset(
            "structure-towns",
            "from scratch on every sensor's common beams above the ground, five towns",
            model=STRUCTURE_MODEL,
            train=STRUCTURE,
            data=COMMON_DATA,
            val=SENSOR_VAL,
        ),
        TrainPreset(
            "structure-long",
            "structure-towns for a lent GPU's window (40 epochs planned)",
            model=STRUCTURE_MODEL,
            train=STRUCTURE_LONG,
            data=COMMON_DATA,
            val=SENSOR_VAL,
        ),
        TrainPreset(
            "structure-many",
            "structure-long on train-b and twelve drawn towns",
            model=STRUCTURE_MODEL,
            train=STRUCTURE_LONG,
            data=MANY_TOWNS,
            val=SENSOR_VAL,
        ),
        TrainPreset(
            "structure-many-renders",
            "structure-many with train-b's renderings by three other sensors",
            model=STRUCTURE_MODEL,
            train=STRUCTURE_LONG,
            data=(*MANY_TOWNS, *TRAIN_B_RENDERINGS),
            val=SENSOR_VAL,
        ),
        TrainPreset(
            "structure-all-rows-long",
            "structure-long with every row reaching the descriptor (all-rows backbone)",
            model=STRUCTURE_ALL_ROWS_MODEL,
            train=STRUCTURE_LONG,
            data=COMMON_DATA,
            val=SENSOR_VAL,
        ),
        TrainPreset(
            "bev-towns",
            "from scratch on the bev input (a polar bird's-eye occupancy), five towns",
            model=BEV_MODEL,
            train=BEV,
            data=COMMON_DATA,
            val=SENSOR_VAL,
        ),
        TrainPreset(
            "bev-long",
            "bev-towns for a lent GPU's window (40 epochs planned)",
            model=BEV_MODEL,
            train=BEV_LONG,
            data=COMMON_DATA,
            val=SENSOR_VAL,
        ),
        TrainPreset(
            "bev-thin-pilot",
            "bev-long's network, one short epoch with the sparser-sensor term",
            model=BEV_MODEL,
            train=BEV_THIN_PILOT,
            data=COMMON_DATA,
            val=SENSOR_VAL,
        ),
        TrainPreset(
            "bev-thin-pilot-control",
            "bev-thin-pilot without the sparser-sensor term",
            model=BEV_MODEL,
            train=BEV_THIN_PILOT_CONTROL,
            data=COMMON_DATA,
            val=SENSOR_VAL,
        ),
        TrainPreset(
            "bev-soft-pilot",
            "bev-thin-pilot-control on the bev-soft input (cells shared between columns)",
            model=BEV_SOFT_MODEL,
            train=BEV_THIN_PILOT_CONTROL,
            data=COMMON_DATA,
            val=SENSOR_VAL,
        ),
        TrainPreset(
            "bev-span-pilot",
            "bev-thin-pilot-control on the bev-span input (cells: their returns' spans)",
            model=BEV_SPAN_MODEL,
            train=BEV_THIN_PILOT_CONTROL,
            data=COMMON_DATA,
            val=SENSOR_VAL,
        ),
        TrainPreset(
            "bev-span-thin-pilot",
            "bev-thin-pilot on the bev-span input (the sparser-sensor term with the new cells)",
            model=BEV_SPAN_MODEL,
            train=BEV_THIN_PILOT,
            data=COMMON_DATA,
            val=SENSOR_VAL,
        ),
        TrainPreset(
            "bev-span-heavy-pilot",
            "bev-span-thin-pilot with the sparser-sensor term at weight 4",
            model=BEV_SPAN_MODEL,
            train=BEV_HEAVY_PILOT,
            data=COMMON_DATA,
            val=SENSOR_VAL,
        ),
        TrainPreset(
            "bev-span-renders-pilot",
            "bev-span-thin-pilot with train-b's renderings by three other sensors added",
            model=BEV_SPAN_MODEL,
            train=BEV_THIN_PILOT,
            data=(*COMMON_DATA, *TRAIN_B_RENDERINGS),
            val=SENSOR_VAL,
        ),
        TrainPreset(
            "bev-span-thin-more",
            "bev-span-thin-pilot's pick, a second short epoch by the same recipe",
            model=BEV_SPAN_MODEL,
            train=BEV_SPAN_THIN_MORE,
            data=COMMON_DATA,
            val=SENSOR_VAL,
        ),
        TrainPreset(
            "bev-span-thin-long",
            "bev-long on bev-span with the sparser-sensor term, for a lent GPU",
            model=BEV_SPAN_MODEL,
            train=BEV_SPAN_THIN_LONG,
            data=COMMON_DATA,
            val=SENSOR_VAL,
        ),
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
