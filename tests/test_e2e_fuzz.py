"""End to end, fuzz: schemathesis against the live OpenAPI schema (every route, examples,
coverage, fuzzing and stateful phases following the schema's links), and a hand-made corpus
of hostile scan bodies. No 5xx, responses conform to the schema, every hostile body gets a
4xx naming the problem, and the server stays healthy.

Quick (``make test``): a 25 s schemathesis budget. Full (``make e2e``): 5 minutes.
"""

from __future__ import annotations

import gzip
import io
import json
import os
import pickle
import re
import socket
import subprocess
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest
import zstandard
from e2e_kit import OUT, size, unit, write_report
from service_kit import MODEL, OCTET, scan, server

from overlapmamba.service.encoder import Encoder

pytestmark = pytest.mark.e2e
HERE = Path(__file__).resolve().parent


def _npy(a: np.ndarray, **kw: object) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a, **kw)  # type: ignore[arg-type]
    return buf.getvalue()


def _zeros_zstd(n_bytes: int) -> bytes:
    """n_bytes of zeros, zstd-compressed in a stream (the body stays a few KB)."""
    c = zstandard.ZstdCompressor().compressobj()
    chunk = bytes(1 << 20)
    out = [c.compress(chunk) for _ in range(n_bytes >> 20)]
    return b"".join([*out, c.flush()])


class _Trap:
    """Unpickling this creates a folder: proof that a pickle was (or was not) loaded."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple:
        return (os.makedirs, (str(self.marker),))


def _hostile_cases(marker: Path) -> list[tuple[str, bytes, dict[str, str]]]:
    good = scan(0)
    nan = good.copy()
    nan[5, 0] = np.nan
    inf = good.copy()
    inf[7, 2] = np.inf
    pcd_bad = b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
    pcd_bad += b"WIDTH 10\nHEIGHT 1\nPOINTS 10\nDATA binary\n" + bytes(40)
    pcd_huge = b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
    pcd_huge += b"WIDTH 50000000\nHEIGHT 1\nPOINTS 50000000\nDATA binary\n" + bytes(120)
    from ros_messages import F32, MEDIA, U16, XYZ, XYZI, message, patch_u32

    pc2 = {"content-type": MEDIA}
    pc2_good = message(good, XYZI, 16)
    pc2_int = message(good, XYZ, 12, declared=[("x", 0, U16), *XYZ[1:]])
    pc2_nan = message(nan, XYZI, 16, dense=True)
    return [
        ("NaN coordinates", nan.tobytes(), OCTET),
        ("Inf coordinates", inf.tobytes(), OCTET),
        ("0 points (empty body)", b"", OCTET),
        ("1 point", good[:1].tobytes(), OCTET),
        (
            "50M points (800 MB, zstd-compressed)",
            _zeros_zstd(800 << 20),
            {**OCTET, "content-encoding": "zstd"},
        ),
        ("50M points declared by a PCD header", pcd_huge, {"content-type": "application/x-pcd"}),
        ("odd byte length (13 B)", bytes(13), OCTET),
        ("odd byte length (not a whole xyzi record)", good.tobytes()[:-3], OCTET),
        ("zstd bomb (1 GB of zeros)", _zeros_zstd(1 << 30), {**OCTET, "content-encoding": "zstd"}),
        (
            "gzip bomb (256 MB of zeros)",
            gzip.compress(bytes(256 << 20), 9),
            {**OCTET, "content-encoding": "gzip"},
        ),
        (
            "truncated zstd frame",
            zstandard.ZstdCompressor().compress(good.tobytes())[:-20],
            {**OCTET, "content-encoding": "zstd"},
        ),
        ("unknown Content-Encoding", good.tobytes(), {**OCTET, "content-encoding": "br"}),
        ("wrong X-Point-Fields", good.tobytes(), {**OCTET, "x-point-fields": "xyzrgb"}),
        (
            "xyz fields, length not a multiple of 12",
            good[:, :3].tobytes()[:-6],
            {**OCTET, "x-point-fields": "xyz"},
        ),
        (
            "npy with object dtype",
            _npy(np.array([{"a": 1}] * 200, dtype=object), allow_pickle=True),
            {"content-type": "application/x-npy"},
        ),
        (
            "a pickle posing as npy (loading it would create a folder)",
            pickle.dumps(_Trap(marker)),
            {"content-type": "application/x-npy"},
        ),
        (
            "2,000,001 points (32 MB; max_points is 2M)",
            np.ones((2_000_001, 4), np.float32).tobytes(),
            OCTET,
        ),
        ("npy of strings", _npy(np.array(["x"] * 400)), {"content-type": "application/x-npy"}),
        (
            "npy with 7 columns",
            _npy(np.zeros((200, 7), np.float32)),
            {"content-type": "application/x-npy"},
        ),
        ("PCD with a malformed header", pcd_bad, {"content-type": "application/x-pcd"}),
        ("PCD that is text garbage", b"hello\nworld\n" * 50, {"content-type": "application/x-pcd"}),
        (
            "JSON list of points",
            json.dumps(good[:200].tolist()).encode(),
            {"content-type": "application/json"},
        ),
        ("PointCloud2 cut short", pc2_good[:-100], pc2),
        ("PointCloud2 declaring 50M points", patch_u32(pc2_good, "width", 50_000_000), pc2),
        ("PointCloud2 declaring 4 billion fields", patch_u32(pc2_good, "fields", 2**32 - 1), pc2),
        ("PointCloud2 with a 2 GB frame_id", patch_u32(pc2_good, "frame_id", 2**31), pc2),
        ("PointCloud2 with an integer x", pc2_int, pc2),
        ("PointCloud2 dense, holding NaN", pc2_nan, pc2),
        ("PointCloud2 that is text garbage", b"hello\nworld\n" * 50, pc2),
        (
            "PointCloud2 z beyond point_step",
            message(good, XYZ, 12, declared=[*XYZ[:2], ("z", 10, F32)]),
            pc2,
        ),
        ("no content type", good.tobytes(), {}),
        ("image/png content type", good.tobytes(), {"content-type": "image/png"}),
    ]


def _raw(port: int, request: bytes, *, half_close: bool = False) -> bytes:
    """Send bytes as they are (a lying Content-Length cannot be sent with httpx)."""
    with socket.create_connection(("127.0.0.1", port), timeout=35) as s:
        s.sendall(request)
        if half_close:
            s.shutdown(socket.SHUT_WR)
        data = b""
        try:
            while chunk := s.recv(65536):
                data += chunk
        except (TimeoutError, ConnectionResetError):
            pass
    return data


def _status(raw: bytes) -> int | None:
    if not raw.startswith(b"HTTP/1.1 "):
        return None
    return int(raw.split(b" ", 2)[1])


@pytest.mark.timeout(900)
def test_hostile_scan_bodies_get_4xx_and_the_server_stays_healthy(tmp_path):
    results = []
    with server(tmp_path / "data") as (url, proc), httpx.Client(base_url=url, timeout=60) as c:
        assert c.put("/v1/maps/m").status_code == 201
        kf = {"keyframe_id": "k", "timestamp": 1.0, "robot_id": "r", "session_id": "s"}
        marker = tmp_path / "unpickled"
        obs = {"robot_id": "r", "session_id": "s", "timestamp": 1.0, "insert": "always"}
        routes = (
            ("/v1/descriptors", None),
            ("/v1/maps/m/keyframes", kf),
            ("/v1/maps/m/observe", obs),
            ("/v1/maps/m/query", {"k": 3}),
        )
        for name, body, headers in _hostile_cases(marker):
            for route, params in routes:
                r = c.post(route, content=body, headers=headers, params=params)
                results.append(
                    {
                        "case": name,
                        "route": route,
                        "status": r.status_code,
                        "code": r.json()["error"]["code"] if r.status_code >= 400 else None,
                    }
                )
                assert 400 <= r.status_code < 500, (name, route, r.status_code, r.text[:300])
                msg = r.json()["error"]["message"]
                assert msg and len(msg) > 10, (name, msg)
            assert proc.poll() is None and c.get("/healthz").status_code == 200, name
        # A Content-Length that lies, in both directions, over a raw socket.
        port = int(url.rsplit(":", 1)[1])
        head = "POST /v1/descriptors HTTP/1.1\r\nHost: x\r\n"
        head += "Content-Type: application/octet-stream\r\n"
        more = _raw(
            port, (head + "Content-Length: 100000\r\n\r\n").encode() + bytes(64), half_close=True
        )
        # smaller: 32 bytes (2 points) are the body; what follows is the next request
        follow = b"GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n"
        less = _raw(port, (head + "Content-Length: 32\r\n\r\n").encode() + bytes(32) + follow)
        huge = _raw(port, (head + f"Content-Length: {1 << 40}\r\n\r\n").encode())
        for name, raw in (
            ("Content-Length larger than the body", more),
            ("Content-Length smaller than the body", less),
            ("Content-Length of 1 TB", huge),
        ):
            status = _status(raw)
            results.append(
                {"case": name, "route": "/v1/descriptors", "status": status, "code": None}
            )
            # larger: the body never completes; the connection is closed, nothing answered or
            # a 4xx; never a 5xx. smaller: the declared bytes are one (bad) body: 4xx.
            assert status is None or 400 <= status < 500, (name, raw[:300])
        assert _status(less) == 422 and b"point_count_out_of_range" in less, less[:400]
        assert less.count(b"HTTP/1.1 200") == 1  # ...and the pipelined request was served
        assert _status(huge) == 413
        assert not marker.exists(), "the pickle was loaded"
        # nothing was written, and the server still does real work
        assert c.get("/v1/maps/m").json()["keyframes"] == 0
        r = c.post("/v1/descriptors", content=scan(1).tobytes(), headers=OCTET)
        assert r.status_code == 200 and len(r.json()["descriptor"]) == 256
        assert proc.poll() is None
    write_report(
        "fuzz_corpus",
        {
            "command": "make e2e (tests/test_e2e_fuzz.py)",
            "cases": results,
            "all_4xx": all(r["status"] is None or 400 <= r["status"] < 500 for r in results),
        },
    )


@pytest.mark.timeout(1200)
def test_schemathesis_finds_no_server_error_and_no_schema_violation(tmp_path):
    budget = size(25, 300)
    report_dir = OUT / "schemathesis"
    report_dir.mkdir(parents=True, exist_ok=True)
    model_id = Encoder(MODEL).model_id
    with server(tmp_path / "data") as (url, proc), httpx.Client(base_url=url, timeout=60) as c:
        # a map and a keyframe for the operations that need them (schemathesis.toml points
        # the path parameters at these; the stateful phase makes its own through the links)
        assert c.put("/v1/maps/e2e").status_code == 201
        rng = np.random.default_rng(0)
        row = {"keyframe_id": "k1", "timestamp": 1.0, "descriptor": unit(rng)}
        body = {"model_id": model_id, "keyframes": [row]}
        assert c.post("/v1/maps/e2e/keyframes:batch", json=body).status_code == 200
        assert c.put("/v1/maps/doomed").status_code == 201  # for DELETE /v1/maps/{map_id}
        cmd = [
            str(Path(sys.executable).parent / "schemathesis"),
            "--config-file",
            str(HERE / "schemathesis.toml"),
            "run",
            f"{url}/openapi.json",
            "--checks",
            "not_a_server_error,response_schema_conformance,content_type_conformance",
            "--phases",
            "examples,coverage,fuzzing,stateful",
            "--max-time",
            str(budget),
            "--seed",
            "1",
            "--no-color",
            "--request-timeout",
            "60",
            "--report",
            "json",
            "--report-json-path",
            str(report_dir / "report.json"),
        ]
        env = {**os.environ, "PYTHONPATH": str(HERE), "SCHEMATHESIS_HOOKS": "schemathesis_hooks"}
        res = subprocess.run(
            cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=budget * 3 + 120
        )
        alive = proc.poll() is None and c.get("/healthz").status_code == 200
    out = res.stdout + res.stderr
    (report_dir / "output.txt").write_text(out)
    summary = out[out.rfind("SUMMARY") :] if "SUMMARY" in out else out[-3000:]
    cases = [int(x) for x in re.findall(r"(\d+) generated", summary)]
    write_report(
        "fuzz_schemathesis",
        {
            "command": "make e2e (tests/test_e2e_fuzz.py)",
            "exit_code": res.returncode,
            "budget_s": budget,
            "test_cases": cases[0] if cases else None,
            "server_alive": alive,
            "summary": summary[-2500:],
        },
    )
    assert alive
    # schemathesis prints what went wrong (operation, check, health check) under ERRORS,
    # above the summary: the failure message carries both
    errors = out[out.rfind("ERRORS") : out.rfind("SUMMARY")] if "ERRORS" in out else ""
    assert res.returncode == 0, errors[-6000:] + summary
    ops = re.search(r"Selected: (\d+)/(\d+)\s+Tested: (\d+)", summary)
    assert ops and len(set(ops.groups())) == 1, summary  # every operation was reached
    assert int(ops.group(1)) >= 20, summary  # …and they are all there (20 with /overview)
