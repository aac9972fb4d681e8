"""The wire says which sensor sent a scan, and the model says which thresholds it answers
with: sensors on every scan route, maps that declare one, calibration from the model file."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from service_kit import MODEL, OCTET, running, scan

from overlapmamba.core.calibration import calibrated
from overlapmamba.core.points import PointCloud
from overlapmamba.core.sensors import CATALOGUE
from overlapmamba.core.sensors.input import SensorInput
from overlapmamba.service.encoder import Encoder
from overlapmamba.service.settings import Settings

pytestmark = pytest.mark.anyio


@pytest.fixture
def settings(tmp_path) -> Settings:
    return Settings(data_dir=tmp_path / "data")


def _expected(encoder: Encoder, points: np.ndarray, sensor: str) -> np.ndarray:
    inp = SensorInput(encoder.meta.profile, CATALOGUE[sensor], encoder.meta.sensor_input)
    images = encoder.project(PointCloud(points[:, :3].copy()), inp)[None]
    return encoder.encode(images)[0][0]


async def test_a_scan_is_projected_as_the_sensor_it_names(settings, encoder):
    s = scan(3)
    async with running(settings, encoder) as c:
        default = np.array(
            (await c.post("/v1/descriptors", content=s.tobytes(), headers=OCTET)).json()[
                "descriptor"
            ]
        )
        own = await c.post("/v1/descriptors?sensor=kitti-hdl64", content=s.tobytes(), headers=OCTET)
        np.testing.assert_allclose(own.json()["descriptor"], default, atol=1e-6)
        r = await c.post("/v1/descriptors?sensor=vlp16", content=s.tobytes(), headers=OCTET)
        assert r.status_code == 200, r.text
        vlp = np.array(r.json()["descriptor"])
        np.testing.assert_allclose(vlp, _expected(encoder, s, "vlp16"), atol=1e-5)
        assert float(vlp @ default) < 0.9999  # another projection, another descriptor
        # a batch names one sensor for all its scans
        body = b"".join(struct.pack("<I", len(x)) + x for x in (s.tobytes(), s.tobytes()))
        b = await c.post(
            "/v1/descriptors:batch?sensor=vlp16",
            content=body,
            headers={"content-type": "application/x-scan-batch"},
        )
        assert b.status_code == 200, b.text
        np.testing.assert_allclose(b.json()["descriptors"][1], vlp, atol=1e-6)
        listed = (await c.get("/v1/sensors")).json()
        assert listed["model_sensor"] == "kitti-hdl64"
        kinds = {x["name"]: x["projection"] for x in listed["sensors"]}
        assert kinds["kitti-hdl64"] == "native" and kinds["vlp16"] == encoder.meta.sensor_input
        assert {"vlp16", "vlp32c", "os1-128", "os0-128", "xt32", "hdl32"} <= set(kinds)
        assert (await c.get("/readyz")).json()["detail"]["sensor"] == "kitti-hdl64"


async def test_a_scan_declares_where_its_sensor_sits(settings, encoder):
    """?mount=HEIGHT[,PITCH[,ROLL]]: the scan is levelled and moved to the model sensor's
    height before it is projected; at that height and level nothing changes; a mount that
    cannot be is a 400 naming what is allowed."""
    from overlapmamba.core.sensors.mount import REFERENCE_HEIGHT, Mount

    s = scan(4)
    async with running(settings, encoder) as c:

        async def describe(query: str):
            return await c.post(f"/v1/descriptors?{query}", content=s.tobytes(), headers=OCTET)

        plain = np.array((await describe("sensor=vlp16")).json()["descriptor"])
        same = (await describe(f"sensor=vlp16&mount={REFERENCE_HEIGHT}")).json()["descriptor"]
        np.testing.assert_allclose(same, plain, atol=1e-5)
        low = await describe("sensor=vlp16&mount=0.7,2.5,-1")
        assert low.status_code == 200, low.text
        inp = SensorInput(
            encoder.meta.profile,
            CATALOGUE["vlp16"],
            encoder.meta.sensor_input,
            Mount(height=0.7, pitch_deg=2.5, roll_deg=-1),
        )
        images = encoder.project(PointCloud(s[:, :3].copy()), inp)[None]
        np.testing.assert_allclose(
            low.json()["descriptor"], encoder.encode(images)[0][0], atol=1e-5
        )
        assert float(np.array(low.json()["descriptor"]) @ plain) < 0.9999
        for bad in ("0", "0.7,60", "abc", "1,2,3,4"):
            r = await describe(f"sensor=vlp16&mount={bad}")
            assert r.status_code == 400, (bad, r.text)
        r = await describe("mount=0.7,60")
        assert r.json()["error"]["code"] == "bad_mount" and "±45°" in r.json()["error"]["message"]
        assert (await c.put("/v1/maps/m")).status_code == 201
        for route in ("keyframes?keyframe_id=k&timestamp=1&", "observe?robot_id=r&timestamp=2&"):
            r = await c.post(
                f"/v1/maps/m/{route}sensor=vlp16&mount=0.7", content=s.tobytes(), headers=OCTET
            )
            assert r.status_code in (200, 201), r.text
        q = await c.post(
            "/v1/maps/m/query?k=1&verify=false&sensor=vlp16&mount=0.7",
            content=s.tobytes(),
            headers=OCTET,
        )
        assert q.json()["matches"][0]["distance"] < 1e-3  # the same scan from the same mount
        far = await c.post(
            "/v1/maps/m/query?k=1&verify=false&sensor=vlp16", content=s.tobytes(), headers=OCTET
        )
        assert far.json()["matches"][0]["distance"] > 1e-3  # the same points, mount undeclared


async def test_an_unknown_sensor_is_a_400_that_lists_the_known_ones(settings, encoder):
    s = scan(0).tobytes()
    async with running(settings, encoder) as c:
        assert (await c.put("/v1/maps/m")).status_code == 201
        kf = "keyframe_id=a&timestamp=1"
        for method, url in [
            ("post", "/v1/descriptors?sensor=mid360"),
            ("post", "/v1/maps/m/query?sensor=mid360"),
            ("post", "/v1/maps/m/observe?robot_id=r&timestamp=1&sensor=mid360"),
            ("post", f"/v1/maps/m/keyframes?{kf}&sensor=mid360"),
        ]:
            r = await getattr(c, method)(url, content=s, headers=OCTET)
            assert r.status_code == 400, (url, r.text)
            e = r.json()["error"]
            assert e["code"] == "unknown_sensor" and "allowed: hdl32, hdl64e" in e["message"]
            assert "vlp16" in e["detail"]["allowed"]
        bad = await c.put("/v1/maps/n", json={"sensor": "mid360"})
        assert bad.status_code == 400 and bad.json()["error"]["code"] == "unknown_sensor"
        assert (await c.get("/v1/maps/n")).status_code == 404  # nothing was created
        weird = await c.post("/v1/descriptors?sensor=../etc", content=s, headers=OCTET)
        assert weird.status_code == 422  # not even a name


async def test_a_map_of_one_sensor_holds_and_answers_others(settings, encoder):
    async with running(settings, encoder) as c:
        r = await c.put("/v1/maps/robots", json={"sensor": "vlp16"})
        assert r.status_code == 201 and r.json()["sensor"] == "vlp16"
        again = await c.put("/v1/maps/robots", json={"sensor": "os1-64"})
        assert again.status_code == 409 and again.json()["error"]["detail"]["sensor"] == "vlp16"
        assert (await c.put("/v1/maps/robots", json={"sensor": "vlp16"})).status_code == 200
        own = await c.put("/v1/maps/robots", json={"sensor": "kitti-hdl64"})
        assert own.status_code == 409  # the model's own sensor is not the map's either
        # a map made naming the model's own sensor is the map made naming none
        assert (await c.put("/v1/maps/cars", json={"sensor": "kitti-hdl64"})).json()[
            "sensor"
        ] is None
        assert (await c.put("/v1/maps/cars")).status_code == 200
        for i in range(3):  # scans that name no sensor are the map's
            ins = await c.post(
                f"/v1/maps/robots/keyframes?keyframe_id=k{i}&timestamp={i}",
                content=scan(i).tobytes(),
                headers=OCTET,
            )
            assert ins.status_code == 201 and ins.json()["sensor"] == "vlp16"
        car = await c.post(  # a car's HDL-64E scan of the same place, into the robots' map
            "/v1/maps/robots/keyframes?keyframe_id=car1&timestamp=9&sensor=kitti-hdl64",
            content=scan(1).tobytes(),
            headers=OCTET,
        )
        assert car.status_code == 201 and car.json()["sensor"] == "kitti-hdl64"
        q = await c.post(
            "/v1/maps/robots/query?k=4&verify=false&sensor=kitti-hdl64",
            content=scan(1).tobytes(),
            headers=OCTET,
        )
        assert q.status_code == 200, q.text
        matches = q.json()["matches"]
        assert matches[0]["keyframe_id"] == "car1" and matches[0]["distance"] < 1e-3
        assert {m["sensor"] for m in matches} == {"kitti-hdl64", "vlp16"}
        # the map's own sensor answers the same scan as its VLP-16 keyframe
        own = await c.post(
            "/v1/maps/robots/query?k=1&verify=false", content=scan(1).tobytes(), headers=OCTET
        )
        assert own.json()["matches"][0]["keyframe_id"] == "k1"
        # retrying an insert with another sensor is other content: refused, not overwritten
        retry = await c.post(
            "/v1/maps/robots/keyframes?keyframe_id=k1&timestamp=1&sensor=os1-64",
            content=scan(1).tobytes(),
            headers=OCTET,
        )
        assert retry.status_code == 409
        got = (await c.get("/v1/maps/robots/keyframes/k1")).json()
        assert got["sensor"] == "vlp16"


async def test_a_map_declares_where_the_sensor_of_its_scans_sits(settings, encoder):
    """A map made with ``mount`` takes it for every scan sent to it that names none: the
    same keyframe as the scan sent with that mount, fixed when the map is made."""
    s = scan(5)

    async def keyframe(c, map_id: str, kid: str, query: str = "") -> np.ndarray:
        r = await c.post(
            f"/v1/maps/{map_id}/keyframes?keyframe_id={kid}&timestamp=1&sensor=vlp16{query}",
            content=s.tobytes(),
            headers=OCTET,
        )
        assert r.status_code == 201, r.text
        got = await c.post(
            f"/v1/maps/{map_id}/query?k=1&verify=false&sensor=vlp16{query}",
            content=s.tobytes(),
            headers=OCTET,
        )
        return got.json()["matches"][0]

    async with running(settings, encoder) as c:
        r = await c.put("/v1/maps/robots", json={"mount": "0.7,2.5"})
        assert r.status_code == 201, r.text
        assert r.json()["mount"] == {"height": 0.7, "pitch_deg": 2.5, "roll_deg": 0.0}
        assert (await c.put("/v1/maps/cars")).json()["mount"] is None
        mounted = await keyframe(c, "robots", "a")  # the map's mount, undeclared by the scan
        assert mounted["distance"] < 1e-3
        said = await keyframe(c, "cars", "b", "&mount=0.7,2.5")  # the same mount, said per scan
        d = await c.post(
            "/v1/descriptors?sensor=vlp16&mount=0.7,2.5", content=s.tobytes(), headers=OCTET
        )
        by_descriptor = await c.post(  # the keyframe is the scan described from that mount
            "/v1/maps/robots/query", params={"k": 1}, json={"descriptor": d.json()["descriptor"]}
        )
        hit = by_descriptor.json()["matches"][0]
        assert hit["keyframe_id"] == "a" and hit["distance"] < 1e-3
        assert said["distance"] < 1e-3
        cross = await c.post(  # the robots' keyframe, asked from the car map's scan
            "/v1/maps/robots/query?k=1&verify=false&sensor=vlp16&mount=1.73",
            content=s.tobytes(),
            headers=OCTET,
        )
        assert cross.json()["matches"][0]["distance"] > 1e-3  # a scan's own mount wins
        conflict = await c.put("/v1/maps/robots", json={"mount": "0.35"})
        assert conflict.status_code == 409
        assert conflict.json()["error"]["detail"]["mount"]["height"] == 0.7
        assert (await c.put("/v1/maps/robots", json={"mount": "0.7,2.5,0"})).status_code == 200
        bad = await c.put("/v1/maps/new", json={"mount": "0.7,60"})
        assert bad.status_code == 400 and bad.json()["error"]["code"] == "bad_mount"
        assert (await c.get("/v1/maps/new")).status_code == 404  # nothing made
    async with running(settings, encoder) as c:  # a restart keeps it
        got = (await c.get("/v1/maps/robots")).json()
        assert got["mount"] == {"height": 0.7, "pitch_deg": 2.5, "roll_deg": 0.0}


# ---- calibration travels with the model ----------------------------------------------------
def _calibrated_copy(tmp_path, name: str, max_score: float, accept_distance: float):
    from overlapmamba.train.modelfile import with_calibration

    path = tmp_path / name
    path.write_bytes(MODEL.read_bytes())
    entry = calibrated(
        "loop_closure",
        {"max_score": max_score, "accept_distance": accept_distance},
        chosen_by="tests/test_service_sensors.py",
        data="a test",
    )
    meta = with_calibration(path, "loop_closure", entry)
    assert meta.model_id == Encoder(MODEL).model_id  # the model is the same model
    return path


async def test_each_model_answers_with_its_own_calibration(tmp_path):
    strict = _calibrated_copy(tmp_path, "strict.onnx", -5.0, 0.01)
    loose = _calibrated_copy(tmp_path, "loose.onnx", 5.0, 1.9)
    seen = {}
    for path in (strict, loose):
        enc = Encoder(path, intra_op_threads=2)
        settings = Settings(data_dir=tmp_path / path.stem)
        async with running(settings, enc) as c:
            await c.put("/v1/maps/m")
            await c.post(
                "/v1/maps/m/keyframes?keyframe_id=a&timestamp=1",
                content=scan(0).tobytes(),
                headers=OCTET,
            )
            q = (
                await c.post(
                    "/v1/maps/m/query?verify=false", content=scan(0).tobytes(), headers=OCTET
                )
            ).json()
            ready = (await c.get("/readyz")).json()["detail"]["thresholds"]
            seen[path.stem] = (q["loop_closure"], ready)
    (lc_strict, t_strict), (lc_loose, t_loose) = seen["strict"], seen["loose"]
    assert lc_strict["threshold"] == -5.0 and not lc_strict["accepted"]
    assert lc_loose["threshold"] == 5.0 and lc_loose["accepted"]
    assert t_strict["loop_closure.max_score"] == {
        "value": -5.0,
        "source": "model",
        "chosen_by": "tests/test_service_sensors.py on a test",
    }
    assert t_loose["loop_closure.accept_distance"]["value"] == 1.9


async def test_an_explicit_setting_overrides_the_models_calibration(tmp_path, caplog):
    loose = _calibrated_copy(tmp_path, "loose.onnx", 5.0, 1.9)
    settings = Settings(data_dir=tmp_path / "d", loop_closure={"max_score": -1.0})
    with caplog.at_level("INFO", logger="overlapmamba.service"):
        async with running(settings, Encoder(loose, intra_op_threads=2)) as c:
            t = (await c.get("/readyz")).json()["detail"]["thresholds"]
    assert t["loop_closure.max_score"] == {"value": -1.0, "source": "setting"}
    assert t["loop_closure.accept_distance"]["source"] == "model"
    assert "loop_closure.max_score=-1.0 (setting)" in caplog.text
    assert "loop_closure.accept_distance=1.9 (model)" in caplog.text


def test_a_benchmark_records_its_pick_in_the_model_and_the_service_takes_it(tmp_path, monkeypatch):
    """benchmarks/*.py --write-calibration: bench_kit.write_calibration stamps the section
    with the command that chose it; served_settings (what the service would answer with)
    reads it back; the other sections stay the defaults, the model id stays the same."""
    import sys

    from overlapmamba.core.modelmeta import EncoderMetadata
    from overlapmamba.train.modelfile import read_metadata

    sys.path.insert(0, str(MODEL.parents[1] / "benchmarks"))
    from bench_kit import served_settings, write_calibration
    from reports_kit import provenance

    path = tmp_path / "m.onnx"
    path.write_bytes(MODEL.read_bytes())
    before = read_metadata(path)
    write_calibration(path, "rerank", {"shortlist": 7, "weight": 0.3}, "data/synth/val")
    meta = read_metadata(path)
    assert meta.model_id == before.model_id and meta.calibration["rerank"].data == "data/synth/val"
    assert meta.calibration["rerank"].chosen_by == provenance()["command"]  # this process's
    served = served_settings(meta)
    assert (served.rerank.shortlist, served.rerank.weight) == (7, 0.3)
    assert served.verify.min_fitness == Settings().verify.min_fitness
    with pytest.raises(ValueError, match="not calibrated here; allowed: shortlist, weight"):
        write_calibration(path, "rerank", {"gate": 1.0}, "x")
    # a value the service would refuse at start-up is refused before the file is touched,
    # even where a variable of this process sets that value (and would hide the file's)
    with pytest.raises(ValueError, match="calibration of rerank is not valid"):
        write_calibration(path, "rerank", {"shortlist": 201, "weight": 2.0}, "data/synth/val")
    monkeypatch.setenv("OVERLAPMAMBA_RERANK__SHORTLIST", "10")
    with pytest.raises(ValueError, match="calibration of rerank is not valid"):
        write_calibration(path, "rerank", {"shortlist": 201, "weight": 2.0}, "data/synth/val")
    assert read_metadata(path).calibration == meta.calibration
    assert isinstance(EncoderMetadata.from_props(meta.to_props()), EncoderMetadata)


def test_a_maps_unknown_sensor_is_the_maps_fault_and_a_bad_calibration_stops_the_service():
    from overlapmamba.core.modelmeta import EncoderMetadata
    from overlapmamba.service.calibration import resolve
    from overlapmamba.service.errors import BadRequest, Conflict
    from overlapmamba.service.sensors import Sensors

    meta = Encoder(MODEL).meta
    sensors = Sensors(meta)
    assert (
        sensors.resolve(None, None) == "kitti-hdl64" and sensors.resolve("xt32", "vlp16") == "xt32"
    )
    with pytest.raises(Conflict, match="map declares sensor 'gone'") as e:
        sensors.resolve(None, "gone")  # a sensor file removed since the map was made
    assert e.value.code == "unknown_map_sensor"
    with pytest.raises(BadRequest, match="unknown sensor 'gone'"):
        sensors.resolve("gone", "vlp16")
    assert sensors.declared("kitti-hdl64") is None and sensors.declared("vlp16") == "vlp16"
    bad = calibrated("rerank", {"shortlist": 0, "weight": 0.2}, chosen_by="x", data="y")
    broken = EncoderMetadata.model_validate(
        {**meta.model_dump(by_alias=True), "calibration": {"rerank": bad}}, by_alias=True
    )
    with pytest.raises(ValueError, match="calibration of rerank is not valid"):
        resolve(Settings(), broken)
    # a section this code does not know (a newer writer's) is left out; the model loads
    props = {**meta.to_props(), "overlapmamba.calibration": '{"future": {"values": {"x": 1}, '
             '"chosen_by": "a", "data": "b", "at": "c"}}'}  # fmt: skip
    assert EncoderMetadata.from_props(props).calibration == {}


def test_the_sensor_input_mode_is_rewritten_with_its_model_id(tmp_path):
    from overlapmamba.train.errors import ExportError
    from overlapmamba.train.modelfile import read_metadata, with_sensor_input

    path = tmp_path / "m.onnx"
    path.write_bytes(MODEL.read_bytes())
    before = read_metadata(path)
    rows = with_sensor_input(path, "rows")
    assert rows.sensor_input == "rows" and rows.model_id != before.model_id
    assert rows.graph == before.graph and rows.views == before.views
    enc = Encoder(path)  # the service projects another sensor's scans by the file's mode
    assert sensor_input_kind(enc, "vlp16") == "rows"
    assert with_sensor_input(path, "elevation").model_id == before.model_id
    with pytest.raises(ExportError, match="allowed: elevation, elevation-lerp, elevation-fill"):
        with_sensor_input(path, "stretch")  # type: ignore[arg-type]


def sensor_input_kind(enc: Encoder, name: str) -> str:
    from overlapmamba.service.sensors import Sensors

    return Sensors(enc.meta).input(name).kind


async def test_a_clouds_ring_field_must_fit_the_sensor_it_is_projected_as(settings, encoder):
    """A PointCloud2 with a `ring` field numbering 32 rings is not a VLP-16's scan: refused
    with both counts; as a 32-beam sensor's it is accepted. The rings never pick a sensor."""
    from ros_messages import F32, U16, message

    from overlapmamba.core.io.pointcloud2 import decode_pointcloud2

    s = scan(2)
    pts = s.copy()
    pts[:, 3] = np.arange(len(s)) % 32  # the driver's ring numbers, 0–31
    body = message(pts, [("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("ring", 12, U16)], 16)
    cloud = decode_pointcloud2(body)
    assert cloud.ring is not None and cloud.ring.max() == 31 and cloud.intensity is None
    ros = {"content-type": "application/x-ros2-pointcloud2"}
    async with running(settings, encoder) as c:
        bad = await c.post("/v1/descriptors?sensor=vlp16", content=body, headers=ros)
        assert bad.status_code == 400, bad.text
        e = bad.json()["error"]
        assert e["code"] == "sensor_mismatch" and e["detail"] == {
            "sensor": "vlp16",
            "beams": 16,
            "rings": [0, 31],
        }
        assert (
            await c.post("/v1/descriptors?sensor=xt32", content=body, headers=ros)
        ).status_code == 200
        # the model's own sensor (64 beams) fits too: a scan that names none is not refused
        assert (await c.post("/v1/descriptors", content=body, headers=ros)).status_code == 200


def test_a_keyframe_of_another_sensor_is_scored_within_its_field_of_view():
    """Sensors.view: the keyframe's sensor's field of view when the query's sensor is another
    (a keyframe that recorded none is the model's own), else None; FieldOfView keeps what
    that sensor could have returned."""
    from overlapmamba.service.sensors import FieldOfView, Sensors

    sensors = Sensors(Encoder(MODEL).meta)
    assert sensors.view("vlp16", "vlp16") is None and sensors.view("vlp16", None) is None
    assert sensors.view(None, "kitti-hdl64") is None  # the model's own, both sides
    assert sensors.view("gone", "vlp16") is None  # not known: scored as before, in full
    vlp = CATALOGUE["vlp16"]
    view = sensors.view("vlp16", "kitti-hdl64")
    assert view == FieldOfView.of(vlp.elevations_deg, vlp.max_range)
    hdl = sensors.view(None, "vlp16")  # the model's HDL-64E keyframe, a VLP-16 query
    assert hdl is not None and hdl.high_deg < 5.0 < view.high_deg
    pts = np.array([[10.0, 0.0, 0.0], [10.0, 0.0, 2.0], [500.0, 0.0, 0.0]])
    assert hdl.inside(pts).tolist() == [True, False, False]  # 11° up is above its top beam


def test_a_sensor_the_model_cannot_read_stops_the_start_and_an_empty_scan_names_the_real_range(
    tmp_path,
):
    """A sensor file whose beams all miss the model's image (every scan of it would be an
    empty image) is refused at start-up; and a scan with nothing in range is refused naming
    the range the model's input takes (the model's 80 m), not the sensor's own (120 m)."""
    from overlapmamba.core.errors import ProfileError
    from overlapmamba.service.calibration import read_model_metadata
    from overlapmamba.service.errors import Unprocessable
    from overlapmamba.service.pipeline import check_in_range
    from overlapmamba.service.sensors import Sensors

    meta = read_model_metadata(MODEL)
    up = tmp_path / "up.toml"
    up.write_text('base = "os1-64"\nname = "up"\nelevations_deg = [60.0, 45.0, 30.0, 15.0]\n')
    with pytest.raises(ProfileError, match="none of 'up''s beams .* falls in the model's image"):
        Sensors(meta, [up])
    taken = SensorInput(meta.profile, CATALOGUE["os1-64"], "elevation")
    ring = 100.0 * np.stack([np.cos(np.arange(500)), np.sin(np.arange(500)), np.zeros(500)], 1)
    image = taken.project(ring.astype(np.float32))[0]
    with pytest.raises(Unprocessable, match=r"\(0 m < range < 80 m\)") as err:
        check_in_range(image, meta.profile, taken, 500)
    assert err.value.detail["max_range"] == 80.0 and CATALOGUE["os1-64"].max_range == 120.0


def test_a_declared_model_mount_is_no_mount_and_wins_over_the_maps():
    """Found in review: a car's drive names its mount (1.73 m, level) so that a map whose
    robots sit lower does not stand in for it; declared, the model's own mount must take the
    scan exactly as an undeclared one (native, intensity kept), not through the levelling."""
    from overlapmamba.core.sensors.mount import Mount
    from overlapmamba.service.sensors import Sensors

    sensors = Sensors(Encoder(MODEL).meta)
    own = sensors.input("kitti-hdl64")
    assert sensors.input("kitti-hdl64", Mount(height=1.73)) is own and own.native
    low = sensors.input("kitti-hdl64", Mount(height=0.35))
    assert low.kind == "native+mount" and not low.native
    assert sensors.input("kitti-hdl64", Mount(height=1.73, pitch_deg=2.0)).kind == "native+mount"
