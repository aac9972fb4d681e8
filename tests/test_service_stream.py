"""The observation stream (``/v1/maps/{map}/stream``, a WebSocket) on the ASGI app in
process: an observation that fails in a way the service did not foresee is answered and
logged, and the stream goes on."""

from __future__ import annotations

import asyncio
import contextlib
import json
import sqlite3

import httpx
import numpy as np
import pytest
from service_kit import OCTET, running, scan, ws_scope

from overlapmamba.service.auth import hash_key
from overlapmamba.service.settings import Settings

pytestmark = pytest.mark.anyio


def _not_json(constant: str) -> None:
    """An answer is JSON: NaN and Infinity, which Python's json module writes, are not."""
    raise ValueError(f"the answer holds {constant}, which is not JSON")


async def _stream(app, path: str, query: str, frames: list[dict], answers: int) -> list[dict]:
    """Open a WebSocket on the ASGI app, send ``frames`` (ASGI receive messages) and gather
    the server's first ``answers`` text frames, decoded."""
    got: list[dict] = []
    inbox: asyncio.Queue[dict] = asyncio.Queue()
    for message in [{"type": "websocket.connect"}, *frames]:
        inbox.put_nowait(message)
    enough = asyncio.Event()

    async def send(message: dict) -> None:
        if message["type"] == "websocket.send":
            got.append(json.loads(message["text"], parse_constant=_not_json))
            if len(got) >= answers:
                enough.set()
        elif message["type"] == "websocket.close":
            got.append({"closed": message.get("code"), "reason": message.get("reason")})
            enough.set()

    task = asyncio.create_task(app(ws_scope(path, query), inbox.get, send))
    await asyncio.wait_for(enough.wait(), timeout=60)
    inbox.put_nowait({"type": "websocket.disconnect", "code": 1000})
    with contextlib.suppress(BaseException):
        await asyncio.wait_for(task, timeout=10)
    return got


async def test_an_unforeseen_error_is_answered_and_the_stream_goes_on(tmp_path, encoder, caplog):
    """The store's disk full (sqlite3.OperationalError) during one observation: the robot
    gets that frame's error and the next frame's answer, not a stream that dies silently."""
    async with running(Settings(data_dir=tmp_path / "data"), encoder) as c:
        assert (await c.put("/v1/maps/m")).status_code == 201
        app = c.app  # type: ignore[attr-defined]
        svc = app.state.service
        real, calls = svc.observe, []

        async def disk_full_once(m, body, obs):
            calls.append(obs.timestamp)
            if len(calls) == 1:
                raise sqlite3.OperationalError("database or disk is full")
            return await real(m, body, obs)

        svc.observe = disk_full_once
        points = scan(0).tobytes()
        frames = []
        for seq in (1, 2):
            frames.append(
                {
                    "type": "websocket.receive",
                    "text": json.dumps({"seq": seq, "timestamp": float(seq)}),
                }
            )
            frames.append({"type": "websocket.receive", "bytes": points})
        first, second = await _stream(app, "/v1/maps/m/stream", "robot_id=r1", frames, 2)
    assert first["seq"] == 1 and first["ok"] is False and first["status"] == 500
    assert first["error"]["code"] == "internal_error"
    assert "OperationalError" in first["error"]["message"]
    assert second["seq"] == 2 and second["ok"] is True, second
    assert calls == [1.0, 2.0]
    assert any("observation 1 failed" in r.getMessage() for r in caplog.records)


async def test_a_metadata_frame_whose_scan_never_came_is_answered(tmp_path, encoder):
    """Two metadata frames in a row: the first's observation was not made, and its seq is
    answered so (a robot waiting on it does not wait for ever); the second goes on."""
    async with running(Settings(data_dir=tmp_path / "data"), encoder) as c:
        assert (await c.put("/v1/maps/m")).status_code == 201
        meta = [
            {"type": "websocket.receive", "text": json.dumps({"seq": s, "timestamp": s})}
            for s in (1.0, 2.0)
        ]
        frames = [*meta, {"type": "websocket.receive", "bytes": scan(0).tobytes()}]
        app = c.app  # type: ignore[attr-defined]
        first, second = await _stream(app, "/v1/maps/m/stream", "robot_id=r1", frames, 2)
    assert first["seq"] == 1 and first["ok"] is False and first["status"] == 400
    assert first["error"]["code"] == "bad_stream_frame"
    assert "not its scan" in first["error"]["message"]
    assert second["seq"] == 2 and second["ok"] is True, second


async def test_an_invalid_metadata_frame_is_answered_once_under_its_seq(tmp_path, encoder):
    """A metadata frame that does not validate (a NaN timestamp) is answered under its own
    seq, naming the field; the scan that follows it belongs to it and is dropped, not
    answered a second time as a scan without metadata. The next pair is served."""
    async with running(Settings(data_dir=tmp_path / "data"), encoder) as c:
        assert (await c.put("/v1/maps/m")).status_code == 201
        body = scan(0).tobytes()
        frames = [
            {"type": "websocket.receive", "text": '{"seq": 7, "timestamp": NaN}'},
            {"type": "websocket.receive", "bytes": body},
            {"type": "websocket.receive", "text": "not json"},
            {"type": "websocket.receive", "bytes": body},
            {"type": "websocket.receive", "text": json.dumps({"seq": 8, "timestamp": 8.0})},
            {"type": "websocket.receive", "bytes": body},
        ]
        app = c.app  # type: ignore[attr-defined]
        bad, garbled, good = await _stream(app, "/v1/maps/m/stream", "robot_id=r1", frames, 3)
    assert bad["seq"] == 7 and bad["ok"] is False and bad["status"] == 400, bad
    assert bad["error"]["code"] == "bad_stream_frame"
    assert "timestamp" in bad["error"]["message"], bad
    assert garbled["seq"] is None and garbled["ok"] is False
    assert "not valid" in garbled["error"]["message"]
    assert good["seq"] == 8 and good["ok"] is True, good


async def test_a_seq_that_json_cannot_echo_is_refused_and_answers_stay_json(tmp_path, encoder):
    """``1e999`` is valid JSON that parses as infinity, and Python also reads NaN: echoed, the
    answer would hold Infinity or NaN, which no strict JSON parser takes. The frame is refused
    (its seq answered as null), its scan dropped, and the stream goes on."""
    async with running(Settings(data_dir=tmp_path / "data"), encoder) as c:
        assert (await c.put("/v1/maps/m")).status_code == 201
        body = scan(0).tobytes()
        frames = [
            {"type": "websocket.receive", "text": '{"seq": 1e999, "timestamp": 1}'},
            {"type": "websocket.receive", "bytes": body},
            {"type": "websocket.receive", "text": '{"seq": [1, NaN], "timestamp": 2}'},
            {"type": "websocket.receive", "bytes": body},
            {"type": "websocket.receive", "text": '{"seq": {"n": 3.5}, "timestamp": 3}'},
            {"type": "websocket.receive", "bytes": body},
        ]
        app = c.app  # type: ignore[attr-defined]
        inf, nan, good = await _stream(app, "/v1/maps/m/stream", "robot_id=r1", frames, 3)
    for bad in (inf, nan):
        assert bad["seq"] is None and bad["ok"] is False and bad["status"] == 400, bad
        assert "seq" in bad["error"]["message"] and "finite" in bad["error"]["message"], bad
    assert good["seq"] == {"n": 3.5} and good["ok"] is True, good


async def test_a_k_past_the_servers_limit_closes_the_handshake(tmp_path, encoder):
    """``k`` within the schema's bound (1000) but past ``limits.max_k`` (100): the handshake
    is closed naming it, not accepted and then every observation refused."""
    async with running(Settings(data_dir=tmp_path / "data"), encoder) as c:
        assert (await c.put("/v1/maps/m")).status_code == 201
        app = c.app  # type: ignore[attr-defined]
        (closed,) = await _stream(app, "/v1/maps/m/stream", "robot_id=r1&k=500", [], 1)
    assert closed["closed"] == 1008, closed
    assert "k=500" in closed["reason"] and "1 to 100" in closed["reason"], closed


async def test_a_frame_nested_past_the_parsers_depth_is_answered_and_the_stream_goes_on(
    tmp_path, encoder
):
    """Thousands of nested brackets: pydantic refuses the frame, and reading its seq for the
    answer hit Python's recursion limit, which killed the stream's handler (no answer, no
    close frame, every later observation lost)."""
    async with running(Settings(data_dir=tmp_path / "data"), encoder) as c:
        assert (await c.put("/v1/maps/m")).status_code == 201
        body = scan(0).tobytes()
        deep = '{"seq": 2, "timestamp": 2, "pose": ' + "[" * 5000 + "]" * 5000 + "}"
        # found in review: a seq nested within the parser's depth (400) but past the stack
        # the echo check took ended the handler all the same
        seq = "[" * 400 + "1" + "]" * 400
        deep_seq = '{"seq": ' + seq + ', "timestamp": 4, "pose": "x"}'
        frames = [
            {"type": "websocket.receive", "text": deep},
            {"type": "websocket.receive", "bytes": body},
            {"type": "websocket.receive", "text": deep_seq},
            {"type": "websocket.receive", "bytes": body},
            {"type": "websocket.receive", "text": json.dumps({"seq": 3, "timestamp": 3.0})},
            {"type": "websocket.receive", "bytes": body},
        ]
        app = c.app  # type: ignore[attr-defined]
        bad, bad_seq, good = await _stream(app, "/v1/maps/m/stream", "robot_id=r1", frames, 3)
    assert bad["ok"] is False and bad["status"] == 400, bad
    assert bad_seq["ok"] is False and bad_seq["seq"] is None, bad_seq
    assert good["seq"] == 3 and good["ok"] is True, good


async def test_a_map_deleted_and_made_again_under_an_open_stream_is_the_new_one(tmp_path, encoder):
    """The stream looked its map up once: deleted, its observations were 404 for good, even
    once a map of that id was made again. Each observation now takes the map of its id."""
    async with running(Settings(data_dir=tmp_path / "data"), encoder) as c:
        assert (await c.put("/v1/maps/m")).status_code == 201
        app = c.app  # type: ignore[attr-defined]
        body = scan(0).tobytes()
        inbox: asyncio.Queue[dict] = asyncio.Queue()
        answers: asyncio.Queue[dict] = asyncio.Queue()

        async def send(message: dict) -> None:
            if message["type"] == "websocket.send":
                answers.put_nowait(json.loads(message["text"]))

        inbox.put_nowait({"type": "websocket.connect"})
        task = asyncio.create_task(
            app(ws_scope("/v1/maps/m/stream", "robot_id=r1"), inbox.get, send)
        )

        async def observe(seq: int) -> dict:
            meta = {"seq": seq, "timestamp": float(seq), "insert": "always"}
            inbox.put_nowait({"type": "websocket.receive", "text": json.dumps(meta)})
            inbox.put_nowait({"type": "websocket.receive", "bytes": body})
            return await asyncio.wait_for(answers.get(), timeout=60)

        try:
            assert (await observe(1))["ok"] is True
            assert (await c.delete("/v1/maps/m")).status_code == 204
            gone = await observe(2)
            assert gone["ok"] is False and gone["status"] == 404, gone
            assert (await c.put("/v1/maps/m")).status_code == 201
            again = await observe(3)
            assert again["ok"] is True and again["inserted"] is True, again
            assert (await c.get("/v1/maps/m")).json()["keyframes"] == 1
        finally:
            inbox.put_nowait({"type": "websocket.disconnect", "code": 1000})
            with contextlib.suppress(BaseException):
                await asyncio.wait_for(task, timeout=10)


async def test_the_access_log_says_how_each_stream_ended(tmp_path, encoder, caplog):
    """Every WebSocket's access line said 101, a refused handshake too: the log could not
    tell a robot streaming from one turned away. It now says 101 for an accepted stream, the
    refusal's status for a handshake answered as a route (404 for a missing map), 403 for a
    close before the accept, and the close code."""
    import logging

    async with running(Settings(data_dir=tmp_path / "data"), encoder) as c:
        assert (await c.put("/v1/maps/m")).status_code == 201
        app = c.app  # type: ignore[attr-defined]
        caplog.set_level(logging.INFO, logger="overlapmamba.access")
        frames = [
            {"type": "websocket.receive", "text": json.dumps({"seq": 1, "timestamp": 1.0})},
            {"type": "websocket.receive", "bytes": scan(0).tobytes()},
        ]
        (ok,) = await _stream(app, "/v1/maps/m/stream", "robot_id=r1", frames, 1)
        assert ok["ok"] is True, ok
        (closed,) = await _stream(app, "/v1/maps/m/stream", "robot_id=r1&k=500", [], 1)
        assert closed["closed"] == 1008
        denied: list[dict] = []

        async def keep(message: dict) -> None:
            denied.append(message)

        scope = ws_scope("/v1/maps/gone/stream", "robot_id=r1")
        scope["extensions"] = {"websocket.http.response": {}}
        inbox: asyncio.Queue[dict] = asyncio.Queue()
        inbox.put_nowait({"type": "websocket.connect"})
        await asyncio.wait_for(app(scope, inbox.get, keep), timeout=30)
        assert denied[0]["type"] == "websocket.http.response.start"
    lines = [
        (r.path, r.status, getattr(r, "close_code", None))  # type: ignore[attr-defined]
        for r in caplog.records
        if r.name == "overlapmamba.access" and "stream" in r.path  # type: ignore[attr-defined]
    ]
    assert lines == [
        ("/v1/maps/m/stream", 101, 1000),
        ("/v1/maps/m/stream", 403, 1008),
        ("/v1/maps/gone/stream", denied[0]["status"], None),
    ], lines
    assert denied[0]["status"] == 404


async def test_a_metadata_frame_of_megabytes_is_refused_before_it_is_parsed(tmp_path, encoder):
    """A metadata frame is parsed, and its seq echoed, on the event loop: a 7 MiB frame
    held every other request up for 1.3 s and came back as an 11 MiB answer. A frame past
    64 KiB is answered with an error naming the limit, unparsed; its scan is dropped, and
    the stream goes on."""
    async with running(Settings(data_dir=tmp_path / "data"), encoder) as c:
        assert (await c.put("/v1/maps/m")).status_code == 201
        body = scan(0).tobytes()
        big = json.dumps({"seq": "x" * (1 << 20), "timestamp": 1.0})
        frames = [
            {"type": "websocket.receive", "text": big},
            {"type": "websocket.receive", "bytes": body},
            {"type": "websocket.receive", "text": json.dumps({"seq": 2, "timestamp": 2.0})},
            {"type": "websocket.receive", "bytes": body},
        ]
        app = c.app  # type: ignore[attr-defined]
        bad, good = await _stream(app, "/v1/maps/m/stream", "robot_id=r1", frames, 2)
    assert bad["ok"] is False and bad["seq"] is None and "at most 65536" in bad["error"]["message"]
    assert len(json.dumps(bad)) < 1000
    assert good["seq"] == 2 and good["ok"] is True, good


async def test_a_scan_frame_past_the_body_limit_is_refused_as_http_refuses_it(tmp_path, encoder):
    """The socket takes frames up to ``max_body_bytes`` + 64 KiB (the metadata's room), so a
    scan between the two was observed on the stream while HTTP refused the same bytes with
    a 413. It is answered with that 413 under its seq, and the stream goes on."""
    body = scan(0).tobytes()
    settings = Settings(data_dir=tmp_path / "data", limits={"max_body_bytes": len(body) + 16})
    async with running(settings, encoder) as c:
        assert (await c.put("/v1/maps/m")).status_code == 201
        over = body + bytes(32)  # 16 bytes past the limit, a whole number of points
        r = await c.post("/v1/maps/m/observe?robot_id=r1&timestamp=1", content=over, headers=OCTET)
        assert r.status_code == 413
        frames = []
        for seq, data in ((1, over), (2, body)):
            meta = json.dumps({"seq": seq, "timestamp": float(seq)})
            frames += [
                {"type": "websocket.receive", "text": meta},
                {"type": "websocket.receive", "bytes": data},
            ]
        app = c.app  # type: ignore[attr-defined]
        bad, good = await _stream(app, "/v1/maps/m/stream", "robot_id=r1", frames, 2)
    assert bad["seq"] == 1 and bad["ok"] is False and bad["status"] == 413, bad
    assert bad["error"]["code"] == "payload_too_large"
    assert f"at most {len(body) + 16}" in bad["error"]["message"]
    assert good["seq"] == 2 and good["ok"] is True, good


async def test_a_handshake_whose_parameters_do_not_validate_is_a_422_naming_them(tmp_path, encoder):
    """Found in review: a handshake without robot_id, or with a sensor, k or mount the schema
    refuses, was closed by FastAPI's own handler before our refusal: a bare 403 to the robot,
    which could not tell a bad k from a refused key."""
    async with running(Settings(data_dir=tmp_path / "data"), encoder) as c:
        assert (await c.put("/v1/maps/m")).status_code == 201
        app = c.app  # type: ignore[attr-defined]
        for query, field in (("k=1001&robot_id=r1", "k"), ("sensor=VLP-16&robot_id=r1", "sensor"),
                             ("session_id=x", "robot_id")):  # fmt: skip
            sent: list[dict] = []

            async def keep(message: dict, sent=sent) -> None:
                sent.append(message)

            scope = ws_scope("/v1/maps/m/stream", query)
            scope["extensions"] = {"websocket.http.response": {}}
            inbox: asyncio.Queue[dict] = asyncio.Queue()
            inbox.put_nowait({"type": "websocket.connect"})
            await asyncio.wait_for(app(scope, inbox.get, keep), timeout=30)
            assert sent[0]["type"] == "websocket.http.response.start" and sent[0]["status"] == 422
            body = json.loads(b"".join(m.get("body", b"") for m in sent[1:]))
            assert body["error"]["code"] == "invalid_request", body
            assert field in body["error"]["message"], body


async def test_a_stream_from_a_web_page_of_another_origin_is_refused(tmp_path, encoder):
    """Found in review: a browser opens a WebSocket for any page with no preflight, so any
    site a user visited could observe into, and insert keyframes into, a keyless service on
    that user's machine. Programs send no Origin; listed origins are let through."""
    settings = Settings(
        data_dir=tmp_path / "data", auth={"allowed_origins": ["https://OPS.example:443/"]}
    )
    async with running(settings, encoder) as c:
        assert (await c.put("/v1/maps/m")).status_code == 201
        app = c.app  # type: ignore[attr-defined]

        async def handshake(headers: dict[str, str]) -> dict:
            sent: list[dict] = []

            async def keep(message: dict) -> None:
                sent.append(message)

            scope = ws_scope("/v1/maps/m/stream", "robot_id=r1", headers)
            scope["extensions"] = {"websocket.http.response": {}}
            inbox: asyncio.Queue[dict] = asyncio.Queue()
            inbox.put_nowait({"type": "websocket.connect"})
            inbox.put_nowait({"type": "websocket.disconnect", "code": 1000})
            await asyncio.wait_for(app(scope, inbox.get, keep), timeout=30)
            return sent[0]

        evil = await handshake({"host": "127.0.0.1:8000", "origin": "http://evil.example"})
        assert evil["type"] == "websocket.http.response.start" and evil["status"] == 403
        for headers in (
            {"host": "127.0.0.1:8000"},  # a robot: no Origin
            {"host": "127.0.0.1:8000", "origin": "http://127.0.0.1:8000"},  # its own page
            {"host": "evil.example", "origin": "https://ops.example"},  # listed
        ):
            assert (await handshake(headers))["type"] == "websocket.accept", headers


async def test_a_write_from_a_web_page_of_another_origin_is_refused(tmp_path, encoder):
    """Found in review: the JSON routes parse a text/plain body, which a browser sends for
    any site's page with no preflight: a page a user visited could insert descriptors into
    a keyless service on that user's machine, also by DNS rebinding (its own name resolved
    to 127.0.0.1, its Origin matching the Host it sends). Reads, programs (no Origin), the
    service's own pages under a loopback name or an IP, listed origins, and any request to a
    service with keys (a browser cannot present one without a preflight) pass."""
    settings = Settings(
        data_dir=tmp_path / "data", auth={"allowed_origins": ["https://ops.example"]}
    )
    vec = np.zeros(encoder.meta.descriptor_dim)
    vec[0] = 1.0

    def body(i: int) -> str:
        kf = {"keyframe_id": f"x{i}", "timestamp": 0.0, "descriptor": vec.tolist()}
        return json.dumps({"model_id": encoder.model_id, "keyframes": [kf]})

    async with running(settings, encoder) as c:
        assert (await c.put("/v1/maps/m")).status_code == 201

        async def write(i: int, host: str, origin: str) -> httpx.Response:
            headers = {"content-type": "text/plain", "host": host, "origin": origin}
            return await c.post("/v1/maps/m/keyframes:batch", content=body(i), headers=headers)

        refused = [
            ("127.0.0.1:8000", "http://evil.example"),  # another site's page
            ("evil.example:8000", "http://evil.example:8000"),  # DNS rebinding
            ("127.0.0.1:8000", "null"),  # a file:// page, a sandboxed frame
        ]
        for host, origin in refused:
            page = await write(0, host, origin)
            assert page.status_code == 403, (host, origin)
            assert page.json()["error"]["code"] == "cross_origin"
        assert (await c.get("/v1/maps/m")).json()["keyframes"] == 0
        read = await c.get("/v1/maps/m", headers={"origin": "http://evil.example"})
        assert read.status_code == 200  # a read: the browser keeps its answer from the page
        passed = [
            ("127.0.0.1:8000", "http://127.0.0.1:8000"),  # its own page
            ("localhost", "http://localhost:80"),  # default port, written or not
            ("[::1]:8000", "http://[::1]:8000"),
            ("127.0.0.1:8000", "https://ops.example"),  # listed (a proxy's public origin)
        ]
        for i, (host, origin) in enumerate(passed, start=1):
            ok = await write(i, host, origin)
            assert ok.status_code == 200, (host, origin, ok.text)
    key = {"name": "ops", "role": "admin", "sha256": hash_key("k-admin")}
    keyed = Settings(data_dir=tmp_path / "keyed", auth={"keys": [key]})
    async with running(keyed, encoder) as c:
        headers = {"x-api-key": "k-admin", "origin": "https://om.example", "host": "10.0.0.2"}
        assert (await c.put("/v1/maps/m", headers=headers)).status_code == 201
    with pytest.raises(ValueError, match="'ops.example' is no origin"):
        Settings(auth={"allowed_origins": ["ops.example"]})
