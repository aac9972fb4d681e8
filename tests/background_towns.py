"""Generate synthetic presets one after another into a folder, each marked done when whole
(``NAME.done``): the test suite's tiny towns, started at the beginning of a run in the
background (``tests/conftest.py``), at low priority.

    python tests/background_towns.py ROOT PRESET [PRESET ...]
"""

from __future__ import annotations

import sys
from pathlib import Path

from overlapmamba.synth.generate import generate
from overlapmamba.synth.presets import PRESETS

if __name__ == "__main__":
    root = Path(sys.argv[1])
    for name in sys.argv[2:]:
        # Its own stall limit: a stuck or dead worker fails the run with the chunk named.
        generate(root / name, PRESETS[name], workers=2, progress=False, stall_timeout_s=120)
        (root / f"{name}.done").touch()
