"""The static cost of an adapter model, bounded before anything runs (docs/method.md section 12).

An uploaded model of allowed operators can still be arbitrarily expensive: each ``Concat(x, x)`` doubles a tensor,
so twenty of them after a small MatMul ask for gigabytes per frame from a model of a few kilobytes. The operator
allow-list and node count bound the graph's size, not its work; :func:`check_cost` bounds the work.

How: the input ``source`` [B, S] gets the batch B = :data:`ADAPTER_BATCH` (the largest batch the engine runs in
one adapter call: ``max_batch`` is at most 64), every value-info the model declares is dropped (an uploader's
shapes are not trusted; the outputs' too), and ONNX shape inference (strict) gives every tensor's shape from the
input and the model's constants. Every node output must come out fully static, of a numeric type; a tensor whose
size cannot be bounded (a shape computed from data, an unknown dimension) is refused by name. ONNX's data
propagation (``data_prop``) is not used: it computes the values of integer tensors while inferring (a chain of
``Concat`` on an int64 constant builds them in memory: a bomb of its own), so shape inputs (Reshape's shape,
Slice's starts...) must be constants (initializers or Constant nodes), as exporters write them after constant
folding.

Then, for the batch B: each node output's elements (at most :data:`MAX_ADAPTER_TENSOR_ELEMENTS`, and no
dimension larger), the bytes of all node outputs together (at most :data:`MAX_ADAPTER_INTERMEDIATE_BYTES`; no
reuse of buffers assumed, so an upper bound of the run's memory) and the work, at most :data:`MAX_ADAPTER_WORK`:
multiply-adds for MatMul and Gemm (output elements x the inner dimension), elements written for every other node
(elementwise, Concat, Slice, Reshape, Cast...; Constant nodes are the model's own bytes: none). A model over a
bound is refused with an :class:`AdapterError` on ``model`` whose message says "cost", the tensor or node, and the
figure against the limit.

The bounds are generous for honest adapters: the fitted linear ones (MatMul + Add + clamp) cost about 64 x S x T
multiply-adds (170 k for ARKit-52 to 52 expressions), a two-layer MLP of 256 units about 6 M, three layers of 1024
about 75 M (1.5 ms for the batch of 64 on one core); the limit of 2^28 is a few to a few tens of ms on one core.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import onnx
from onnx import TensorProto

from .manifest import INPUT, AdapterError

ADAPTER_BATCH = 64  # frames of one adapter run at most (the engine's max_batch is at most 64)
MAX_ADAPTER_TENSOR_ELEMENTS = 1 << 22  # one tensor, for the batch: 16 MiB of float32 (65 536 per frame)
MAX_ADAPTER_INTERMEDIATE_BYTES = 1 << 26  # all node outputs together, for the batch (64 MiB)
MAX_ADAPTER_WORK = 1 << 28  # multiply-adds and elements written, for the batch (about 4 M per frame)
_MATMUL = frozenset({"MatMul", "Gemm"})
_NOT_NUMERIC = frozenset({TensorProto.UNDEFINED, TensorProto.STRING})


@dataclass(frozen=True)
class AdapterCost:
    """What one run of ``batch`` frames costs: the largest tensor (name, elements), the bytes of all node outputs
    together and the work (multiply-adds and elements written)."""

    batch: int
    largest: tuple[str, int]
    intermediate_bytes: int
    work: int


def _refuse(message: str) -> AdapterError:
    return AdapterError(f"the adapter's cost cannot be bounded: {message}", field="model")


def _over(message: str) -> AdapterError:
    return AdapterError(f"the adapter's cost is over its bound: {message}", field="model")


def _name(node: onnx.NodeProto) -> str:
    return f"{node.op_type} node {node.name[:40]!r}" if node.name else f"a {node.op_type} node"


def static_shapes(model: onnx.ModelProto, batch: int = ADAPTER_BATCH) -> dict[str, tuple[int, list[int | None]]]:
    """{tensor name: (element type, dims)} by strict ONNX shape inference of ``model`` with ``source`` [batch, S]
    and no declared value-info (the model itself is not changed). A dim None is unknown."""
    m = onnx.ModelProto()
    m.CopyFrom(model)
    g = m.graph
    del g.value_info[:]
    for vi in g.output:
        vi.type.tensor_type.ClearField("shape")
    for vi in g.input:
        if vi.name == INPUT and vi.type.tensor_type.shape.dim:
            dim = vi.type.tensor_type.shape.dim[0]
            dim.Clear()
            dim.dim_value = batch
    try:
        g = onnx.shape_inference.infer_shapes(m, check_type=True, strict_mode=True).graph
    except (onnx.shape_inference.InferenceError, onnx.checker.ValidationError, ValueError, RuntimeError) as e:
        raise _refuse(f"ONNX shape inference fails for a batch of {batch}: "
                      f"{str(e).splitlines()[0][:200] if str(e) else type(e).__name__}") from None
    shapes: dict[str, tuple[int, list[int | None]]] = {}
    for vi in (*g.input, *g.value_info, *g.output):
        t = vi.type.tensor_type
        if vi.type.HasField("tensor_type") and t.HasField("shape"):
            shapes[vi.name] = (t.elem_type, [d.dim_value if d.HasField("dim_value") and d.dim_value >= 0 else None
                                             for d in t.shape.dim])
    for init in g.initializer:
        shapes[init.name] = (init.data_type, list(init.dims))
    return shapes


def _node_work(node: onnx.NodeProto, shapes: dict[str, tuple[int, list[int | None]]], written: int) -> int:
    """Multiply-adds of a MatMul or Gemm (output elements x inner dimension); elements written otherwise."""
    if node.op_type not in _MATMUL:
        return 0 if node.op_type == "Constant" else written
    a = shapes.get(node.input[0], (0, []))[1] if node.input else []
    if node.op_type == "Gemm":
        trans_a = next((attr.i for attr in node.attribute if attr.name == "transA"), 0)
        inner = a[0 if trans_a else 1] if len(a) == 2 else None
    else:
        inner = a[-1] if a else None
    if inner is None:
        raise _refuse(f"the inner dimension of {_name(node)} is not known")
    return written * max(int(inner), 1)


def adapter_cost(model: onnx.ModelProto, batch: int = ADAPTER_BATCH,
                 max_tensor_elements: int = MAX_ADAPTER_TENSOR_ELEMENTS,
                 max_intermediate_bytes: int = MAX_ADAPTER_INTERMEDIATE_BYTES,
                 max_work: int = MAX_ADAPTER_WORK) -> AdapterCost:
    """The cost of one run of ``batch`` frames of ``model`` (the module docstring), without running it; an
    :class:`AdapterError` on ``model`` naming the tensor or node when it cannot be bounded or passes a limit."""
    shapes = static_shapes(model, batch)
    largest, total_bytes, work = ("", 0), 0, 0
    heaviest = ("", 0)  # the node of most work
    for node in model.graph.node:
        written, where = 0, _name(node)
        for out in node.output:
            if not out:
                continue  # an optional output left out
            elem, dims = shapes.get(out, (TensorProto.UNDEFINED, None))
            where = f"tensor {out[:40]!r} ({_name(node)})"
            if dims is None or any(d is None for d in dims):
                shown = "unknown" if dims is None else "[" + ", ".join("?" if d is None else str(d) for d in dims) + "]"
                raise _refuse(f"the shape of {where} is {shown} for a batch of {batch}; every shape must follow "
                              "from the input's and the model's constants (not from data)")
            if elem in _NOT_NUMERIC:
                raise _refuse(f"{where} is not of a numeric type")
            n = math.prod(dims)
            if n > max_tensor_elements or max(dims, default=0) > max_tensor_elements:
                raise _over(f"{where} has shape {dims}: {n:,} elements for a batch of {batch}, the limit is "
                            f"{max_tensor_elements:,} (MAX_ADAPTER_TENSOR_ELEMENTS)")
            if node.op_type != "Constant":
                total_bytes += n * onnx.helper.tensor_dtype_to_np_dtype(elem).itemsize
                written += n
            if n > largest[1]:
                largest = (out, n)
        w = _node_work(node, shapes, written)
        work += w
        if w > heaviest[1]:
            heaviest = (node.output[0] if node.output else node.op_type, w)
        if total_bytes > max_intermediate_bytes:
            raise _over(f"the tensors up to {where} hold {total_bytes:,} bytes for a batch of {batch}, the limit is "
                        f"{max_intermediate_bytes:,} (MAX_ADAPTER_INTERMEDIATE_BYTES)")
        if work > max_work:
            raise _over(f"the work up to {_name(node)} (output {node.output[0][:40]!r}) is {work:,} multiply-adds "
                        f"and elements written for a batch of {batch}, the limit is {max_work:,} (MAX_ADAPTER_WORK); "
                        f"the heaviest node writes {heaviest[0][:40]!r} ({heaviest[1]:,})")
    return AdapterCost(batch, largest, total_bytes, work)
