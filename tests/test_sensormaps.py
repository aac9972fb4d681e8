"""Sensor maps: other sensors' descriptors moved into the model sensor's, fitted for one model
and carried in its file (overlapmamba.core.sensormaps), and the service applying them."""

from __future__ import annotations

import numpy as np
import pytest
from service_kit import MODEL, OCTET, running, scan

from overlapmamba.core.sensormaps import SensorMap, fit_map, maps_digest
from overlapmamba.service.encoder import Encoder
from overlapmamba.service.settings import Settings

STAMP = {"chosen_by": "tests/test_sensormaps.py", "data": "a test", "at": "2026-11-27T00:00:00"}


def unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def paired(rng: np.random.Generator, n: int = 300, dim: int = 16):
    """Unit descriptors of n places by the model sensor, and the same places by a sensor
    that mixes and offsets them."""
    model = unit(rng.normal(size=(n, dim)) * 0.3 + np.eye(dim)[0])
    mix = np.linalg.qr(rng.normal(size=(dim, dim)))[0]
    offset = rng.normal(size=dim) * 0.5
    return model, (model - model.mean(0)) @ mix + offset, offset


def test_maps_undo_a_sensors_offset_and_mixing_and_keep_unit_length():
    rng = np.random.default_rng(0)
    model, mixed, offset = paired(rng)
    linear = fit_map(mixed, model, "linear", **STAMP)
    np.testing.assert_allclose(linear.apply(mixed), model, atol=1e-5)
    shift = fit_map(model + offset, model, "shift", **STAMP)
    np.testing.assert_allclose(shift.apply(model + offset), model, atol=1e-5)
    one = linear.apply(mixed[0])  # one descriptor as well as a batch
    assert one.shape == (16,) and one.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(linear.apply(mixed), axis=1), 1.0, atol=1e-6)
    # a ridge shrinks the matrix, and the fitted map says what it was fitted on
    ridged = fit_map(mixed, model, "linear", ridge=0.1, **STAMP)
    assert np.linalg.norm(ridged.arrays()[2]) < np.linalg.norm(linear.arrays()[2])
    assert ridged.ridge == 0.1 and ridged.pairs == 300 and shift.ridge is None
    # the file's JSON gives the same map back
    again = SensorMap.model_validate_json(linear.model_dump_json())
    np.testing.assert_array_equal(again.apply(mixed), linear.apply(mixed))
    assert maps_digest({"vlp16": again}) == maps_digest({"vlp16": linear})
    assert maps_digest({"vlp16": linear}) != maps_digest({"vlp16": ridged})
    assert maps_digest({"vlp16": linear}) != maps_digest({"xt32": linear})


def test_bad_maps_and_inputs_are_refused_with_what_is_allowed():
    rng = np.random.default_rng(1)
    model, mixed, _ = paired(rng, 40)
    linear = fit_map(mixed, model, "linear", **STAMP)
    with pytest.raises(ValueError, match="allowed: shift, linear"):
        fit_map(mixed, model, "rotate", **STAMP)
    with pytest.raises(ValueError, match=r"two \(N ≥ 2, D\) arrays"):
        fit_map(mixed[:, :8], model, "linear", **STAMP)
    with pytest.raises(ValueError, match="this map takes 16"):
        linear.apply(np.ones((2, 8)))
    fields = linear.model_dump()
    with pytest.raises(ValueError, match="a 16² map needs 256"):
        SensorMap.model_validate(
            {**fields, "matrix": fit_map(mixed[:, :4], model[:, :4], "linear", **STAMP).matrix}
        )
    with pytest.raises(ValueError, match="a shift map has no matrix"):
        SensorMap.model_validate({**fields, "how": "shift"})
    with pytest.raises(ValueError, match="a linear map needs its matrix"):
        SensorMap.model_validate({**fields, "matrix": None})
    with pytest.raises(ValueError, match="not base64"):
        SensorMap.model_validate({**fields, "mean_in": "not base64!"})


def _map_for(dim: int, seed: int = 0) -> SensorMap:
    """A linear map of the model's dimension: a turn of the descriptor space."""
    rng = np.random.default_rng(seed)
    q = unit(rng.normal(size=(600, dim)))
    return fit_map(q, unit(q @ np.linalg.qr(rng.normal(size=(dim, dim)))[0]), "linear", **STAMP)


def test_a_model_file_carries_its_maps_in_its_id_and_refuses_stale_ones(tmp_path):
    from overlapmamba.train.errors import ExportError
    from overlapmamba.train.modelfile import (
        read_metadata,
        with_sensor_input,
        with_sensor_maps,
        with_views,
    )

    before = read_metadata(MODEL)
    m = _map_for(before.descriptor_dim)
    out = tmp_path / "mapped.onnx"
    meta = with_sensor_maps(MODEL, out, {"vlp16": m})
    assert meta.model_id != before.model_id and meta.graph == before.graph
    assert set(read_metadata(out).sensor_maps) == {"vlp16"}
    assert with_sensor_maps(out, tmp_path / "other.onnx", {"xt32": m}).model_id != meta.model_id
    assert with_sensor_maps(out, tmp_path / "plain.onnx", {}).model_id == before.model_id
    # views and the input mode change other sensors' descriptors: maps fitted before refuse
    with pytest.raises(ExportError, match="sensor maps fitted with views = 3"):
        with_views(out, tmp_path / "one.onnx", 1)
    with pytest.raises(ExportError, match="sensor maps fitted with sensor_input = elevation"):
        with_sensor_input(out, "rows")
    with pytest.raises(ExportError, match="'kitti-hdl64', the model's own sensor"):
        with_sensor_maps(MODEL, tmp_path / "own.onnx", {"kitti-hdl64": m})
    with pytest.raises(ExportError, match="not of the descriptor's dimension"):
        with_sensor_maps(MODEL, tmp_path / "small.onnx", {"vlp16": _map_for(8)})
    assert not (tmp_path / "own.onnx").exists() and not (tmp_path / "small.onnx").exists()
    # found in review: the maps change the descriptors the file's thresholds were chosen on,
    # yet the calibration was kept; adding, changing or removing them drops it
    assert before.calibration and not meta.calibration
    assert not read_metadata(tmp_path / "plain.onnx").calibration
    same = with_sensor_maps(out, tmp_path / "same.onnx", {"vlp16": m})
    assert same.model_id == meta.model_id


def test_a_map_for_a_custom_model_sensor_is_refused_by_the_name_scans_are_looked_up_by():
    """Found in review: the own-sensor check used the profile's name ("My Lidar") where the
    service looks a scan's sensor up by the catalogue name made of it ("my-lidar"), so a map
    under that name passed and mapped the model's own scans."""
    from overlapmamba.core.modelmeta import EncoderMetadata
    from overlapmamba.core.sensors.catalogue import sensor_of_profile

    meta = Encoder(MODEL, intra_op_threads=1, scan_kernel=False).meta
    custom = meta.profile.model_copy(update={"name": "My Lidar"})
    name = sensor_of_profile(custom).name
    assert name != custom.name
    fields = meta.model_dump(by_alias=True) | {"profile": custom.model_dump()}
    with pytest.raises(ValueError, match="the model's own sensor"):
        EncoderMetadata.model_validate(
            fields | {"sensor_maps": {name: _map_for(meta.descriptor_dim)}}
        )


def test_the_own_sensor_check_is_the_services_name_only_and_a_refused_file_can_be_repaired(
    tmp_path,
):
    """Found in review: (1) a profile named as a catalogue sensor but built otherwise is the
    service's "NAME-model", so the catalogue's NAME is another sensor, yet its map was
    refused; (2) metadata whose profile makes no service sensor (over 256 rows) failed to
    load although it carried no maps; (3) a file written before the check, with a map for
    its own sensor, could not have it removed: with_sensor_maps read it with the check."""
    from overlapmamba.core.modelmeta import EncoderMetadata
    from overlapmamba.core.sensors.catalogue import sensor_of_profile
    from overlapmamba.train.errors import ExportError
    from overlapmamba.train.modelfile import load_encoder, save_encoder, with_sensor_maps

    proto, meta = load_encoder(MODEL)
    m = _map_for(meta.descriptor_dim)
    retrained = meta.profile.model_copy(update={"max_range": meta.profile.max_range - 10})
    assert sensor_of_profile(retrained).name == "kitti-hdl64-model"
    fields = meta.model_dump(by_alias=True) | {"profile": retrained.model_dump()}
    ok = EncoderMetadata.model_validate(fields | {"sensor_maps": {"kitti-hdl64": m}})
    assert set(ok.sensor_maps) == {"kitti-hdl64"}
    with pytest.raises(ValueError, match="'kitti-hdl64-model', the model's own sensor"):
        EncoderMetadata.model_validate(fields | {"sensor_maps": {"kitti-hdl64-model": m}})
    tall = meta.profile.model_copy(update={"name": "tall", "rows": 300})
    EncoderMetadata.model_validate(meta.model_dump(by_alias=True) | {"profile": tall.model_dump()})
    # a file with a map for its own sensor, as the code before the check wrote them
    stale = meta.model_copy(update={"sensor_maps": {"kitti-hdl64": m}})
    save_encoder(proto, stale, tmp_path / "stale.onnx")
    with pytest.raises(ExportError, match="the model's own sensor.*with_sensor_maps"):
        load_encoder(tmp_path / "stale.onnx")
    mended = with_sensor_maps(tmp_path / "stale.onnx", tmp_path / "mended.onnx", {"vlp16": m})
    assert set(mended.sensor_maps) == {"vlp16"}
    assert set(load_encoder(tmp_path / "mended.onnx")[1].sensor_maps) == {"vlp16"}
    with pytest.raises(ExportError, match="the model's own sensor"):  # the new maps are checked
        with_sensor_maps(tmp_path / "stale.onnx", tmp_path / "no.onnx", {"kitti-hdl64": m})


pytestmark = pytest.mark.anyio


async def test_the_service_maps_the_descriptors_of_sensors_its_model_has_maps_for(tmp_path):
    from overlapmamba.train.modelfile import with_sensor_maps

    plain = Encoder(MODEL, intra_op_threads=2)
    m = _map_for(plain.dim)
    path = tmp_path / "mapped.onnx"
    with_sensor_maps(MODEL, path, {"vlp16": m})
    s = scan(4).tobytes()
    got = {}
    for name, enc in (("plain", plain), ("mapped", Encoder(path, intra_op_threads=2))):
        async with running(Settings(data_dir=tmp_path / name), enc) as c:
            for sensor in ("vlp16", "xt32", "kitti-hdl64"):
                r = await c.post(f"/v1/descriptors?sensor={sensor}", content=s, headers=OCTET)
                assert r.status_code == 200, r.text
                got[name, sensor] = np.array(r.json()["descriptor"])
            ready = (await c.get("/readyz")).json()["detail"]["sensor_maps"]
            listed = {
                x["name"]: x["descriptor_map"]
                for x in (await c.get("/v1/sensors")).json()["sensors"]
            }
            got[name, "ready"], got[name, "listed"] = ready, listed
    np.testing.assert_allclose(got["mapped", "vlp16"], m.apply(got["plain", "vlp16"]), atol=1e-5)
    assert float(got["mapped", "vlp16"] @ got["plain", "vlp16"]) < 0.99  # it did move
    for sensor in ("xt32", "kitti-hdl64"):  # no map: the network's descriptor
        np.testing.assert_allclose(got["mapped", sensor], got["plain", sensor], atol=1e-6)
    assert got["plain", "ready"] == {} and set(got["mapped", "ready"]) == {"vlp16"}
    assert got["mapped", "ready"]["vlp16"]["how"] == "linear"
    assert got["mapped", "listed"]["vlp16"] == "linear" and got["mapped", "listed"]["xt32"] is None


def test_an_encoder_describes_a_drive_in_batches_mapped_or_as_the_network_gives_it(tmp_path):
    from overlapmamba.core.points import PointCloud
    from overlapmamba.core.sensors import CATALOGUE
    from overlapmamba.core.sensors.input import SensorInput
    from overlapmamba.train.modelfile import with_sensor_maps

    path = tmp_path / "mapped.onnx"
    m = _map_for(Encoder(MODEL).dim)
    with_sensor_maps(MODEL, path, {"vlp16": m})
    enc = Encoder(path, intra_op_threads=2)
    vlp = SensorInput(enc.meta.profile, CATALOGUE["vlp16"], enc.meta.sensor_input)
    clouds = [PointCloud(scan(i)[:, :3].copy()) for i in range(3)]
    raw, yaw = enc.describe(clouds, vlp, batch=2, mapped=False)  # a full batch and a rest
    assert raw.shape == (3, enc.dim) and yaw.shape[0] == 3
    one, _ = enc.encode(enc.project(clouds[2], vlp)[None])
    np.testing.assert_allclose(raw[2], one[0], atol=1e-6)
    mapped, _ = enc.describe(iter(clouds), vlp)
    np.testing.assert_allclose(mapped, m.apply(raw), atol=1e-5)
    own, _ = enc.describe(clouds)  # the model's own sensor: never mapped
    np.testing.assert_allclose(own, enc.describe(clouds, mapped=False)[0], atol=0)
    with pytest.raises(ValueError, match="no scans to describe"):
        enc.describe([])


def test_the_rerank_grid_refuses_towns_of_a_sensor_its_file_maps(
    tmp_path, synthetic_seq_dir, monkeypatch, capsys
):
    """Found in review: benchmarks/rerank.py describes a town with the network alone; on a
    town of a sensor the file carries a map for, it would choose the service's second stage
    on descriptors the service never compares (loop_threshold.py was mended the same way)."""
    import json
    import shutil
    import sys

    from conftest import benchmark_module

    from overlapmamba.train.modelfile import read_metadata, with_sensor_maps

    mapped = tmp_path / "mapped.onnx"
    with_sensor_maps(MODEL, mapped, {"vlp16": _map_for(read_metadata(MODEL).descriptor_dim)})
    town = shutil.copytree(synthetic_seq_dir, tmp_path / "vlp16-town")
    (town / "manifest.json").write_text(json.dumps({"config": {"sensor": "vlp16"}}))
    rerank = benchmark_module("rerank")
    argv = ["rerank.py", "--model", str(mapped), "--val", str(town), "--second-session", str(town)]
    monkeypatch.setattr(sys, "argv", [*argv, "--out", str(tmp_path / "r.json")])
    with pytest.raises(SystemExit) as stop:
        rerank.main()
    assert stop.value.code == 2
    assert "carries a sensor map for vlp16" in capsys.readouterr().err


def test_eval_describes_a_drive_of_a_mapped_sensor_as_the_service_answers_it(
    tmp_path, synthetic_seq_dir
):
    """``overlapmamba eval`` (and the report, and across sessions) described every drive with
    the network alone, so a file carrying a map for the drive's sensor was scored on
    descriptors its service never gives. The map is applied; the yaw features and the model
    sensor's own drives are as the network gives them."""
    import json
    import shutil

    from overlapmamba.core.datasets import open_recording
    from overlapmamba.train.checkpoint import load_model
    from overlapmamba.train.evaluate import describe_sequence
    from overlapmamba.train.modelfile import read_metadata, with_sensor_maps

    m = _map_for(read_metadata(MODEL).descriptor_dim)
    mapped = tmp_path / "mapped.onnx"
    with_sensor_maps(MODEL, mapped, {"vlp16": m})
    town = shutil.copytree(synthetic_seq_dir, tmp_path / "vlp16-town")
    (town / "manifest.json").write_text(json.dumps({"config": {"sensor": "vlp16"}}))
    got = {}
    for name, path in (("plain", MODEL), ("mapped", mapped)):
        model, profile, _ = load_model(path)
        for drive in (town, synthetic_seq_dir):
            seq = open_recording(drive, need_poses=True)
            got[name, drive.name] = describe_sequence(model, seq, profile)
    raw, raw_yaw = got["plain", town.name]
    desc, yaw = got["mapped", town.name]
    np.testing.assert_allclose(desc, m.apply(raw), atol=1e-5)
    assert float(np.mean(np.sum(desc * raw, axis=1))) < 0.99  # it did move
    np.testing.assert_allclose(yaw, raw_yaw, atol=1e-6)
    own = synthetic_seq_dir.name  # the model's own sensor: never mapped
    np.testing.assert_allclose(got["mapped", own][0], got["plain", own][0], atol=1e-6)
