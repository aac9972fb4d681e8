"""Names that meant more than one thing (overlapmamba.core.renamed): each has its own now, and
the old ones still work for one release, with a warning, wherever a user could have written
them: a settings file, an environment variable, a model file's calibration, a query
parameter, a client keyword, a loop table's saved parameters."""

from __future__ import annotations

import contextlib

import httpx
import pytest
from service_kit import MODEL, OCTET, running, scan

from overlapmamba.client import PlaceRecognitionClient
from overlapmamba.core.calibration import check_calibration
from overlapmamba.core.overlap import LoopParams
from overlapmamba.core.renamed import RENAMED, DeprecatedName, renamed
from overlapmamba.service.encoder import Encoder
from overlapmamba.service.settings import Settings, load_settings


def test_every_old_name_has_one_new_name_and_no_new_name_is_taken_twice():
    for where, table in RENAMED.items():
        assert len(set(table.values())) == len(table), where
        assert not set(table) & set(table.values()), where
    with pytest.warns(DeprecatedName, match=r"verify\.k is deprecated .* verify\.candidates"):
        assert renamed({"k": 3, "radius_m": 1.0}, "verify") == {"candidates": 3, "radius_m": 1.0}
    with pytest.raises(ValueError, match="give candidates only; k is its old name"):
        renamed({"k": 3, "candidates": 4}, "verify")


def test_settings_take_the_old_names_from_a_file_and_the_environment(tmp_path, monkeypatch):
    toml = tmp_path / "old.toml"
    toml.write_text(
        "[loop_closure]\nmax_distance = 0.2\n[verify]\nk = 3\nmax_distance = 0.4\n"
        "[rerank]\nk = 10\n"
    )
    with pytest.warns(DeprecatedName) as seen:
        s = load_settings(toml)
    assert len(seen) == 4
    assert (s.loop_closure.accept_distance, s.verify.candidates, s.verify.gate_distance) == (
        0.2,
        3,
        0.4,
    )
    assert s.rerank.shortlist == 10
    # set by the operator under the old name is still "set": it overrides the model's value
    assert "accept_distance" in s.loop_closure.model_fields_set
    monkeypatch.setenv("OVERLAPMAMBA_VERIFY__K", "2")
    with pytest.warns(DeprecatedName, match="verify.k"):
        assert Settings().verify.candidates == 2
    monkeypatch.setenv("OVERLAPMAMBA_VERIFY__CANDIDATES", "4")
    with pytest.raises(ValueError, match="give candidates only"):
        Settings()


def test_a_calibration_written_under_the_old_names_reads_under_the_new():
    entry = {"chosen_by": "an older benchmark", "data": "val", "at": "2026-11-20T00:00:00+00:00"}
    old = {
        "rerank": {**entry, "values": {"k": 20, "weight": 0.2}},
        "verify": {**entry, "values": {"min_fitness": 0.5, "max_rmse_m": 0.7, "max_distance": 0.3}},
    }
    with pytest.warns(DeprecatedName):
        got = check_calibration(old)
    assert got["rerank"].values == {"shortlist": 20, "weight": 0.2}
    assert (
        got["verify"].values["gate_distance"] == 0.3
        and got["verify"].chosen_by == entry["chosen_by"]
    )


def test_the_shipped_model_carries_the_new_names():
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecatedName)
        meta = Encoder(MODEL).meta
    verify = {"min_fitness", "max_rmse_m", "gate_distance", "ambiguity_margin"}
    assert set(meta.calibration["verify"].values) == verify


def test_a_loop_tables_saved_key_stays_and_means_frames():
    assert LoopParams.of({"exclude_recent": 12, "radius": 10.0}).exclude_recent_frames == 12


@pytest.mark.anyio
async def test_the_query_filter_answers_to_both_names_and_refuses_both_at_once(tmp_path, caplog):
    async with running(Settings(data_dir=tmp_path), Encoder(MODEL)) as c:
        await c.put("/v1/maps/m")
        for i, kid in enumerate(("near", "far")):
            r = await c.post(
                f"/v1/maps/m/keyframes?keyframe_id={kid}&timestamp={i}",
                content=scan(0 if kid == "near" else 7, 40.0).tobytes(),
                headers=OCTET,
            )
            assert r.status_code in (200, 201), r.text
        d = (await c.post("/v1/descriptors", content=scan(0, 40.0).tobytes(), headers=OCTET)).json()
        body = {"descriptor": d["descriptor"]}

        async def matches(**params: float) -> list[dict]:
            r = await c.post("/v1/maps/m/query", params={"k": 5, **params}, json=body)
            assert r.status_code == 200, r.text
            return r.json()["matches"]

        both = await matches()
        assert [m["keyframe_id"] for m in both] == ["near", "far"]
        cut = (both[0]["distance"] + both[1]["distance"]) / 2
        assert [m["keyframe_id"] for m in await matches(max_match_distance=cut)] == ["near"]
        with caplog.at_level("WARNING", logger="overlapmamba.service"):
            assert [m["keyframe_id"] for m in await matches(max_distance=cut)] == ["near"]
        assert "max_distance is deprecated" in caplog.text
        r = await c.post(
            "/v1/maps/m/query", params={"max_distance": cut, "max_match_distance": cut}, json=body
        )
        assert r.status_code == 400 and r.json()["error"]["code"] == "conflicting_parameters"
        spec = (await c.get("/openapi.json")).json()
        query = spec["paths"]["/v1/maps/{map_id}/query"]["post"]["parameters"]
        params = {p["name"]: p for p in query}
        assert params["max_distance"].get("deprecated") is True
        assert not params["max_match_distance"].get("deprecated")


def test_the_client_sends_the_new_name_for_the_old_keyword():
    sent: list[httpx.URL] = []

    def handler(request: httpx.Request) -> httpx.Response:
        sent.append(request.url)
        return httpx.Response(200, json={"matches": [], "loop_closure": None})

    with (
        PlaceRecognitionClient(transport=httpx.MockTransport(handler)) as pr,
        pytest.warns(DeprecatedName, match="query.max_distance"),
        contextlib.suppress(Exception),  # the canned answer's shape is not what is tested
    ):
        pr.query("m", descriptor=[1.0] * 256, max_distance=0.5)
    assert sent and sent[0].params["max_match_distance"] == "0.5"
    assert "max_distance" not in sent[0].params
