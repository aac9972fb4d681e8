"""The every-sensor option, ``models/overlapmamba-any-sensor.onnx`` (the model card's section
of that name): its metadata and calibration, one pass a scan still under turns of real scans,
and, served, a map made by one sensor answering another's scans.

It is read the way the service reads it: onnxruntime and overlapmamba.core only, no torch."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("onnxruntime")

from service_kit import OCTET, running

from overlapmamba.service.encoder import Encoder
from overlapmamba.service.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
ANY = ROOT / "models" / "overlapmamba-any-sensor.onnx"
CARD = ROOT / "models" / "README.md"
SECTIONS = ("rerank", "loop_closure", "verify", "covariance")


@pytest.fixture(scope="module")
def enc() -> Encoder:
    assert ANY.is_file(), f"the every-sensor option {ANY} is missing from the repository"
    return Encoder(ANY, intra_op_threads=2)


def test_one_pass_a_bev_input_and_a_calibration_chosen_on_val_towns_of_every_sensor(enc):
    """What the card promises of the file: one encoder pass a scan, the bird's-eye input, its
    first stage, and each threshold chosen by a benchmark naming this file, on validation
    towns only (never a test town), across the sensors it is for."""
    meta = enc.meta
    assert enc.views == 1 and meta.sensor_input == "bev-span" and meta.weights == "trained"
    assert meta.column_phase == "aligned"
    assert meta.first_stage != "descriptor" and meta.model_id in CARD.read_text()
    assert set(meta.calibration) == set(SECTIONS)
    for section, entry in meta.calibration.items():
        assert f"--model models/{ANY.name}" in entry.chosen_by, (section, entry.chosen_by)
        assert "--write-calibration" in entry.chosen_by, section
        towns = [Path(t.strip()).name for t in entry.data.split(",")]
        assert all(t.startswith(("val-", "cal-x")) for t in towns), (section, towns)
        # val-SENSOR, or the calibration town's drives cal-xNN-sSESSION-SENSOR
        sensors = {t.split("-", 3)[3] if t.startswith("cal-x") else t[4:] for t in towns}
        assert {"kitti-hdl64", "vlp16", "os0-128", "xt32", "os1-128"} <= sensors, (section, towns)
    train = [Path(d["path"]).name for d in meta.training_data["train"]]
    assert train and not any(t.startswith(("test", "val")) for t in train)


def turned_cosines(
    enc: Encoder, clouds: list[np.ndarray], seed: int, sensor: str | None = None
) -> np.ndarray:
    from overlapmamba.core.poses import rotation_z, transform_points
    from overlapmamba.service.sensors import Sensors

    declared = None
    if sensor is not None:
        sensors = Sensors(enc.meta)
        declared = sensors.input(sensors.resolve(sensor))
    theta = np.random.default_rng(seed).uniform(-180, 180, len(clouds))
    turned = [transform_points(c, rotation_z(t)) for c, t in zip(clouds, theta, strict=True)]
    desc, _ = enc.describe(clouds + turned, declared)
    return (desc[: len(clouds)] * desc[len(clouds) :]).sum(1)


@pytest.mark.real_data
def test_one_pass_keeps_the_descriptor_under_continuous_turns_of_real_scans(
    enc, kitti_seq_dir, nuscenes_dir
):
    """The issue's cosine bar (0.999) with one pass a scan, on a sample of both real sets
    (nuScenes declared `hdl32`, as a robot would). The file's columns start at each scan's
    mean bearing, so a turned scan's image is the plain one rolled by whole columns and the
    descriptor moves by float rounding only: far above the bar, where in the sensor's
    columns the same weights sat within a ten-thousandth of it on nuScenes."""
    from overlapmamba.core.datasets import open_sequence

    kitti = open_sequence(kitti_seq_dir)
    cos = turned_cosines(enc, [kitti.points(i).xyz for i in range(0, len(kitti), 10)], 0)
    assert cos.min() >= 0.99999, cos.min()
    nus = open_sequence(nuscenes_dir)
    cos = turned_cosines(enc, [nus.points(i).xyz for i in range(0, len(nus), 4)], 1, "hdl32")
    assert cos.min() >= 0.99999, cos.min()


@pytest.fixture(scope="module")
def two_sensor_drives(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Two drives of one small town no benchmark reports on (calibration town 7), the first
    by an HDL-64E, the second by a VLP-16, both on a car's roof."""
    pytest.importorskip("embreex")
    from overlapmamba.synth.generate import generate
    from overlapmamba.synth.presets import calibration_town

    root = tmp_path_factory.mktemp("two-sensors")
    out = []
    for session, sensor in ((0, "kitti-hdl64"), (1, "vlp16")):
        cfg = calibration_town(7, sensor, 300).model_copy(update={"session": session})
        generate(root / sensor, cfg, workers=2, ground_truth=False, progress=False)
        out.append(root / sensor)
    return out[0], out[1]


def xyzi(cloud) -> bytes:
    inten = cloud.intensity if cloud.intensity is not None else np.zeros(len(cloud.xyz))
    return np.column_stack([cloud.xyz, inten]).astype(np.float32).tobytes()


def world(seq) -> np.ndarray:
    """(N, 4, 4) scan poses in the town's frame (both drives share it)."""
    from overlapmamba.synth.generate import read_manifest

    m = read_manifest(seq.root)
    return np.asarray(m["world_from_sequence"], dtype=np.float64) @ seq.poses


@pytest.mark.anyio
async def test_a_map_by_one_sensor_recognises_another_sensors_scans(
    tmp_path, enc, two_sensor_drives
):
    """Served as a fleet runs it: an HDL-64E drive's scans are the map's keyframes, a VLP-16
    drive's scans (`?sensor=vlp16`) query it. The top answer lies within 5 m of the query for
    most queries that have a keyframe there (the shipped HDL-64E file's descriptor finds about
    half of these; `benchmarks/rerank_across.py` measures every sensor pair on the test town),
    most of them verify against the HDL-64E's keyframe geometry, and every loop closure the
    service verifies carries the right relative pose (≤ 1 m, 2°)."""
    from overlapmamba.core.datasets import open_sequence
    from overlapmamba.core.poses import pose_error
    from overlapmamba.train.sessions import HIT_RADIUS

    maps, queries = (open_sequence(p) for p in two_sensor_drives)
    pm, pq = world(maps), world(queries)
    settings = Settings(data_dir=tmp_path / "data")
    hits, evaluated, verified, wrong = 0, 0, 0, []
    async with running(settings, enc) as c:
        r = await c.put("/v1/maps/town", json={"index": "flat", "sensor": "kitti-hdl64"})
        assert r.status_code == 201, r.text
        for i in range(len(maps)):
            params = {"keyframe_id": f"m{i}", "timestamp": float(i), "robot_id": "car"}
            r = await c.post(
                "/v1/maps/town/keyframes",
                params=params,
                content=xyzi(maps.points(i)),
                headers=OCTET,
            )
            assert r.status_code == 201, r.text
        for i in range(0, len(queries), 2):
            near = np.linalg.norm(pm[:, :2, 3] - pq[i, :2, 3], axis=1) <= HIT_RADIUS
            if not near.any():
                continue
            r = await c.post(
                "/v1/maps/town/query",
                params={"k": 5, "sensor": "vlp16"},
                content=xyzi(queries.points(i)),
                headers=OCTET,
            )
            assert r.status_code == 200, r.text
            answer = r.json()
            evaluated += 1
            hits += bool(near[int(answer["matches"][0]["keyframe_id"][1:])])
            lc = answer["loop_closure"]
            if lc["accepted"] and lc["verified"]:
                verified += 1
                j = int(lc["keyframe_id"][1:])
                truth = np.linalg.inv(pm[j]) @ pq[i]
                t_err, yaw_err = pose_error(np.array(lc["relative_pose"]).reshape(4, 4), truth)
                if t_err > 1.0 or yaw_err > 2.0:
                    wrong.append((i, j, t_err, yaw_err))
    assert evaluated >= 50, evaluated
    assert hits / evaluated >= 0.8, (hits, evaluated)
    # scored within the HDL-64E's field of view, most VLP-16 scans verify against its
    # keyframes (about two in five did when every point of theirs was scored), none wrong
    assert verified >= 0.8 * evaluated and not wrong, (verified, evaluated, wrong)
