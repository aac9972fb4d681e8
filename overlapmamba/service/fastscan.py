"""The served encoder's fast path: the exported graph cut at its scan nodes, onnxruntime for
the parts between them, the C kernel (:mod:`overlapmamba.core.scan_kernel`) for each scan.

    range_image → [session 0] → scan (C) → [session 1] → … → descriptor, yaw_features

The exported file marks every scan as one ``overlapmamba.SelectiveScan[Ring]`` node with its
body (ONNX ``Scan`` loops) as a model-local function: the portable path lets onnxruntime
inline that body, this path runs the same node with the kernel the model was trained with.
It is built at load from the very file the portable path runs, and
:class:`overlapmamba.service.encoder.
Encoder` checks the two against each other before serving with it.

**Cutting the graph.** Every node gets a stage: the number of scans it depends on. Stage j
is one onnxruntime session whose inputs are the tensors it needs from the graph's input,
from earlier stages and from scans, and whose outputs are what later stages, scans and the
graph's outputs need from it. The scans between stage j and j + 1 read their inputs from
what has been computed so far. With one block that is two sessions and the block's scans
between them.

**No spinning.** The stages' sessions are built with onnxruntime's intra-op spinning off:
after a run, a spinning worker keeps its core busy waiting for more work, and here the next
work is the C kernel's, which then runs on a shared core. On 2 threads that made the staged
encoder slower than the portable graph (38–42 ms against 24–31 ms for the narrow model;
21–23 ms with spinning off, measured in one run). With one thread there is no worker.
Spinning within a stage and stopping at its end (``session.force_spinning_stop``) makes a
lone encoder ≈ 10 % faster on 2 threads, but under a fleet's load (8 simulated robots,
verification on) the spinning workers take the cores that decoding, the query's preparation
and registration need: 28.5–29.4 observations/s against 30.7–32.1 with spinning off, in
alternating runs on one machine. The service is sized by its load, so spinning stays off.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import onnx
import onnxruntime as ort
from onnx import helper, numpy_helper, shape_inference

from overlapmamba.core.modelmeta import INPUT, OUTPUTS, SCAN_DOMAIN, SCAN_OPS
from overlapmamba.core.scan_kernel import scan_forward

_CIRCULAR = {name: circular for circular, name in SCAN_OPS.items()}


class FastPathError(RuntimeError):
    """The graph cannot be cut at its scans (the message says why)."""


def _subgraph_refs(graph: onnx.GraphProto) -> set[str]:
    """Names a subgraph reads from the scope around it."""
    defined = {i.name for i in graph.input} | {t.name for t in graph.initializer}
    used: set[str] = set()
    for node in graph.node:
        used |= _reads(node)
        defined |= set(node.output)
    return used - defined


def _reads(node: onnx.NodeProto) -> set[str]:
    """Every tensor a node reads: its inputs, and what its subgraphs take from outside."""
    names = {n for n in node.input if n}
    for attr in node.attribute:
        if attr.type == onnx.AttributeProto.GRAPH:
            names |= _subgraph_refs(attr.g)
        elif attr.type == onnx.AttributeProto.GRAPHS:
            for g in attr.graphs:
                names |= _subgraph_refs(g)
    return names


def is_scan(node: onnx.NodeProto) -> bool:
    return node.domain == SCAN_DOMAIN and node.op_type in _CIRCULAR


def scan_nodes(proto: onnx.ModelProto) -> list[onnx.NodeProto]:
    return [n for n in proto.graph.node if is_scan(n)]


@dataclass
class _Stage:
    session: ort.InferenceSession
    inputs: list[str]
    outputs: list[str]
    scans: list[onnx.NodeProto]  # run after this stage, in graph order


class StagedGraph:
    """An exported encoder cut at its scan nodes (see the module notes)."""

    def __init__(self, proto: onnx.ModelProto, opts: ort.SessionOptions, threads: int) -> None:
        """``opts``: the sessions' options (threads); spinning is turned off in them."""
        self.threads = max(1, threads)
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        graph = proto.graph
        scans = scan_nodes(proto)
        if not scans:
            raise FastPathError(
                f"the graph has no {SCAN_DOMAIN} scan node (exported before scans were marked)"
            )
        inits = {t.name: t for t in graph.initializer}
        # A scan reads A and D as constants: keep them as arrays, not in a session.
        self.constants = {
            name: numpy_helper.to_array(inits[name])
            for node in scans
            for name in node.input
            if name in inits
        }
        stage_of: dict[str, int] = {i.name: 0 for i in graph.input}
        node_stage: list[tuple[int, onnx.NodeProto]] = []
        scans_after: dict[int, list[onnx.NodeProto]] = {}
        for node in graph.node:
            reads = _reads(node) - inits.keys()
            s = max((stage_of.get(n, 0) for n in reads), default=0)
            if is_scan(node):
                if len(node.input) != 6 or len(node.output) != 1:
                    raise FastPathError(f"scan node {node.name!r} is not (u, Δ, A, B, C, D) → y")
                scans_after.setdefault(s, []).append(node)
                stage_of[node.output[0]] = s + 1
            else:
                node_stage.append((s, node))
                stage_of.update({o: s for o in node.output if o})
        types = _tensor_types(proto)
        later_reads: dict[int, set[str]] = {}  # stage → what it and every later step reads
        for s, node in node_stage:
            later_reads.setdefault(s, set()).update(_reads(node))
        for s, nodes in scans_after.items():
            later_reads.setdefault(s + 1, set()).update(n for node in nodes for n in node.input)
        n_stages = max(stage_of.values()) + 1
        graph_outputs = {o.name for o in graph.output}
        self.stages: list[_Stage] = []
        for j in range(n_stages):
            nodes = [node for s, node in node_stage if s == j]
            made = {o for node in nodes for o in node.output if o}
            reads = set().union(*(_reads(node) for node in nodes)) if nodes else set()
            inputs = sorted(reads - made - inits.keys())
            needed_later = set().union(*(later_reads.get(k, set()) for k in range(j + 1, n_stages)))
            needed_later |= {n for node in scans_after.get(j, []) for n in node.input}
            outputs = sorted(made & (needed_later | graph_outputs))
            self.stages.append(
                _Stage(
                    session=self._session(proto, j, nodes, inputs, outputs, inits, types, opts),
                    inputs=inputs,
                    outputs=outputs,
                    scans=scans_after.get(j, []),
                )
            )
        self.scan_count = len(scans)

    @staticmethod
    def _session(
        proto: onnx.ModelProto,
        j: int,
        nodes: list[onnx.NodeProto],
        inputs: list[str],
        outputs: list[str],
        inits: dict[str, onnx.TensorProto],
        types: dict[str, int],
        opts: ort.SessionOptions,
    ) -> ort.InferenceSession:
        missing = [n for n in (*inputs, *outputs) if n not in types]
        if missing:
            raise FastPathError(f"stage {j}: no element type known for {missing[:5]}")
        used = set().union(*(_reads(node) for node in nodes)) if nodes else set()
        graph = helper.make_graph(
            nodes,
            f"stage{j}",
            [helper.make_tensor_value_info(n, types[n], None) for n in inputs],
            [helper.make_tensor_value_info(n, types[n], None) for n in outputs],
            initializer=[inits[n] for n in sorted(used & inits.keys())],
        )
        model = helper.make_model(
            graph,
            opset_imports=[o for o in proto.opset_import if o.domain != SCAN_DOMAIN],
            ir_version=proto.ir_version,
        )
        model.functions.extend(f for f in proto.functions if f.domain != SCAN_DOMAIN)
        try:
            return ort.InferenceSession(
                model.SerializeToString(), sess_options=opts, providers=["CPUExecutionProvider"]
            )
        except Exception as err:  # onnxruntime raises its own unrelated classes
            raise FastPathError(f"stage {j} does not load in onnxruntime: {err}") from None

    def run(
        self, images: np.ndarray, parts: dict[str, float] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """images (B, 1, H, W) float32 → descriptor (B, D), yaw_features (B, C, W).
        ``parts``: seconds spent in the onnxruntime stages ("sessions") and in the kernel
        ("scan") are added to it (benchmarks/encoder.py splits the served time so)."""
        env: dict[str, np.ndarray] = {INPUT: images}
        clock = time.perf_counter
        t_sessions = t_scan = 0.0
        for stage in self.stages:
            t0 = clock()
            values = stage.session.run(stage.outputs, {n: env[n] for n in stage.inputs})
            t1 = clock()
            env.update(zip(stage.outputs, values, strict=True))
            for node in stage.scans:
                u, delta, A, Bm, Cm, D = (
                    self.constants[n] if n in self.constants else env[n] for n in node.input
                )
                env[node.output[0]] = scan_forward(
                    u, delta, A, Bm, Cm, D, _CIRCULAR[node.op_type], self.threads
                )
            t_sessions += t1 - t0
            t_scan += clock() - t1
        if parts is not None:
            parts["sessions"] = parts.get("sessions", 0.0) + t_sessions
            parts["scan"] = parts.get("scan", 0.0) + t_scan
        desc, yaw = (env[name] for name in OUTPUTS)
        return desc, yaw


def _tensor_types(proto: onnx.ModelProto) -> dict[str, int]:
    """Element type of every tensor of the top-level graph (shape inference; a scan's output
    is float32 by the node's contract)."""
    inferred = shape_inference.infer_shapes(proto, strict_mode=False)
    g = inferred.graph
    types: dict[str, int] = {}
    infos: Iterable[onnx.ValueInfoProto] = (*g.input, *g.output, *g.value_info)
    for info in infos:
        t = info.type.tensor_type.elem_type
        if t:
            types[info.name] = t
    for t in g.initializer:
        types[t.name] = t.data_type
    for node in g.node:
        if is_scan(node):
            types[node.output[0]] = onnx.TensorProto.FLOAT
    return types
