"""onnxruntime's own per-operator profile of an exported encoder, for ``benchmarks/encoder.py``:
where a run's time goes, by operator type, at the top level and inside the scans' loops."""

from __future__ import annotations

import collections
import json
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort


def op_profile(path: Path, x1: np.ndarray, runs: int = 10) -> dict[str, dict[str, float]]:
    """ms per run by operator type, one thread: the top level (Scan includes its loop bodies;
    the entries partition the run) and, separately, the nodes inside the loop bodies."""
    proto = onnx.load(str(path))
    body_names = {n.name for n in _body_nodes(proto.graph.node)}
    for fn in proto.functions:  # the scans' bodies, in the local function onnxruntime inlines
        body_names |= {f"_inlfunc_{fn.name}_{n.name}" for n in _body_nodes(fn.node)}
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    so.enable_profiling = True
    so.profile_file_prefix = str(path.with_suffix(""))
    sess = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    for _ in range(runs):
        sess.run(None, {"range_image": x1})
    trace = Path(sess.end_profiling())
    top: collections.Counter = collections.Counter()
    body: collections.Counter = collections.Counter()
    for ev in json.loads(trace.read_text()):
        if ev.get("cat") == "Node" and ev["name"].endswith("_kernel_time"):
            node = ev["name"][: -len("_kernel_time")]
            (body if node in body_names else top)[ev["args"]["op_name"]] += ev["dur"] / 1e3 / runs
    trace.unlink()
    return {"top_level": dict(top.most_common()), "inside_scan": dict(body.most_common())}


def _body_nodes(nodes) -> list[onnx.NodeProto]:  # type: ignore[no-untyped-def]
    out = []
    for node in nodes:
        for attr in node.attribute:
            if attr.type == onnx.AttributeProto.GRAPH:
                out += list(attr.g.node) + _body_nodes(attr.g.node)
    return out
