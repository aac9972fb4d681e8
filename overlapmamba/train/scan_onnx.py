"""The selective scan in the exported ONNX graph: one ``overlapmamba`` node per block, defined
by a model-local ONNX function whose body is :func:`overlapmamba.train.scan.selective_scan_loop`.

    model (scan backend "onnx") ──torch.onnx.export──► graph with one SelectiveScan[Ring] node
    selective_scan_loop ──torch.onnx.export──► FunctionProto (the node's body, Scan loops)

Why a function: every ONNX runtime inlines a model-local function, so the file stays
portable (standard operators inside, the scan as ``Scan`` loops, no custom library needed),
and a runtime that brings its own kernel for the node (the service's fast path,
:mod:`overlapmamba.service.fastscan`) finds the whole scan as one node with named inputs, instead of
reshapes and transposes around three or four loops.

The node's contract (names in :data:`overlapmamba.core.modelmeta.SCAN_OPS`), float32, token-major::

    inputs   u, delta: (B, L, E)   A: (E, N)   B, C: (B, L, N)   D: (E,)
    output   y: (B, L, E)
    SelectiveScan      open scan from h = 0
    SelectiveScanRing  circular scan from the ring's periodic state (overlapmamba.train.scan)

In PyTorch the node is the custom operator ``torch.ops.overlapmamba.selective_scan``, whose
eager implementation is the loop algorithm itself: the model with ``scan_backend="onnx"``
computes exactly what the exported body computes.
"""

from __future__ import annotations

import contextlib
import functools
import io
import logging
import warnings

import onnx
import onnxscript
import torch
from onnx import defs, helper
from torch import Tensor

from overlapmamba.core.modelmeta import SCAN_DOMAIN, SCAN_OPS
from overlapmamba.train.scan import selective_scan_loop

SCAN_INPUTS = ("u", "delta", "A", "B", "C", "D")


def _register_schemas() -> None:
    """The nodes' schemas in onnx's registry: the exporter's tracer and onnx.checker look
    operators up there (the runtime never does: it reads the local function)."""
    for name in SCAN_OPS.values():
        if defs.has(name, SCAN_DOMAIN):
            continue
        defs.register_schema(
            defs.OpSchema(
                name,
                SCAN_DOMAIN,
                1,
                doc=f"{name}: the selective scan (overlapmamba.train.scan_onnx)",
                inputs=[defs.OpSchema.FormalParameter(n, "T") for n in SCAN_INPUTS],
                outputs=[defs.OpSchema.FormalParameter("y", "T")],
                type_constraints=[("T", ["tensor(float)"], "float32 only")],
            )
        )


_register_schemas()
_OPSET = onnxscript.values.Opset(SCAN_DOMAIN, 1)


@torch.library.custom_op("overlapmamba::selective_scan", mutates_args=())
def selective_scan_op(
    u: Tensor,
    delta: Tensor,
    A: Tensor,
    Bm: Tensor,
    Cm: Tensor,
    D: Tensor,
    circular: bool,
    chunk: int | None = None,
) -> Tensor:
    """The exported scan as one PyTorch operator (eager: the loop algorithm)."""
    return selective_scan_loop(u, delta, A, Bm, Cm, D, circular, chunk)


@selective_scan_op.register_fake
def _(u, delta, A, Bm, Cm, D, circular, chunk=None):
    return torch.empty_like(u)


def _translate(u, delta, A, Bm, Cm, D, circular: bool = False, chunk: int | None = None):
    op = getattr(_OPSET, SCAN_OPS[bool(circular)])
    return op(u, delta, A, Bm, Cm, D)


TRANSLATIONS = {torch.ops.overlapmamba.selective_scan.default: _translate}


class _Body(torch.nn.Module):
    def __init__(self, circular: bool, chunk: int | None) -> None:
        super().__init__()
        self.circular, self.chunk = circular, chunk

    def forward(self, u, delta, A, Bm, Cm, D):
        return selective_scan_loop(u, delta, A, Bm, Cm, D, self.circular, self.chunk)


def quiet_export(module: torch.nn.Module, args: tuple, **kwargs) -> onnx.ModelProto:
    """torch.onnx.export (dynamo) without its progress lines and warnings; raises what it
    raises, with the end of what it printed as a note (the caller names the step)."""
    sink = io.StringIO()
    logger = logging.getLogger("torch.onnx")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        with (
            warnings.catch_warnings(),
            contextlib.redirect_stdout(sink),
            contextlib.redirect_stderr(sink),
        ):
            warnings.simplefilter("ignore")
            program = torch.onnx.export(module, args, dynamo=True, optimize=True, **kwargs)
    except Exception as err:
        err.add_note(sink.getvalue()[-2000:])
        raise
    finally:
        logger.setLevel(level)
    if program is None:
        raise RuntimeError("torch.onnx.export returned no program")
    proto: onnx.ModelProto = program.model_proto
    return proto


def scan_function(
    circular: bool, length: int, channels: int, state: int, chunk: int | None, opset: int
) -> onnx.FunctionProto:
    """The node's body for one scan shape: :func:`selective_scan_loop` exported with a
    symbolic batch axis (L, E, N fixed, as they are in one model), as a FunctionProto.

    Exported once per process and shape (half of a model's export time), then copied: the
    exporter numbers the nodes it names across calls, so without the cache a second export
    of the same model in one process got another function, and another model id."""
    out = onnx.FunctionProto()
    out.CopyFrom(_scan_function(circular, length, channels, state, chunk, opset))
    return out


@functools.lru_cache(maxsize=16)
def _scan_function(
    circular: bool, length: int, channels: int, state: int, chunk: int | None, opset: int
) -> onnx.FunctionProto:
    B = 2  # not 1: the exporter would specialise a size-1 example axis to a constant
    ex = (
        torch.zeros(B, length, channels),
        torch.zeros(B, length, channels),
        -torch.ones(channels, state),
        torch.zeros(B, length, state),
        torch.zeros(B, length, state),
        torch.ones(channels),
    )
    batch = torch.export.Dim("batch", min=1, max=1 << 16)
    per_row = {0: batch}
    proto = quiet_export(
        _Body(circular, chunk),
        ex,
        dynamic_shapes=(per_row, per_row, None, per_row, per_row, None),
    )
    g = proto.graph
    # A function has no initializers: its constants become Constant nodes.
    consts = [helper.make_node("Constant", [], [t.name], value=t) for t in g.initializer]
    return helper.make_function(
        SCAN_DOMAIN,
        SCAN_OPS[bool(circular)],
        [i.name for i in g.input],
        [o.name for o in g.output],
        consts + list(g.node),
        opset_imports=[helper.make_opsetid("", opset)],
    )


def attach_functions(
    proto: onnx.ModelProto, length: int, channels: int, state: int, chunk: int | None
) -> int:
    """Give every scan node of an exported graph its body as a local function; returns the
    number of scan nodes. Raises ValueError when a node's domain is not ours."""
    opset = next(o.version for o in proto.opset_import if o.domain in ("", "ai.onnx"))
    used: set[str] = set()
    count = 0
    for node in proto.graph.node:
        if node.domain in ("", "ai.onnx"):
            continue
        if node.domain != SCAN_DOMAIN or node.op_type not in SCAN_OPS.values():
            raise ValueError(f"unexpected operator {node.domain}.{node.op_type} in the graph")
        used.add(node.op_type)
        count += 1
    for circular, name in SCAN_OPS.items():
        if name in used and not any(f.name == name for f in proto.functions):
            proto.functions.append(scan_function(circular, length, channels, state, chunk, opset))
    return count
