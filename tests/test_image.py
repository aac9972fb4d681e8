"""The container image, started and sent real scans: what operators deploy is what the tests
ran. `make image` builds it (deploy/image.py), `make image-test` runs this file against it
(also in `make e2e`); without OVERLAPMAMBA_IMAGE_TEST=1 it is skipped, since building the
image needs a container engine and takes minutes.

Against the running container: /readyz within the start-up budget; a real KITTI scan's
descriptor equal (≤ 1e-5) to the venv's; keyframes inserted, the container stopped with
SIGTERM (a graceful drain) and started again on the same volume with every acknowledged
keyframe back; /metrics; a non-root user; no torch or compiler in the runtime. The image's
size and cold start are written to reports/deploy/image.json."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
import uuid
from pathlib import Path

import httpx
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "deploy"))
from image import IMAGE, env_for  # noqa: E402  (deploy/image.py)

pytestmark = [
    pytest.mark.e2e,
    pytest.mark.skipif(
        os.environ.get("OVERLAPMAMBA_IMAGE_TEST") != "1",
        reason="the image test runs in `make image-test` (OVERLAPMAMBA_IMAGE_TEST=1)",
    ),
]
STARTUP_BUDGET_S = 60.0
KEY = "image-test-key"
REPORT = ROOT / "reports" / "deploy" / "image.json"


def _engine() -> list[str]:
    for name in ("podman", "docker"):
        path = shutil.which(name)
        if path:
            return [path]
    pytest.fail("no container engine: `make image` installs podman")


def _run(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    cmd = _engine()
    done = subprocess.run([*cmd, *args], env=env_for(cmd), capture_output=True, text=True)
    if check and done.returncode != 0:
        raise AssertionError(f"{' '.join(args[:3])}: {done.stderr[-2000:]}")
    return done


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Container:
    """The image run detached with a named volume on /data and API keys; started, stopped
    (SIGTERM) and started again on the same volume."""

    def __init__(self, volume: str) -> None:
        from overlapmamba.service.auth import hash_key

        self.name = f"om-test-{uuid.uuid4().hex[:8]}"
        self.volume = volume
        self.port = _free_port()
        keys = [{"name": "admin", "role": "admin", "sha256": hash_key(KEY)}]
        self.env = {"OVERLAPMAMBA_AUTH__KEYS": json.dumps(keys)}

    def start(self) -> float:
        """Start it; the seconds until /readyz answers 200."""
        env = [a for k, v in self.env.items() for a in ("-e", f"{k}={v}")]
        t0 = time.perf_counter()
        _run("run", "-d", "--name", self.name, "-p", f"127.0.0.1:{self.port}:8000",
             "-v", f"{self.volume}:/data", *env, IMAGE)  # fmt: skip
        while time.perf_counter() - t0 < STARTUP_BUDGET_S:
            try:
                if httpx.get(f"{self.url}/readyz", timeout=2).status_code == 200:
                    return time.perf_counter() - t0
            except httpx.HTTPError:
                pass
            time.sleep(0.1)
        raise AssertionError(f"not ready in {STARTUP_BUDGET_S} s:\n{self.logs()[-3000:]}")

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def stop(self) -> str:
        """SIGTERM (the image's STOPSIGNAL), wait, remove; its logs."""
        _run("stop", "-t", "60", self.name)
        logs = self.logs()
        _run("rm", self.name)
        return logs

    def logs(self) -> str:
        done = _run("logs", self.name, check=False)
        return done.stdout + done.stderr


@pytest.fixture(scope="module")
def volume():
    name = f"om-test-{uuid.uuid4().hex[:8]}"
    _run("volume", "create", name)
    yield name
    _run("volume", "rm", "-f", name, check=False)


def test_the_image_serves_what_the_venv_serves(volume, kitti_seq_dir, encoder):
    from overlapmamba.core.datasets import open_sequence

    inspect = json.loads(_run("image", "inspect", IMAGE).stdout)[0]
    size = int(inspect["Size"])
    seq = open_sequence(kitti_seq_dir)
    c = Container(volume)
    cold = c.start()
    headers = {"x-api-key": KEY}
    try:
        with httpx.Client(base_url=c.url, headers=headers, timeout=60) as http:
            ready = http.get("/readyz").json()["detail"]
            assert ready["model_id"] == encoder.model_id and ready["scan"].startswith("c-kernel")
            # a real KITTI scan: the container's descriptor is the venv's
            body = seq.scan_paths[0].read_bytes()
            octet = {"content-type": "application/octet-stream"}
            got = np.array(http.post("/v1/descriptors", content=body, headers=octet).json()[
                "descriptor"])  # fmt: skip
            want = encoder.encode(encoder.project(seq.points(0))[None])[0][0]
            gap = float(np.abs(got - want).max())
            assert gap <= 1e-5, gap
            # keyframes acknowledged, then a graceful stop
            assert http.put("/v1/maps/town").status_code == 201
            acked = []
            for i in range(0, 40, 2):
                r = http.post(
                    "/v1/maps/town/keyframes",
                    params={"keyframe_id": f"kf-{i}", "timestamp": float(i)},
                    content=seq.scan_paths[i].read_bytes(),
                    headers=octet,
                )
                assert r.status_code == 201, r.text
                acked.append(f"kf-{i}")
            metrics = http.get("/metrics")
            assert metrics.status_code == 200 and "overlapmamba" in metrics.text
        user = _run("exec", c.name, "id", "-u").stdout.strip()
        probe = "import importlib.util as u; print(u.find_spec('torch'), u.find_spec('onnxruntime') is not None)"  # noqa: E501
        found = _run("exec", c.name, "python", "-c", probe).stdout.split()
        compilers = _run("exec", c.name, "sh", "-c", "command -v gcc cc clang || true").stdout
    finally:
        logs = c.stop()
    assert user == "10001"  # the image's own user, not root
    assert found == ["None", "True"] and compilers.strip() == ""
    assert "draining" in logs or "stopped" in logs, logs[-2000:]
    # started again on the same volume: every acknowledged keyframe is back
    again = Container(volume)
    warm = again.start()
    try:
        with httpx.Client(base_url=again.url, headers=headers, timeout=60) as http:
            assert http.get("/v1/maps/town").json()["keyframes"] == len(acked)
            for kid in acked:
                assert http.get(f"/v1/maps/town/keyframes/{kid}").status_code == 200
    finally:
        again.stop()
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from bench_kit import provenance

    REPORT.parent.mkdir(parents=True, exist_ok=True)
    REPORT.write_text(
        json.dumps(
            {
                **provenance(),
                "command": "make image-test",
                "image": IMAGE,
                "image_bytes": size,
                "start_to_ready_s": {"first": round(cold, 2), "restart": round(warm, 2)},
                "descriptor_max_abs_vs_venv": gap,
                "keyframes_back_after_sigterm": f"{len(acked)} of {len(acked)}",
                "user": user,
            },
            indent=2,
        )
        + "\n"
    )


def test_compose_starts_the_service_part(tmp_path):
    """docker-compose.yml through podman's compose support: the file resolves, and the
    service part starts from the image and answers. Qdrant's image cannot be pulled here
    (no registry), so the service runs without it: alive, and not ready until the index
    answers, saying why (the local-mode congruence tests stand in for the server)."""
    compose = shutil.which("podman-compose", path=str(Path(sys.executable).parent))
    if compose is None or Path(_engine()[0]).name != "podman":
        pytest.skip("podman-compose with podman (a dev dependency) checks the compose file")
    from overlapmamba.service.auth import hash_key

    env_file = tmp_path / "compose.env"
    keys = json.dumps([{"name": "admin", "role": "admin", "sha256": hash_key(KEY)}])
    bounds_env = "SERVICE_CPUS=1\nSERVICE_MEMORY=1536m\n"  # .env's bounds reach the container
    env_file.write_text(
        f"QDRANT_API_KEY=compose-test\nOVERLAPMAMBA_AUTH__KEYS={keys}\n{bounds_env}"
    )
    base = [compose, "--env-file", str(env_file), "-f", str(ROOT / "docker-compose.yml")]

    def call(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [*base, *args], env=env_for(["podman"]), capture_output=True, text=True, cwd=ROOT
        )

    config = call("config")
    assert config.returncode == 0, config.stderr
    assert "OVERLAPMAMBA_INDEX__BACKEND: qdrant" in config.stdout
    assert "stop_grace_period: 60s" in config.stdout
    try:
        up = call("up", "-d", "--no-build", "--no-deps", "overlapmamba")
        assert up.returncode == 0, up.stderr
        t0 = time.perf_counter()
        ready = None
        while time.perf_counter() - t0 < STARTUP_BUDGET_S:
            try:
                if httpx.get("http://127.0.0.1:8000/healthz", timeout=2).status_code == 200:
                    # with keys, the probes' detail (the stage) is a key's only (949952b)
                    key = {"x-api-key": KEY}
                    ready = httpx.get("http://127.0.0.1:8000/readyz", headers=key, timeout=5)
                    if "waiting for the index" in ready.text:
                        break
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        assert ready is not None and ready.status_code == 503, ready and ready.text
        assert "Qdrant at http://qdrant:6333 is unreachable" in ready.json()["detail"]["stage"]
        # the bounds set in .env reach the container
        labels = ["--filter", "label=com.docker.compose.project=overlapmamba"]
        labels += ["--filter", "label=com.docker.compose.service=overlapmamba"]
        ids = _run("ps", "-q", *labels).stdout.split()
        limits = "{{.HostConfig.NanoCpus}} {{.HostConfig.Memory}}"
        bounds = _run("inspect", "--format", limits, ids[0]).stdout.split()
        assert bounds == [str(10**9), str(1536 * 1024**2)], bounds
    finally:
        down = call("down", "-v")
        assert down.returncode == 0, down.stderr
