"""End to end, auth: every route of the live OpenAPI schema (plus the WebSocket stream and
the open probes) × every role × {no key, wrong key}, against a real server with API keys.
Each cell must hold its expected status: 401 without a valid key, 403 for a role without
the right, and for an allowed role the route's own answer (never 401/403, never 5xx).
A route missing from the expectation table fails the test: new routes must be placed.
"""

from __future__ import annotations

import json

import httpx
import pytest
from e2e_kit import write_report
from service_kit import server
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from overlapmamba.service.auth import hash_key

pytestmark = pytest.mark.e2e
ROLES = ("robot", "mapper", "viewer", "admin")
OPEN = {"GET /healthz", "GET /readyz"}  # probes answer anyone (so do /openapi.json, /docs)
READ = {"viewer", "admin"}
USE = {"robot", "mapper", "admin"}
BUILD = {"mapper", "admin"}
# method + OpenAPI path → the roles allowed (robot keys may insert only into their maps)
ALLOWED = {
    "GET /v1/stats": READ,
    "GET /metrics": READ,
    "GET /dashboard": READ,
    "GET /v1/maps/{map_id}/stats": READ,
    "GET /v1/maps/{map_id}/overview": READ,
    "POST /v1/descriptors": USE,
    "POST /v1/descriptors:batch": USE,
    "GET /v1/sensors": USE,
    "POST /v1/maps/{map_id}/query": USE,
    "POST /v1/maps/{map_id}/observe": USE,
    "POST /v1/maps/{map_id}/keyframes": USE,
    "POST /v1/maps/{map_id}/keyframes:batch": BUILD,
    "GET /v1/maps/{map_id}/keyframes/{keyframe_id}": BUILD,
    "DELETE /v1/maps/{map_id}/keyframes/{keyframe_id}": BUILD,
    "GET /v1/maps": BUILD,
    "GET /v1/maps/{map_id}": BUILD,
    "PUT /v1/maps/{map_id}": BUILD,
    "POST /v1/maps/{map_id}/snapshot": BUILD,
    "DELETE /v1/maps/{map_id}": BUILD,
}
QUERY = {  # the required query parameters, so allowed cells reach the route's own checks
    "/v1/maps/{map_id}/observe": {"robot_id": "r", "timestamp": 1, "insert": "never"},
    "/v1/maps/{map_id}/keyframes": {"keyframe_id": "a", "timestamp": 1},
}


def _routes(schema: dict) -> list[tuple[str, str]]:
    return sorted(
        (method.upper(), path)
        for path, ops in schema["paths"].items()
        for method in ops
        if method in ("get", "post", "put", "delete", "patch")
    )


@pytest.mark.timeout(600)
def test_every_route_every_role_no_key_and_wrong_key(tmp_path):
    keys = [{"name": r, "role": r, "sha256": hash_key(f"secret-{r}")} for r in ROLES]
    keys[0]["maps"] = ["m"]  # the robot key may insert into map m only
    env = {"OVERLAPMAMBA_AUTH__KEYS": json.dumps(keys)}
    cells: list[dict] = []
    with server(tmp_path / "data", env) as (url, _), httpx.Client(base_url=url, timeout=60) as c:
        schema = c.get("/openapi.json").json()
        routes = _routes(schema)
        known = set(ALLOWED) | OPEN
        unplaced = [f"{m} {p}" for m, p in routes if f"{m} {p}" not in known]
        assert not unplaced, f"routes without an expected auth row: {unplaced}"
        admin = {"authorization": "Bearer secret-admin"}
        for method, path in routes:
            name = f"{method} {path}"
            concrete = path.replace("{map_id}", "m").replace("{keyframe_id}", "a")
            params = QUERY.get(path)
            row: dict = {"route": name}
            for who, headers in [
                ("no key", {}),
                ("wrong key", {"x-api-key": "not-a-key"}),
                ("wrong bearer", {"authorization": "Bearer not-a-key"}),
                *[(r, {"x-api-key": f"secret-{r}"}) for r in ROLES],
            ]:
                # every cell meets the same state: map m exists (a DELETE may have removed it)
                c.put("/v1/maps/m", headers=admin)
                r = c.request(method, concrete, headers=headers, params=params)
                row[who] = r.status_code
                assert r.status_code < 500, (name, who, r.text[:300])
                if name in OPEN:
                    assert r.status_code == 200, (name, who, r.status_code)
                elif who in ("no key", "wrong key", "wrong bearer"):
                    assert r.status_code == 401, (name, who, r.status_code)
                    assert r.json()["error"]["code"] in ("missing_api_key", "invalid_api_key")
                elif who in ALLOWED[name]:
                    assert r.status_code not in (401, 403), (name, who, r.text[:300])
                else:
                    assert r.status_code == 403, (name, who, r.status_code)
            cells.append(row)
        # The robot key's map list: inserting into another map is refused, also through
        # observe when it would insert.
        robot = {"x-api-key": "secret-robot"}
        kf = {"keyframe_id": "a", "timestamp": 1}
        r = c.post("/v1/maps/other/keyframes", params=kf, headers=robot)
        assert r.status_code == 403 and r.json()["error"]["code"] == "map_not_allowed"
        obs = {"robot_id": "r", "timestamp": 1, "insert": "always"}
        r = c.post("/v1/maps/other/observe", params=obs, headers=robot)
        assert r.status_code == 403 and r.json()["error"]["code"] == "map_not_allowed", r.text
        # The schema and its docs page are public.
        for path in ("/openapi.json", "/docs"):
            assert c.get(path).status_code == 200, path
        # The WebSocket stream: refused at the handshake without a key or with a viewer key.
        ws = url.replace("http", "ws") + "/v1/maps/m/stream?robot_id=r"
        stream_row: dict = {"route": "WS /v1/maps/{map_id}/stream"}
        for who, headers in [
            ("no key", {}),
            ("wrong key", {"x-api-key": "not-a-key"}),
            ("wrong bearer", {"authorization": "Bearer not-a-key"}),
            *[(r, {"x-api-key": f"secret-{r}"}) for r in ROLES],
        ]:
            try:
                with connect(ws, additional_headers=headers, open_timeout=10) as sock:
                    sock.close()
                    stream_row[who] = 101
            except InvalidStatus as err:
                stream_row[who] = err.response.status_code
            except Exception as err:  # closed with 1008 right after the handshake
                code = getattr(getattr(err, "rcvd", None), "code", None)
                stream_row[who] = f"close {code}" if code else type(err).__name__
        cells.append(stream_row)
    for who in ("no key", "wrong key", "wrong bearer", "viewer"):
        assert stream_row[who] != 101, stream_row
    for who in ("robot", "mapper", "admin"):
        assert stream_row[who] == 101, stream_row
    write_report(
        "auth_matrix",
        {"command": "make e2e (tests/test_e2e_auth.py)", "roles": list(ROLES), "cells": cells},
    )
