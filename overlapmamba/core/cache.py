"""Where derived data (loop tables, range images, compiled kernels) is cached."""

from __future__ import annotations

import os
from pathlib import Path


def cache_root() -> Path:
    """``$OVERLAPMAMBA_CACHE``, default ``~/.cache/overlapmamba``. Never a data folder: real
    data is shared and must stay untouched."""
    return Path(os.environ.get("OVERLAPMAMBA_CACHE", Path.home() / ".cache" / "overlapmamba"))
