"""Checks of any ONNX adapter model before it is stored or run (docs/method.md section 12).

An uploaded model is untrusted. :func:`validate_model` refuses, with an :class:`AdapterError` naming the reason
(``field``), a model that is:

- larger than ``max_bytes`` (``model.size``), or not an ONNX model at all (``model``);
- for an opset or operator domain not allowed: the default ONNX domain only, opset 13 to 21
  (``model.opset_import``); with model-local functions (``model.functions``);
- using an operator outside :data:`ALLOWED_OPS` or any other domain, e.g. a custom op (``model.graph.node``),
  or a node with a subgraph;
- referring to external data (a tensor whose bytes live in another file: ``model.external_data``);
- with inputs and outputs other than the manifest's: one input ``source`` float32 [B, S], outputs ``expression``
  float32 [B, T] and, when the manifest has joints, ``joints`` float32 [B, J, 3] (``model.graph.input`` /
  ``model.graph.output``);
- rejected by the ONNX checker (``model``);
- of a cost that cannot be bounded statically or passes a bound (``model``, "cost" in the message: a tensor's
  elements, all intermediate bytes, the work, for the largest batch; :mod:`.cost`), found by shape inference
  before anything runs;
- failing to load or to run a probe batch in onnxruntime (within :data:`PROBE_LIMIT_S`), or giving outputs of
  other shapes (``model.run``). Only a model whose cost is bounded is ever loaded and run.
"""

from __future__ import annotations

import numpy as np
import onnx
from google.protobuf.message import DecodeError

from .cost import adapter_cost
from .manifest import INPUT, OUTPUT_EXPRESSION, OUTPUT_JOINTS, AdapterError, AdapterManifest

MAX_MODEL_BYTES = 16 << 20
MAX_NODES = 256
PROBE_LIMIT_S = 10.0  # the probe run of a bounded model takes milliseconds; a hard stop, not a budget
OPSETS = range(13, 22)
DOMAINS = ("", "ai.onnx")
ALLOWED_OPS = frozenset({
    "MatMul", "Gemm", "Add", "Sub", "Mul", "Div", "Neg", "Abs", "Max", "Min", "Clip", "Relu", "LeakyRelu", "Tanh",
    "Sigmoid", "Exp", "Sqrt", "Reshape", "Flatten", "Identity", "Concat", "Split", "Slice", "Squeeze", "Unsqueeze",
    "Transpose", "Constant", "Cast",
})


def _tensors(model: onnx.ModelProto):
    g = model.graph
    yield from g.initializer
    for sparse in g.sparse_initializer:
        yield sparse.values
        yield sparse.indices
    for node in g.node:
        for attr in node.attribute:
            if attr.HasField("t"):
                yield attr.t
            yield from attr.tensors


def _dims(vi: onnx.ValueInfoProto) -> tuple[int, list[int | None]]:
    t = vi.type.tensor_type
    return t.elem_type, [d.dim_value if d.HasField("dim_value") else None for d in t.shape.dim]


def parse_model(data: bytes, max_bytes: int = MAX_MODEL_BYTES) -> onnx.ModelProto:
    if len(data) > max_bytes:
        raise AdapterError(f"the model is {len(data)} bytes; the limit is {max_bytes}", field="model.size")
    try:
        model = onnx.ModelProto.FromString(data)
    except (DecodeError, ValueError, RuntimeError) as e:
        raise AdapterError(f"not an ONNX model ({type(e).__name__})", field="model") from None
    if not model.HasField("graph") or not model.graph.output:
        raise AdapterError("not an ONNX model (no graph)", field="model")
    return model


def validate_model(data: bytes, manifest: AdapterManifest, max_bytes: int = MAX_MODEL_BYTES) -> onnx.ModelProto:
    """Every check of the module docstring, in that order; returns the parsed model."""
    model = parse_model(data, max_bytes)
    for op in model.opset_import:
        if op.domain not in DOMAINS:
            raise AdapterError(f"operator domain {op.domain[:60]!r} is not allowed (only the default ONNX domain)",
                               field="model.opset_import")
        if op.version not in OPSETS:
            raise AdapterError(f"opset {op.version} is not allowed (opsets {OPSETS.start}-{OPSETS.stop - 1})",
                               field="model.opset_import")
    if model.functions:
        raise AdapterError("model-local functions are not allowed", field="model.functions")
    if len(model.graph.node) > MAX_NODES:
        raise AdapterError(f"{len(model.graph.node)} nodes; at most {MAX_NODES}", field="model.graph.node")
    for node in model.graph.node:
        if node.domain not in DOMAINS:
            raise AdapterError(f"node {node.name[:40]!r} uses the custom operator domain {node.domain[:60]!r}",
                               field="model.graph.node")
        if node.op_type not in ALLOWED_OPS:
            raise AdapterError(f"operator {node.op_type[:40]!r} is not allowed; allowed: "
                               f"{', '.join(sorted(ALLOWED_OPS))}", field="model.graph.node")
        if any(a.HasField("g") or a.graphs for a in node.attribute):
            raise AdapterError("subgraphs are not allowed", field="model.graph.node")
    for t in _tensors(model):
        if t.data_location == onnx.TensorProto.EXTERNAL or t.external_data:
            where = next((e.value for e in t.external_data if e.key == "location"), "")
            raise AdapterError(f"tensor {t.name[:40]!r} refers to external data {where[:80]!r}; the model must be "
                               "self-contained", field="model.external_data")
    _check_interface(model, manifest)
    try:
        onnx.checker.check_model(model)
    except (onnx.checker.ValidationError, ValueError) as e:
        raise AdapterError(f"the ONNX checker refuses it: {str(e).splitlines()[0][:200]}", field="model") from None
    adapter_cost(model)  # before onnxruntime sees it: loading may fold constants, i.e. run part of the graph
    from .runtime import AdapterRuntime

    try:
        runtime = AdapterRuntime(data, manifest)
        expression, joints = runtime.run_raw(np.zeros((2, manifest.num_source), np.float32), limit_s=PROBE_LIMIT_S)
    except AdapterError:
        raise
    except Exception as e:  # noqa: BLE001 - onnxruntime raises its own types for broken models
        raise AdapterError(f"onnxruntime cannot run it: {str(e).splitlines()[0][:200] if str(e) else type(e).__name__}",
                           field="model.run") from None
    if expression.shape != (2, manifest.num_expressions) or (
            manifest.num_joints and (joints is None or joints.shape != (2, manifest.num_joints, 3))):
        raise AdapterError(f"a batch of 2 gave outputs of shapes {list(expression.shape)}"
                           f"{'' if joints is None else ' and ' + str(list(joints.shape))}", field="model.run")
    return model


def _check_interface(model: onnx.ModelProto, manifest: AdapterManifest) -> None:
    g = model.graph
    init = {t.name for t in g.initializer}
    inputs = [vi for vi in g.input if vi.name not in init]
    s, t, j = manifest.num_source, manifest.num_expressions, manifest.num_joints
    if len(inputs) != 1 or inputs[0].name != INPUT:
        raise AdapterError(f"expected one input {INPUT!r}, got {[vi.name[:40] for vi in inputs]}",
                           field="model.graph.input")
    elem, dims = _dims(inputs[0])
    if elem != onnx.TensorProto.FLOAT or len(dims) != 2 or dims[1] != s:
        raise AdapterError(f"{INPUT!r} must be float32 [B, {s}] (the manifest's {s} source names), got "
                           f"{onnx.TensorProto.DataType.Name(elem) if elem else '?'} {dims}", field="model.graph.input")
    want = {OUTPUT_EXPRESSION: [t]} | ({OUTPUT_JOINTS: [j, 3]} if j else {})
    names = [vi.name for vi in g.output]
    if sorted(names) != sorted(want):
        raise AdapterError(f"expected outputs {sorted(want)}, got {[n[:40] for n in names]}",
                           field="model.graph.output")
    for vi in g.output:
        elem, dims = _dims(vi)
        if elem != onnx.TensorProto.FLOAT or len(dims) != 1 + len(want[vi.name]) or dims[1:] != want[vi.name]:
            raise AdapterError(f"{vi.name!r} must be float32 [B, {', '.join(map(str, want[vi.name]))}], got {dims}",
                               field="model.graph.output")
