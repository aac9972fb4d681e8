"""The recipes on several sensors (issue 40) behind the training presets
(:mod:`overlapmamba.train.presets`): continuations of the shipped network on renderings and
drawn towns, the common, structure and bird's-eye inputs, their data and validation
renderings, and the presets made of them (:data:`SENSOR_PRESETS`):

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
  lent GPU, and ``bev-span-long`` the same without the term (its control).
"""

from __future__ import annotations

from overlapmamba.train.recipes import NARROW, NARROW_HN_AUG, TURN, TrainPreset

# Issue 40's first step: the shipped network continued on train-b and its renderings by three
# other sensors on low or tilted mounts (overlapmamba.synth.presets.RENDERINGS; one pair table
# for all four, overlapmamba.train.drives), against the same continuation on train-b alone.
SENSORS_PILOT_DATA = (
    "data/synth/train-b",
    "data/synth/train-b-vlp16-robot",
    "data/synth/train-b-os0-128-amr",
    "data/synth/train-b-xt32-backpack",
)
SENSORS_PILOT = {
    "init": "models/overlapmamba-hdl64.onnx",
    "freeze_bn": True,
    "epochs": 3,
    "epoch_scans": 3000,
    "lr": 3e-5,
    "warmup_steps": 20,
    "hard_negatives": 0.5,
    "any_sensor": True,
    "augment": {"beam_dropout": 0.2},
}


# The same continuation on train-b alone with no renderings: half of its scans are seen as
# another catalogue sensor would see them (augment.SensorLook) instead of losing rows at random.
SENSORS_SEEN = {**SENSORS_PILOT, "any_sensor": False, "augment": {"sensor_like": 0.5}}
# ... and the sensor term: 8 scans a batch also seen as another sensor, their distance to
# the batch's copy joining the loss at weight 1, as the ranking loss itself
SENSORS_SEEN_LOOK = {**SENSORS_SEEN, "look_weight": 1.0, "look_scans": 8}
# ... at a third of that weight
SENSORS_SEEN_LOOK_LIGHT = {**SENSORS_SEEN_LOOK, "look_weight": 0.3}
# ... and far returns lost as other sensors lose them (augment: far_loss).
SENSORS_SEEN_FAR = {**SENSORS_SEEN, "augment": {"sensor_like": 0.5, "far_loss": 0.4}}


# Many towns: sensors-seen's budget and start on train-b and the first six drawn towns
# (overlapmamba.synth.presets.drawn_town: VLP-16, OS0-128, XT32, OS1-128, HDL-32E and the
# HDL-64E, on drawn mountings, heights and tilts, each town with its own pair table); the
# model's own sensor's scans are still seen as other sensors' half of the time.
SENSORS_TOWNS_DATA = (
    "data/synth/train-b",
    *(f"data/synth/train-x{k:02d}" for k in range(6)),
)
SENSORS_TOWNS = {**SENSORS_SEEN, "any_sensor": True}
# ... and the same towns, sensors and drives with every sensor on a car's roof, level: the
# ablation of the drawn mountings, heights and tilts
SENSORS_TOWNS_CAR_DATA = (
    "data/synth/train-b",
    *(f"data/synth/train-x{k:02d}-car" for k in range(6)),
)


# One pass a scan: sensors-seen with the turn term (TURN's weight and turned scans),
# selected on the sensor towns' validation drive and its renderings by every other sensor
# the across-sensor bars name (train.valsensors).
SENSOR_VAL = "data/synth/val-kitti-hdl64"
SENSOR_VAL_RENDERINGS = tuple(
    f"data/synth/val-{s}" for s in ("vlp16", "os0-128", "xt32", "os1-128", "hdl32")
)
SENSORS_SEEN_TURN = {
    **SENSORS_SEEN,
    "turn_weight": TURN["turn_weight"],
    "turn_scans": TURN["turn_scans"],
    "val_sensors": list(SENSOR_VAL_RENDERINGS),
    "select_on": "sensors",
}

# Common beams (overlapmamba.core.sensors.input, mode "common"): the shipped network
# continued on every sensor's scans thinned to the beams nearest the VLP-16's elevations, the
# HDL-64E's own too, on train-b and the first four drawn towns (VLP-16, OS0-128, XT32,
# OS1-128: the sensors the across-sensor bars name), selected on the mean over the sensor
# validation drive and its renderings by those four. The input changed, so the rate is the
# recipe's own (not a continuation's tenth); batch norm stays frozen as in every continuation.
COMMON_MODEL = {**NARROW, "sensor_input": "common"}
COMMON_DATA = ("data/synth/train-b", *(f"data/synth/train-x{k:02d}" for k in range(4)))
COMMON_VAL_RENDERINGS = tuple(
    f"data/synth/val-{s}" for s in ("vlp16", "os0-128", "xt32", "os1-128")
)
COMMON = {
    "init": "models/overlapmamba-hdl64.onnx",
    "freeze_bn": True,
    "epochs": 4,
    "epoch_scans": 4000,
    "lr": 1e-4,
    "warmup_steps": 20,
    "hard_negatives": 0.5,
    "any_sensor": True,
    "val_sensors": list(COMMON_VAL_RENDERINGS),
    "select_on": "sensors",
}
# ... at a continuation's rate (TURN's and the sensor pilots'): common-towns collapsed at 1e-4
COMMON_SLOW = {**COMMON, "lr": 3e-5}
# The structure input (common beams above the ground, within 50 m), trained from scratch: no
# network has seen such images, and the continuations of the HDL-64E network on common beams
# lost on every sensor. The towns, validation and selection are common-towns'; the recipe's
# rate, live batch norm, hard negatives and the augmentations (sub-column turns,
# dropped returns, range noise), 5 epochs of 6,000 scans (≈ 75 min on 2 CPU cores).
STRUCTURE_MODEL = {**NARROW, "sensor_input": "structure"}
STRUCTURE = {
    "epochs": 5,
    "epoch_scans": 6000,
    "hard_negatives": 0.5,
    "any_sensor": True,
    "augment": NARROW_HN_AUG,
    "val_sensors": list(COMMON_VAL_RENDERINGS),
    "select_on": "sensors",
}
# The structure recipe for a lent GPU (benchmarks/lent_gpu.py: the towns simulated again
# there, three runs side by side), 40 epochs planned and the window deciding how many run:
# on common-towns' five towns (structure-long), on train-b and all twelve drawn towns
# (structure-many: what more towns are worth at an equal budget), and on those with train-b's
# renderings by a robot's VLP-16, an AMR's OS0-128 and a backpack's XT32 (structure-many-
# renders: the same places seen by several sensors, labelled by train-b's pair table).
STRUCTURE_LONG = {**STRUCTURE, "epochs": 40}
MANY_TOWNS = ("data/synth/train-b", *(f"data/synth/train-x{k:02d}" for k in range(12)))
TRAIN_B_RENDERINGS = tuple(
    f"data/synth/train-b-{r}" for r in ("vlp16-robot", "os0-128-amr", "xt32-backpack")
)

# The structure network saw few of its rings: the reference backbone on 64 rows reaches the
# descriptor from rows 0–26 only (overlapmamba.train.model._backbone), where the common
# beams fill five. structure-all-rows-long: structure-long with every row reaching it.
STRUCTURE_ALL_ROWS_MODEL = {**STRUCTURE_MODEL, "backbone": "all-rows"}
# The bev input (overlapmamba.core.sensors.input: a polar bird's-eye occupancy of every
# scan's returns, rings of range × height bands in the rows), from scratch on the structure
# recipe's towns, validation and selection, every row reaching the descriptor. Its cells are
# 1 or empty, so range noise means nothing to it: sub-column turns and dropped returns only.
BEV_MODEL = {**NARROW, "sensor_input": "bev", "backbone": "all-rows"}
BEV = {**STRUCTURE, "augment": {"yaw_jitter": True, "dropout": 0.2}}
BEV_LONG = {**BEV, "epochs": 40}

# bev-long's network continued for one short epoch, with the sensor term on the bev input (8
# scans a batch also seen through the beams of a sparser catalogue sensor, pulled to their
# copies at weight 1: train_inputs.Images.sparser), and its control without the term: whether
# the term moves the VLP-16's scans towards the others' (bev-long's weakest pair).
BEV_THIN_PILOT = {
    **BEV,
    "init": "runs/bev-long/best.pt",
    "epochs": 1,
    "epoch_scans": 3000,
    "lr": 5e-5,
    "warmup_steps": 20,
    "look_weight": 1.0,
    "look_scans": 8,
}
BEV_THIN_PILOT_CONTROL = {**BEV_THIN_PILOT, "look_weight": 0.0}

# The bev-soft input (each return shared between its two nearest columns: the image moves
# with a turn instead of jumping a column): bev-long's network continued on it with
# bev-thin-pilot-control's recipe (whose network continued on bev).
BEV_SOFT_MODEL = {**BEV_MODEL, "sensor_input": "bev-soft"}
# The same on bev-span (each cell: how much of its column its returns' one-column spans
# cover), whose cells do not depend on how densely a surface is sampled where bev-soft's do.
BEV_SPAN_MODEL = {**BEV_MODEL, "sensor_input": "bev-span"}
# bev-thin-pilot with the sensor term four times as heavy: whether pulling sparser copies
# harder keeps closing the gap (at weight 1 a copy ends nearer its scan than the batch's
# positives are, where a thinned real query must be nearer than scans a metre away).
BEV_HEAVY_PILOT = {**BEV_THIN_PILOT, "look_weight": 4.0}
# bev-span-thin-pilot's pick continued for a second short epoch by the same recipe: whether
# the term's gains keep growing with more steps.
BEV_SPAN_THIN_MORE = {**BEV_THIN_PILOT, "init": "runs/bev-span-thin-pilot/best.pt"}
# What the pilots point to, from scratch for a lent GPU: bev-long on bev-span with the
# sparser-sensor term (bev-thin-pilot's weight and scans).
BEV_SPAN_THIN_LONG = {**BEV_LONG, "look_weight": 1.0, "look_scans": 8}

# The presets made of these recipes, in the order `overlapmamba train --help` lists them.
SENSOR_PRESETS: tuple[TrainPreset, ...] = (
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
        "bev-span-long",
        "bev-long on bev-span without the term (bev-span-thin-long's control), for a lent GPU",
        model=BEV_SPAN_MODEL,
        train=BEV_LONG,  # bev-long's recipe on bev-span: what the term is worth
        data=COMMON_DATA,
        val=SENSOR_VAL,
    ),
)
