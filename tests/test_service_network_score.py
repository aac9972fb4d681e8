"""A file whose first stage mixes the network's descriptor with the yaw features' spectrum,
served: its answer is re-ranked by the network's own distance (``rerank.score = "network"``,
calibrated in the file), each candidate's taken from the descriptor the map stores."""

from __future__ import annotations

import math

import numpy as np
import pytest
from service_kit import OCTET, ROOT, running, scan

from overlapmamba.service.calibration import resolve
from overlapmamba.service.encoder import Encoder
from overlapmamba.service.settings import Settings

pytestmark = pytest.mark.anyio

ONE_PASS = ROOT / "models" / "overlapmamba-hdl64-one-pass.onnx"


@pytest.fixture(scope="module")
def one_pass() -> Encoder:
    return Encoder(ONE_PASS, intra_op_threads=2)


def network(v: np.ndarray, floats: int = 256) -> np.ndarray:
    part = np.asarray(v[:floats], np.float64)
    return part / np.linalg.norm(part)


@pytest.mark.parametrize("backend", ["faiss", "qdrant"])
async def test_a_scan_query_is_scored_by_the_network_distance_inside_the_first_stage(
    backend, one_pass, tmp_path
):
    extra = (
        {}
        if backend == "faiss"
        else {"index": {"backend": "qdrant"}, "qdrant": {"path": tmp_path / "q"}}
    )
    settings = Settings(data_dir=tmp_path / "data", **extra)
    served, used = resolve(settings, one_pass.meta)
    assert served.rerank.score == "network" and used["rerank.score"].source == "model"
    scans = [scan(i) for i in range(4)]
    async with running(settings, one_pass) as c:
        assert (await c.put("/v1/maps/town")).status_code in (200, 201)
        desc = {}
        for i, s in enumerate(scans):
            r = await c.post(
                "/v1/maps/town/keyframes",
                params={
                    "keyframe_id": f"k{i}",
                    "timestamp": 100.0 + i,
                    "robot_id": "r1",
                    "session_id": "s1",
                },
                content=s.tobytes(),
                headers=OCTET,
            )
            assert r.status_code == 201, r.text
            got = await c.post("/v1/descriptors", content=s.tobytes(), headers=OCTET)
            desc[f"k{i}"] = np.array(got.json()["descriptor"])
        query = scan(2, 40.0)
        q = np.array(
            (await c.post("/v1/descriptors", content=query.tobytes(), headers=OCTET)).json()[
                "descriptor"
            ]
        )
        assert q.shape == (one_pass.meta.descriptor_dim,)
        r = await c.post(
            "/v1/maps/town/query", params={"k": 4}, content=query.tobytes(), headers=OCTET
        )
        assert r.status_code == 200, r.text
        answer = r.json()
    matches = answer["matches"]
    assert matches[0]["keyframe_id"] == "k2" and len(matches) == 4
    w = served.rerank.weight
    stage_scores = []
    for m in matches:
        d2 = float(((network(q) - network(desc[m["keyframe_id"]])) ** 2).sum())
        assert math.isclose(m["score"], d2 - w * m["yaw_confidence"], abs_tol=2e-4), m
        stage_scores.append(m["distance"] ** 2 - w * m["yaw_confidence"])
    assert [m["score"] for m in matches] == sorted(m["score"] for m in matches)
    # the first stage's own distance would have scored otherwise (else this checks nothing)
    assert max(abs(a - m["score"]) for a, m in zip(stage_scores, matches, strict=True)) > 0.01
    lc = answer["loop_closure"]
    assert lc["rule"] == "score" and lc["threshold"] == served.loop_closure.max_score


async def test_the_network_score_of_a_file_whose_first_stage_is_its_descriptor_is_the_stages(
    tmp_path, encoder
):
    """rerank.score = "network" on a file whose first stage is its descriptor scores as the
    stage does (the two are the same)."""
    settings = Settings(data_dir=tmp_path / "data", rerank={"score": "network"})
    async with running(settings, encoder) as c:
        s = scan(0)
        await c.put("/v1/maps/town")
        r = await c.post(
            "/v1/maps/town/keyframes",
            params={"keyframe_id": "k0", "timestamp": 1.0, "robot_id": "r", "session_id": "s"},
            content=s.tobytes(),
            headers=OCTET,
        )
        assert r.status_code == 201, r.text
        r = await c.post("/v1/maps/town/query", params={"k": 1}, content=s.tobytes(), headers=OCTET)
        m = r.json()["matches"][0]
        w = resolve(settings, encoder.meta)[0].rerank.weight
        assert math.isclose(m["score"], m["distance"] ** 2 - w * m["yaw_confidence"], abs_tol=1e-6)


def test_a_score_the_model_cannot_give_stops_the_service_before_it_serves(one_pass):
    """A first stage that is the spectrum alone holds no network descriptor: resolving the
    settings (the service's start-up, ``overlapmamba dump-config``) names the model, the
    score and what is allowed."""
    spectrum = one_pass.meta.model_copy(
        update={"first_stage": "spectrum:32:sqrt", "descriptor_dim": 512}
    )
    with pytest.raises(ValueError, match=r"om-.*'network'.*holds no network descriptor.*allowed"):
        resolve(Settings(rerank={"score": "network"}), spectrum)
    uncalibrated = spectrum.model_copy(update={"calibration": {}})
    assert resolve(Settings(), uncalibrated)[0].rerank.score == "stage"
