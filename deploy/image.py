"""Build the service's container image here, with podman (or docker where its engine runs),
from nothing a registry must serve: what ``make image`` runs.

    python deploy/image.py base     # localhost/overlapmamba-base:bookworm from Debian's packages
    python deploy/image.py wheels   # deploy/wheelhouse: the runtime's wheels, the venv's versions
    python deploy/image.py build    # the Dockerfile, on that base, from that wheelhouse
    python deploy/image.py all      # the three (make image)
    python deploy/image.py report   # reports/deploy/image.md from the figures measured

**Base.** No registry is reachable from these machines, so ``python:3.11-slim-bookworm``
cannot be pulled. Debian bookworm's own Python is 3.11: ``debootstrap`` makes a minimal
bookworm with python3, its venv module and CA certificates, which is imported as the base
image (``--base IMAGE`` takes any other, e.g. the official slim one where it can be pulled).
**Wheels.** Inside a build PyPI over TLS does not trust this machine's certificate authority,
so the dependencies come from a wheelhouse made on the host with ``pip wheel``, pinned to the
versions installed in the venv the tests ran (the image runs what was tested), plus the
build backend; the Dockerfile installs from it with no index. An air-gapped operator does
the same. **Engine.** podman is installed from Debian where missing (as root); on these
machines it needs runc, the cgroupfs manager and no default ulimits, which
``deploy/containers.conf`` sets for this script's podman calls only.

Each step writes what it measured to ``reports/deploy/image-build.json`` (build time, cold or
with a warm layer cache, the image's size), with the command, commit and machine.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
IMAGE = "localhost/overlapmamba:latest"
BASE = "localhost/overlapmamba-base:bookworm"
WHEELS = ROOT / "deploy" / "wheelhouse"
REPORT = ROOT / "reports" / "deploy" / "image-build.json"
MIRROR = "http://deb.debian.org/debian"
BASE_PACKAGES = "python3,python3-venv,ca-certificates"
# trimmed from the base: documentation, package caches and lists (apt fetches lists again)
TRIM = ("usr/share/doc", "usr/share/man", "usr/share/info", "var/cache/apt", "var/lib/apt/lists")


class ImageError(RuntimeError):
    """A step that cannot go on, with what to do about it."""


def engine() -> list[str]:
    """The container engine's command: podman (installed from Debian where missing, when
    root with apt), else docker when its daemon answers."""
    podman = shutil.which("podman")
    if podman is None and os.geteuid() == 0 and shutil.which("apt-get"):
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        for args in (
            ["apt-get", "update", "-qq"],
            ["apt-get", "install", "-y", "-qq", "podman", "runc", "debootstrap", "fuse-overlayfs"],
        ):
            subprocess.run(args, check=True, env=env, stdout=subprocess.DEVNULL)
        podman = shutil.which("podman")
    if podman is not None:
        return [podman]
    docker = shutil.which("docker")
    if docker and subprocess.run([docker, "info"], capture_output=True).returncode == 0:
        return [docker]
    raise ImageError(
        "no container engine: install podman (apt-get install podman runc) or run a Docker daemon"
    )


def env_for(cmd: list[str]) -> dict[str, str]:
    """podman reads deploy/containers.conf (runc, cgroupfs, no default ulimits) unless the
    caller chose a configuration of their own."""
    env = dict(os.environ)
    if Path(cmd[0]).name == "podman":
        env.setdefault("CONTAINERS_CONF", str(ROOT / "deploy" / "containers.conf"))
    return env


def run(cmd: list[str], *args: str, capture: bool = False, **kw: Any) -> str:
    done = subprocess.run(
        [*cmd, *args], env=env_for(cmd), text=True, capture_output=capture, check=False, **kw
    )
    if done.returncode != 0:
        raise ImageError(
            f"{' '.join([*cmd, *args][:4])} … failed ({done.returncode})"
            + (f": {done.stderr[-2000:]}" if capture else "")
        )
    return done.stdout if capture else ""


def has_image(cmd: list[str], name: str) -> bool:
    return (
        subprocess.run(
            [*cmd, "image", "inspect", name], env=env_for(cmd), capture_output=True
        ).returncode
        == 0
    )


def make_base(cmd: list[str], name: str = BASE, *, force: bool = False) -> dict[str, Any]:
    """A minimal Debian bookworm with python3 and its venv module, imported as ``name``."""
    if has_image(cmd, name) and not force:
        return {"base": name, "made": False}
    if shutil.which("debootstrap") is None:
        raise ImageError("debootstrap is missing: apt-get install debootstrap")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="om-base-") as tmp:
        rootfs = Path(tmp) / "rootfs"
        subprocess.run(
            [
                "debootstrap",
                "--variant=minbase",
                f"--include={BASE_PACKAGES}",
                "bookworm",
                str(rootfs),
                MIRROR,
            ],
            check=True,
            stdout=subprocess.DEVNULL,
        )
        for part in TRIM:
            shutil.rmtree(rootfs / part, ignore_errors=True)
        (rootfs / "var" / "lib" / "apt" / "lists" / "partial").mkdir(parents=True)
        (rootfs / "var" / "cache" / "apt" / "archives" / "partial").mkdir(parents=True)
        archive = Path(tmp) / "rootfs.tar"
        with tarfile.open(archive, "w") as tar:
            tar.add(rootfs, arcname=".")
        run(cmd, "import", "--change", 'CMD ["python3"]', str(archive), name)
    return {"base": name, "made": True, "seconds": round(time.perf_counter() - t0, 1)}


def make_wheels(python: str = sys.executable) -> dict[str, Any]:
    """deploy/wheelhouse: wheels of the runtime's requirements at the versions installed in
    ``python``'s environment (the tested venv), and the build backend."""
    t0 = time.perf_counter()
    sys.path.insert(0, str(ROOT / "deploy"))
    from lock import freeze, pins  # deploy/lock.py
    from requirements import requirements  # deploy/requirements.py

    reqs = requirements(ROOT / "pyproject.toml", ["serve"])
    frozen = freeze(python)
    WHEELS.mkdir(parents=True, exist_ok=True)
    for old in WHEELS.glob("*.whl"):  # an earlier venv's: pip would take the highest
        old.unlink()
    with tempfile.TemporaryDirectory(prefix="om-wheels-") as tmp:
        req, constraints = Path(tmp) / "requirements.txt", Path(tmp) / "constraints.txt"
        req.write_text("\n".join([*reqs, "setuptools"]) + "\n")  # at the venv's version
        constraints.write_text("\n".join(pins(frozen)) + "\n")
        subprocess.run(
            [
                python,
                "-m",
                "pip",
                "wheel",
                "-q",
                "-r",
                str(req),
                "-c",
                str(constraints),
                "-w",
                str(WHEELS),
            ],
            check=True,
        )
    wheels = sorted(WHEELS.glob("*.whl"))
    return {
        "wheels": len(wheels),
        "wheel_bytes": sum(w.stat().st_size for w in wheels),
        "seconds": round(time.perf_counter() - t0, 1),
    }


# What the Dockerfile's build context holds (.dockerignore lets only these in).
CONTEXT = (
    "Dockerfile",
    ".dockerignore",
    "pyproject.toml",
    "README.md",
    "deploy/requirements-serve.txt",
    "deploy/healthcheck.py",
    "deploy/wheelhouse",
    "overlapmamba/__init__.py",
    "overlapmamba/__main__.py",
    "overlapmamba/py.typed",
    "overlapmamba/cli",
    "overlapmamba/core",
    "overlapmamba/service",
    "models/overlapmamba-hdl64.onnx",
)


def build(
    cmd: list[str], base: str, *, no_cache: bool = False, edited: bool = False
) -> dict[str, Any]:
    """The Dockerfile on ``base``; its time, and the image's size. ``edited``: from a copy of
    the context whose source differs by a comment, as after a code change (the dependency
    layers come from the cache, the source layers are rebuilt)."""
    fmt = ["--format", "docker"] if Path(cmd[0]).name == "podman" else []  # keeps HEALTHCHECK
    cache = ["--no-cache"] if no_cache else []
    with tempfile.TemporaryDirectory(prefix="om-context-") as tmp:
        context = ROOT
        if edited:
            context = Path(tmp)
            for part in CONTEXT:
                src, dst = ROOT / part, context / part
                dst.parent.mkdir(parents=True, exist_ok=True)
                if src.is_dir():
                    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("__pycache__"))
                else:
                    shutil.copy2(src, dst)
            marker = context / "overlapmamba" / "service" / "__init__.py"
            marker.write_text(marker.read_text() + f"# edited {time.time_ns()}\n")
        t0 = time.perf_counter()
        build_arg = f"PYTHON_IMAGE={base}"
        run(cmd, "build", *fmt, *cache, "--build-arg", build_arg, "-t", IMAGE, str(context))
        seconds = time.perf_counter() - t0
    size = int(run(cmd, "image", "inspect", IMAGE, "--format", "{{.Size}}", capture=True).strip())
    return {"image": IMAGE, "base": base, "seconds": round(seconds, 1), "bytes": size}


def provenance() -> dict[str, Any]:
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from bench_kit import provenance as bench_provenance

    return bench_provenance()


def record(key: str, values: dict[str, Any]) -> None:
    """Merge one step's figures into reports/deploy/image-build.json."""
    REPORT.parent.mkdir(parents=True, exist_ok=True)
    report = json.loads(REPORT.read_text()) if REPORT.is_file() else {}
    report[key] = {**values, **provenance()}
    REPORT.write_text(json.dumps(report, indent=2) + "\n")


MARKDOWN = ROOT / "reports" / "deploy" / "image.md"
CHECKS = ROOT / "reports" / "deploy" / "image.json"  # written by tests/test_image.py


def markdown() -> str:
    """The image's figures as docs/deploy.md includes them: size, build times, start-up."""
    build = json.loads(REPORT.read_text()) if REPORT.is_file() else {}
    checks = json.loads(CHECKS.read_text()) if CHECKS.is_file() else {}
    machine = (build.get("build_cold") or checks or {}).get("machine", {})

    def where(m: dict[str, Any]) -> str:
        return f"{m.get('cores', '?')} cores, {m.get('cpu', '?')}"

    def elsewhere(record: dict[str, Any]) -> str:  # a row measured on another machine says so
        m = record.get("machine", {})
        return "" if not m or where(m) == where(machine) else f" (on {where(m)})"

    rows = []
    for key, label in (
        ("base", "base image from Debian's packages (debootstrap, import)"),
        ("wheels", "wheelhouse (pip wheel, the venv's versions)"),
        ("build_cold", "image build, cold (no layer cache)"),
        ("build_cached", "image build by `make image` (the layer cache as it found it)"),
        ("build_after_a_source_edit", "image build after a source edit (warm layer cache)"),
    ):
        if key in build:
            b = build[key]
            rows.append(
                f"| {label} | {b['seconds']:.0f} s | `{b['command']}` at "
                f"{b['commit'][:12]}, {b['date'][:10]}{elsewhere(b)} |"
            )
    if "image_bytes" in checks:
        start = checks["start_to_ready_s"]
        rows += [
            f"| image size | {checks['image_bytes'] / 1e6:.0f} MB | `make image-test` at "
            f"{checks['commit'][:12]}, {checks['date'][:10]}{elsewhere(checks)} |",
            f"| `run` to `/readyz` 200, first start / restart on the same volume | "
            f"{start['first']:.1f} / {start['restart']:.1f} s | the same run |",
            f"| a real KITTI scan's descriptor, image against venv (max abs) | "
            f"{checks['descriptor_max_abs_vs_venv']:.1e} | the same run |",
            f"| keyframes back after SIGTERM and a restart | "
            f"{checks['keyframes_back_after_sigterm']} | the same run |",
        ]
    head = "| what | measured | command |\n|---|---|---|\n"
    return f"On this project's machine ({where(machine)}):\n\n" + head + "\n".join(rows) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("step", choices=["base", "wheels", "build", "all", "report"])
    ap.add_argument("--base", default=None, help=f"the base image (default: {BASE}, made here)")
    ap.add_argument(
        "--cold", action="store_true", help="build without the layer cache (timed as cold)"
    )
    ap.add_argument(
        "--edited",
        action="store_true",
        help="time a rebuild after a source edit (a copy of the context; warm layer cache)",
    )
    args = ap.parse_args()
    if args.step == "report":
        MARKDOWN.parent.mkdir(parents=True, exist_ok=True)
        MARKDOWN.write_text(markdown())
        print(f"wrote {MARKDOWN}")
        return 0
    try:
        cmd = engine()
        base = args.base or BASE
        if args.step in ("base", "all") and args.base is None:
            out = make_base(cmd)
            print(f"base {base}: " + ("made" if out["made"] else "present"))
            if out["made"]:
                record("base", out)
        if args.step in ("wheels", "all"):
            out = make_wheels()
            print(f"wheelhouse: {out['wheels']} wheels, {out['wheel_bytes'] / 1e6:.0f} MB")
            record("wheels", out)
        if args.step in ("build", "all"):
            out = build(cmd, base, no_cache=args.cold, edited=args.edited)
            kind = "cold" if args.cold else "after_a_source_edit" if args.edited else "cached"
            print(f"{IMAGE}: {out['bytes'] / 1e6:.0f} MB, built in {out['seconds']:.0f} s ({kind})")
            record(f"build_{kind}", out)
    except (ImageError, subprocess.CalledProcessError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
