"""The locks: constraints.txt (what ``make test`` and ``make serve`` install) and
deploy/requirements-serve.txt (what the image installs, with every file's hash), both
written by ``make lock`` (deploy/lock.py). Offline: these read the files and this
environment; tests/test_deploy.py installs the hashed lock into a fresh venv and serves
from it, and ``make image-test`` builds the image with it.
"""

from __future__ import annotations

import re
import sys
import tomllib
from importlib.metadata import PackageNotFoundError, distribution
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parents[1]
SERVE_LOCK = ROOT / "deploy" / "requirements-serve.txt"
sys.path.insert(0, str(ROOT / "deploy"))


def lock_pins() -> dict[str, str]:
    pinned = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, _, version = line.partition("==")
            pinned[canonicalize_name(name)] = version
    return pinned


def hashed_entries(text: str) -> dict[str, tuple[str, list[str], bool]]:
    """name → (version, hashes, whether its marker holds here) of a ``--generate-hashes``
    requirements file."""
    joined = re.sub(r"\\\n\s*", " ", text)
    out = {}
    for line in joined.splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        req, *hashes = line.split(" --hash=")
        spec = Requirement(req.strip())
        (pin,) = list(spec.specifier)
        assert pin.operator == "==", line
        here = spec.marker is None or spec.marker.evaluate()
        assert canonicalize_name(spec.name) not in out, f"{spec.name} is listed twice"
        out[canonicalize_name(spec.name)] = (pin.version, [h.strip() for h in hashes], here)
    return out


def serve_closure() -> set[str]:
    """The names the ``serve`` extra installs here: pyproject's core and serve requirements
    (with their extras) and, recursively, what each installed distribution requires on this
    platform, plus the build backend the image builds the source with."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    todo = [
        Requirement(r)
        for r in (*project["dependencies"], *project["optional-dependencies"]["serve"])
    ]
    extras_of: dict[str, set[str]] = {}
    while todo:
        req = todo.pop()
        name = canonicalize_name(req.name)
        known = extras_of.get(name)
        if known is not None and set(req.extras) <= known:
            continue
        extras = extras_of[name] = (known or set()) | set(req.extras)
        try:
            dist = distribution(name)
        except PackageNotFoundError:  # not installed here: named all the same
            continue
        envs = [{"extra": e} for e in extras] or [{"extra": ""}]
        for text in dist.requires or []:
            dep = Requirement(text)
            if dep.marker is None or any(dep.marker.evaluate(env) for env in envs):
                todo.append(dep)
    return set(extras_of) | {"setuptools"}


def test_the_lock_pins_every_requirement_within_what_pyproject_allows():
    """constraints.txt is what a fresh machine installs: every requirement of the project
    and its extras must be pinned there (one left out would take whatever was released
    since), at a version pyproject.toml allows, and make's installs must take it."""
    from lock import pins

    pinned = lock_pins()
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    extras = project["optional-dependencies"].values()
    every = [*project["dependencies"], *(req for extra in extras for req in extra)]
    for text in every:
        req = Requirement(text)
        name = canonicalize_name(req.name)
        assert name in pinned, f"{req.name} is not in constraints.txt: run make lock"
        version = pinned[name].split("+")[0]  # torch's local tag (+cpu)
        assert req.specifier.contains(version, prereleases=True), (text, pinned[name])
    make = (ROOT / "Makefile").read_text()
    assert make.count("-c constraints.txt -e '.[") == 2  # the dev set and the serve set
    # uv takes a package from the first index that has it: with PyTorch's beside PyPI, the
    # pins of numpy, pillow … must be matched across both
    assert "whl/cpu --index-strategy unsafe-best-match" in make
    # the freeze it is written from: installers, editables and URLs left out, sorted
    frozen = "Zeta==1.0\n-e file:///src\npip==23.2\nuv==0.9\nalpha==2.0+cpu\nx @ file:///x.whl\n"
    assert pins(frozen) == ["alpha==2.0+cpu", "Zeta==1.0"]
    # found in review: the freeze was pip's, in which a package installed from a file is
    # "name @ URL": its pin was dropped. Every installed package but the installers and the
    # project itself is pinned from this environment
    from importlib.metadata import distributions

    from lock import SKIP, freeze

    got = {canonicalize_name(p.partition("==")[0]) for p in pins(freeze(sys.executable))}
    have = {canonicalize_name(d.metadata["Name"]) for d in distributions()}
    assert have - got <= {*SKIP, "overlapmamba"}, have - got


def test_the_images_hashed_lock_is_the_serve_closure_at_the_locks_versions():
    """deploy/requirements-serve.txt, which the image installs with --require-hashes: every
    package the serve extra needs here is in it (pip refuses a hashed install with one
    missing), each at constraints.txt's version with at least one SHA-256, and nothing
    torch's. Out of step after an edit of pyproject.toml or the lock: run make lock."""
    entries = hashed_entries(SERVE_LOCK.read_text())
    pinned = lock_pins()
    for name, (version, hashes, here) in entries.items():
        if here:  # the lock is this platform's (colorama, for one, is Windows' alone)
            assert pinned.get(name) == version, f"{name}=={version}, the lock {pinned.get(name)}"
        assert hashes and all(re.fullmatch(r"sha256:[0-9a-f]{64}", h) for h in hashes), name
    missing = serve_closure() - set(entries)
    assert not missing, f"{sorted(missing)} are not in {SERVE_LOCK.name}: run make lock"
    assert "torch" not in entries and "setuptools" in entries
    assert SERVE_LOCK.read_text().startswith("# What the image installs")


def test_the_hashed_lock_reader_and_the_closure_find_what_is_wrong():
    """The checks above can fail: an entry without a hash, an unpinned one, and a closure
    that names what the serve extra pulls in through an extra (uvicorn[standard])."""
    good = "a==1.0 \\\n    --hash=sha256:" + "0" * 64 + "\nb==2.0 ; sys_platform == 'win32'\n"
    entries = hashed_entries(good)
    assert entries["a"] == ("1.0", ["sha256:" + "0" * 64], True)
    assert entries["b"] == ("2.0", [], sys.platform == "win32")
    with pytest.raises(AssertionError):
        hashed_entries("a>=1.0 \\\n    --hash=sha256:" + "0" * 64 + "\n")
    closure = serve_closure()
    assert {"uvicorn", "uvloop", "httptools", "starlette", "pydantic-core"} <= closure


def test_find_uv_says_what_to_do_without_one(tmp_path, monkeypatch):
    import lock

    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(SystemExit, match="pip install uv"):
        lock.find_uv(str(tmp_path / "python"))
    (tmp_path / "uv").write_text("")
    assert lock.find_uv(str(tmp_path / "python")) == str(tmp_path / "uv")
