"""The recipes on several sensors (issue 40) behind the training presets
(:mod:`overlapmamba.train.presets`): continuations of the shipped network on renderings and
drawn towns, the common and structure inputs, and their data and validation renderings."""

from __future__ import annotations

from overlapmamba.train.recipes import NARROW, NARROW_HN_AUG, TURN

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
