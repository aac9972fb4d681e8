"""The files a command writes its results to (``overlapmamba eval``'s JSON and plot,
``overlapmamba-client simulate-fleet``'s report and plot): checked before the work that fills
them, and written whole or not at all.

A folder in a file's place, a file in a folder's, a folder that cannot be made or written
into, a plot format nothing writes: each used to be found after minutes of work, whose
result was then lost. A file written in place and cut off (a killed run, a full disk)
leaves a torn file that a later reader takes for a result; :func:`write_whole` leaves the
old one or the new one.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Collection, Iterator
from pathlib import Path

# (flag, path or None, allowed suffixes without the dot or None: any)
Output = tuple[str, Path | None, Collection[str] | None]


def check_outputs(*outputs: Output) -> None:
    """Check where each output goes, all of them before any folder is made (a refused
    command leaves nothing behind), then make their folders and check that a file can be
    written there. A ValueError names the flag, the path and what is wrong."""
    given = [(flag, path, formats) for flag, path, formats in outputs if path is not None]
    seen: dict[Path, str] = {}
    for flag, path, _ in given:
        assert path is not None
        where = path.resolve()
        if where in seen:
            raise ValueError(
                f"{seen[where]} and {flag} are the same file, {path}: give each its own"
            )
        seen[where] = flag
    for flag, path, formats in given:
        assert path is not None
        if path.is_dir():
            raise ValueError(f"{flag} {path} is a folder; give a file name")
        if formats is not None and path.suffix.lower().lstrip(".") not in formats:
            allowed = ", ".join(sorted(formats))
            raise ValueError(f"{flag} {path}: allowed formats are {allowed}")
        in_the_way = next((p for p in path.parents if p.exists() and not p.is_dir()), None)
        if in_the_way is not None:
            raise ValueError(f"{flag} {path}: {in_the_way} is a file, not a folder")
    for flag, path, _ in given:
        assert path is not None
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise ValueError(f"{flag} {path}: cannot make its folder: {err.strerror}") from None
        if not os.access(path.parent, os.W_OK):
            raise ValueError(f"{flag} {path}: cannot write into {path.parent}")


@contextlib.contextmanager
def replacing(path: Path, suffix: str = "") -> Iterator[Path]:
    """A temporary file beside ``path`` (ending in ``suffix``, for writers that add their
    own) for the block to write, renamed over ``path`` once the block ends without error. No
    temporary file is left either way, and a failure to remove it never hides the error that
    ended the block."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}{suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)


def write_whole(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` whole or not at all (:func:`replacing`)."""
    with replacing(path) as tmp:
        tmp.write_text(text)


def incomplete_path(path: Path, suffix: str) -> Path:
    """Where a failed run keeps what it wrote of ``path``: beside it, ``NAME.incomplete``
    and the path's suffix (``suffix`` for a bare path), else ``NAME.incomplete-2…``: an
    earlier failed run's is never replaced."""
    name = f"{path.stem}.incomplete"
    suffix = path.suffix or suffix
    for n in range(1, 10_000):
        kept = path.with_name(f"{name}{'' if n == 1 else f'-{n}'}{suffix}")
        if not kept.exists():
            return kept
    raise OSError(f"no free name for {name}{suffix} beside {path}")
