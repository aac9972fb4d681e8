"""The test suite's shared synthetic data, made in the background from the start of a run
(``tests/conftest.py`` starts it): synthetic presets one after another, then
optionally the shared tiny training run on the first two and its export, each marked done
when whole (``NAME.done``). The run's history is pickled as ``train`` returned it (NaNs
included).

    python tests/background_towns.py ROOT PRESET [PRESET ...] [--run [--onnx]]
"""

from __future__ import annotations

import pickle
import sys
from pathlib import Path

if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).parent))
    from conftest import export_tiny_run, generate_preset, train_tiny_run

    root = Path(sys.argv[1])
    for name in [a for a in sys.argv[2:] if not a.startswith("--")]:
        generate_preset(root / name, name)
        (root / f"{name}.done").touch()
    if "--run" in sys.argv:
        history = train_tiny_run(root / "tiny", root / "tiny-check", root / "runs" / "tiny")
        (root / "tiny-run.pkl").write_bytes(pickle.dumps(history))
        (root / "tiny-run.done").touch()
        if "--onnx" in sys.argv:
            export_tiny_run(root / "runs" / "tiny", root / "tiny.onnx")
            (root / "tiny-onnx.done").touch()
