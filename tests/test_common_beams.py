"""The ``common`` sensor input: every sensor's scan, the model's own too, thinned to its beams
nearest a common sensor's elevations and projected as that sensor's scan, and ``structure``
(the same, above the ground and within a common range); in the core, the service's encoder
and training."""

from __future__ import annotations

import numpy as np
import pytest
from service_kit import MODEL, scan
from test_catalogue import _cloud

from overlapmamba.core.errors import ProfileError
from overlapmamba.core.points import PointCloud
from overlapmamba.core.sensors import CATALOGUE, Sensor, get_profile, sensor_of_profile
from overlapmamba.core.sensors.catalogue import COMMON_MAX_RANGE
from overlapmamba.core.sensors.input import (
    COMMON_MODES,
    COMMON_SENSOR,
    COMMON_TOLERANCE_DEG,
    SensorInput,
    common_beams,
    project_input_reference,
    row_beams,
)
from overlapmamba.core.sensors.mount import GROUND_CLEARANCE, REFERENCE_HEIGHT, Mount

KITTI = get_profile("kitti-hdl64")
SENSORS = ("kitti-hdl64", "vlp16", "xt32", "os1-128", "os0-128", "hdl32")


def _at(elevation_deg: float, r: float = 20.0, az_deg: float = 30.0) -> np.ndarray:
    el, az = np.radians(elevation_deg), np.radians(az_deg)
    return np.array([[r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)]])


def _rows_hit(image: np.ndarray) -> list[int]:
    return np.flatnonzero((image > 0).any(1)).tolist()


@pytest.mark.parametrize("mode", COMMON_MODES)
@pytest.mark.parametrize("name", SENSORS)
def test_fast_common_projection_matches_the_reference(name, mode):
    xyz = _cloud(4000, 3)
    inp = SensorInput(KITTI, CATALOGUE[name], mode)
    got = inp.project(xyz)[0]
    np.testing.assert_array_equal(got, project_input_reference(xyz, KITTI, CATALOGUE[name], mode))
    # only the common sensor's rows are ever filled
    common_rows = row_beams(KITTI, CATALOGUE[COMMON_SENSOR], "elevation") >= 0
    assert (got[~common_rows] == KITTI.empty_value).all() and (got[common_rows] > 0).any()


def test_the_models_own_sensor_is_thinned_too_and_cached_apart():
    own = SensorInput(KITTI, sensor_of_profile(KITTI), "common")
    plain = SensorInput(KITTI, sensor_of_profile(KITTI), "elevation")
    assert not own.native and own.kind == "common" and plain.native
    assert own.key() != plain.key() == {}
    assert own.key()["common"] == {"sensor": COMMON_SENSOR, "tolerance_deg": COMMON_TOLERANCE_DEG}
    xyz = _cloud(20000, 4)
    thin, full = own.project(xyz)[0], plain.project(xyz)[0]
    # the KITTI HDL-64E keeps 10 beams (those nearest the VLP-16's +1°, −1°, …, −15°), each
    # shown on the rows of its VLP-16 beam
    assert common_beams(CATALOGUE["kitti-hdl64"]).size == 10
    distinct = {r.tobytes() for r in thin if (r > 0).any()}
    assert len(distinct) == 10 and len({r.tobytes() for r in full if (r > 0).any()}) == 64


@pytest.mark.parametrize("name", SENSORS)
def test_a_place_on_a_common_beam_lands_on_the_same_rows_whatever_the_sensor(name):
    """A return on each sensor's beam nearest −7° (a VLP-16 beam) fills the rows of the
    VLP-16's −7° beam; a return between two common beams (−8°, on a beam of the dense
    sensors) is dropped by every sensor."""
    sensor = CATALOGUE[name]
    inp = SensorInput(KITTI, sensor, "common")
    el = np.asarray(sensor.elevations_deg)
    nearest = float(el[np.argmin(np.abs(el + 7.0))])
    want = np.flatnonzero(
        row_beams(KITTI, CATALOGUE[COMMON_SENSOR], "elevation")
        == list(CATALOGUE[COMMON_SENSOR].elevations_deg).index(-7.0)
    ).tolist()
    assert _rows_hit(inp.project(_at(nearest))[0]) == want and len(want) >= 4
    off = float(el[np.argmin(np.abs(el + 8.0))])
    if abs(off + 8.0) < 0.2:  # the sensor has a beam there
        assert _rows_hit(inp.project(_at(off))[0]) == []


def test_common_beams_are_found_in_the_sensors_own_frame():
    """A tilted sensor's return on its common beam stays in, though levelling moves it off
    that beam's elevation (onto one of the HDL-64E's other beams)."""
    hdl = CATALOGUE["kitti-hdl64"]
    el = np.asarray(hdl.elevations_deg)
    on = float(el[np.argmin(np.abs(el + 7.0))])
    tilted = SensorInput(KITTI, hdl, "common", Mount(height=REFERENCE_HEIGHT, pitch_deg=0.6))
    point = _at(on, r=40.0, az_deg=0.0)
    assert _rows_hit(tilted.project(point)[0])  # kept, and levelled where it really lies
    # thinned after levelling it would have been lost: no common beam is that near
    from overlapmamba.core.sensors.mount import to_reference

    levelled = to_reference(point, tilted.mount)  # type: ignore[arg-type]
    level = SensorInput(KITTI, hdl, "common")
    assert _rows_hit(level.project(levelled)[0]) == []


def test_structure_keeps_what_stands_above_the_reference_ground_within_the_common_range():
    """A robot's VLP-16 half a metre up: its return off the road 4 m ahead is ground once the
    scan is moved to the reference mount, and dropped; its return off a wall 10 m away,
    0.67 m above the road, stays. The KITTI car's return just under the clearance is
    dropped, just over it kept, and anything beyond the common range is dropped, whatever
    the sensor reaches."""
    vlp, hdl = CATALOGUE["vlp16"], CATALOGUE["kitti-hdl64"]
    robot = SensorInput(KITTI, vlp, "structure", Mount(height=0.5))
    road = _at(-7.0, r=0.5 / np.sin(np.radians(7.0)))
    wall = _at(1.0, r=10.0)
    assert _rows_hit(robot.project(road)[0]) == []
    assert _rows_hit(SensorInput(KITTI, vlp, "common", Mount(height=0.5)).project(road)[0])
    assert _rows_hit(robot.project(wall)[0])
    car = SensorInput(KITTI, hdl, "structure")
    el = np.asarray(hdl.elevations_deg)
    on = float(el[np.argmin(np.abs(el + 5.0))])
    low = REFERENCE_HEIGHT - GROUND_CLEARANCE  # a return just under the clearance is ground
    assert _rows_hit(car.project(_at(on, r=(low + 0.01) / np.sin(np.radians(-on))))[0]) == []
    assert _rows_hit(car.project(_at(on, r=(low - 0.01) / np.sin(np.radians(-on))))[0])
    assert _rows_hit(car.project(_at(on, r=COMMON_MAX_RANGE + 0.5))[0]) == []
    assert _rows_hit(SensorInput(KITTI, hdl, "common").project(_at(on, r=60.0))[0])
    assert car.kind == "structure" and not car.native
    assert car.key()["structure"] == {
        "clearance_m": GROUND_CLEARANCE,
        "ground_m": REFERENCE_HEIGHT,
        "max_range_m": COMMON_MAX_RANGE,
    }
    assert car.key() != SensorInput(KITTI, hdl, "common").key()


def test_a_sensor_with_no_common_beam_is_refused_by_name(tmp_path):
    high = Sensor(
        name="sky-16",
        title="a sensor looking up",
        source="a test",
        elevations_deg=tuple(np.linspace(45, 20, 16)),
        columns=1024,
        min_range=0.5,
        max_range=100.0,
        range_sigma=0.01,
    )
    for mode in COMMON_MODES:
        with pytest.raises(ValueError, match="'sky-16' has no beam within 0.5° of the common"):
            SensorInput(KITTI, high, mode)
    SensorInput(KITTI, high, "elevation")  # other modes take it (an empty image)
    with pytest.raises(
        ValueError, match="elevation-fill, elevation-reach, rows, common, structure"
    ):
        SensorInput(KITTI, high, "stretch")  # type: ignore[arg-type]

    # a service whose model takes common beams refuses such a sensor file at start
    from overlapmamba.service.sensors import Sensors
    from overlapmamba.train.modelfile import read_metadata

    path = tmp_path / "sky-16.json"
    path.write_text(high.model_dump_json())
    meta = read_metadata(MODEL).model_copy(update={"sensor_input": "common"})
    with pytest.raises(ProfileError, match="sky-16.json.*no beam within 0.5°"):
        Sensors(meta, [path])
    # and one taking the sensor's own elevations too, since every scan of it would be an
    # empty image (none of its beams falls in the model's rows)
    with pytest.raises(ProfileError, match="none of 'sky-16''s beams .* model's image"):
        Sensors(read_metadata(MODEL), [path])


@pytest.mark.parametrize("mode", COMMON_MODES)
def test_a_file_taking_common_beams_thins_every_scan_the_service_describes(tmp_path, mode):
    from service_kit import rewritten

    from overlapmamba.service.encoder import Encoder
    from overlapmamba.service.sensors import Sensors

    enc = rewritten(tmp_path, mode)
    cloud = PointCloud(scan(3)[:, :3])
    own = Sensors(enc.meta).input("kitti-hdl64")
    assert own.kind == mode
    np.testing.assert_array_equal(enc.project(cloud), own.project(cloud, enc.views))
    np.testing.assert_array_equal(enc.project(cloud, own), enc.project(cloud))
    assert not np.array_equal(enc.project(cloud), Encoder(MODEL).project(cloud))
    assert Sensors(enc.meta).input("vlp16").kind == mode


def test_training_takes_the_models_own_scans_by_its_configs_input(tiny_seq):
    pytest.importorskip("torch")
    from conftest import SMALL_MODEL

    from overlapmamba.core.datasets import open_sequence
    from overlapmamba.train.checkpoint import sensor_input_of
    from overlapmamba.train.errors import ConfigError
    from overlapmamba.train.model import OverlapMamba, OverlapMambaConfig
    from overlapmamba.train.train_inputs import Images, training_input

    seq = open_sequence(tiny_seq)
    assert training_input(KITTI, seq) is None
    inp = training_input(KITTI, seq, "common")
    assert inp is not None and inp.kind == "common"
    images = Images([seq], KITTI, progress=False, mode="common")
    got = images[np.array([3])][0]
    np.testing.assert_allclose(got, inp.project(seq.points(3))[0], atol=0.05)
    assert not images.native(np.array([3]))[0]  # sensor_like never re-renders a common image
    cfg = OverlapMambaConfig(**SMALL_MODEL, sensor_input="common")
    assert sensor_input_of(OverlapMamba(cfg)) == "common"
    with pytest.raises(ConfigError, match="sensor_input 'stretch' is unknown; allowed"):
        OverlapMambaConfig(**SMALL_MODEL, sensor_input="stretch")


@pytest.mark.timeout(900)  # when run alone, its set-up waits for the tiny towns and run
def test_a_run_continues_a_file_on_its_input_and_exports_it(
    tiny_seq, tiny_val_seq, tiny_run, tiny_onnx, tmp_path
):
    """A continuation of a file stamped ``common`` (``overlapmamba export --sensor-input``)
    trains and validates on common images and exports a file that says so; a config given
    alongside may name another input, never another shape."""
    pytest.importorskip("torch")
    from conftest import SMALL_MODEL, small_run
    from typer.testing import CliRunner

    from overlapmamba.cli import app
    from overlapmamba.core.datasets import open_sequence
    from overlapmamba.train.checkpoint import load_model, read_checkpoint
    from overlapmamba.train.errors import ConfigError
    from overlapmamba.train.export import export_onnx
    from overlapmamba.train.model import OverlapMambaConfig
    from overlapmamba.train.modelfile import read_metadata
    from overlapmamba.train.rangecache import cache_key
    from overlapmamba.train.train import train
    from overlapmamba.train.train_config import TrainConfig
    from overlapmamba.train.train_inputs import start_config

    profile = load_model(tiny_run[0] / "epoch-002.pt")[1]
    plain = tiny_onnx  # that checkpoint exported (read, never written)
    start = tmp_path / "start.onnx"
    res = CliRunner().invoke(
        app, ["export", str(plain), "--out", str(start), "--sensor-input", "common"]
    )
    assert res.exit_code == 0, res.output
    assert read_metadata(start).sensor_input == "common"
    bad = CliRunner().invoke(app, ["export", str(plain), "--out", "x.onnx", "--sensor-input", "x"])
    said = " ".join(bad.output.replace("│", " ").split())  # the error box wraps its lines
    assert bad.exit_code != 0 and "must be one of elevation, elevation-lerp, elevation-fill" in said

    cont = TrainConfig(init=str(start), freeze_bn=True)
    assert start_config(cont, None).sensor_input == "common"
    other = OverlapMambaConfig(**SMALL_MODEL, sensor_input="elevation")
    assert start_config(cont, other).sensor_input == "elevation"
    with pytest.raises(ConfigError, match="a network with other d_model"):
        start_config(cont, OverlapMambaConfig(**{**SMALL_MODEL, "d_model": 16}))

    out = tmp_path / "run"
    run = small_run(epochs=1, init=str(start), freeze_bn=True)
    train([tiny_seq], tiny_val_seq, out, None, run, progress=False)
    ckpt = read_checkpoint(out / "best.pt")
    assert ckpt["model_config"]["sensor_input"] == "common"
    val_seq = open_sequence(tiny_val_seq)
    own = SensorInput(KITTI, sensor_of_profile(KITTI), "common")
    assert ckpt["train"]["data"]["val"]["key"] == cache_key(val_seq, KITTI, sensor=own)
    trained, _, _ = load_model(out / "best.pt")
    meta = export_onnx(trained, profile, tmp_path / "after.onnx", checkpoint=ckpt).metadata
    assert meta.sensor_input == "common"


def test_a_runs_summary_keeps_each_epochs_validation_and_health(tiny_run):
    """benchmarks/run_summary.py: what a run's metrics.json says per epoch, no step losses."""
    import sys
    from pathlib import Path

    bench = str(Path(__file__).resolve().parents[1] / "benchmarks")
    sys.path.insert(0, bench)
    try:
        import run_summary
    finally:
        sys.path.remove(bench)
    run, history = tiny_run
    got = run_summary.summary(run)
    assert got["epochs_run"] == got["epochs_planned"] == 2 and len(got["epochs"]) == 3
    for row, e in zip(got["epochs"], history, strict=True):
        assert row["val"]["all"]["f1max"] == e["val"]["all"]["f1max"]
        assert row["score"] == pytest.approx(e["val"]["all"]["f1max"])  # select_on val
        assert "step_losses" not in row and set(row["health"]) >= {"spread", "d_pos"}
    assert got["epochs"][1]["health"]["spread"] == history[1]["health"]["spread"]
    # where the time went: epoch 0 recalibrates and validates, a training epoch trains too
    assert set(got["epochs"][0]["seconds"]) == {"calibrate", "validate"}
    assert got["epochs"][1]["seconds"]["train"] == history[1]["train_s"] > 0
    total = sum(sum(row["seconds"].values()) for row in got["epochs"])
    assert got["seconds"] == pytest.approx(total) and total > 0
