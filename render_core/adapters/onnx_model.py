"""The ONNX model of a linear adapter (docs/method.md section 12), built with the ``onnx`` package.

Graph (opset :data:`OPSET`, IR version :data:`IR_VERSION`)::

    source [B, S] float32
      -> MatMul W_e [S, T] -> Add b_e [T] -> Max lo [T] -> Min hi [T]  -> expression [B, T]
      -> MatMul W_j [S, 3J] -> Add b_j [3J] -> Reshape [-1, J, 3]      -> joints [B, J, 3]     (only when J > 0)

The clamp nodes are left out when the manifest has no range (an unclamped fit).
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from .manifest import INPUT, OUTPUT_EXPRESSION, OUTPUT_JOINTS, AdapterManifest

OPSET = 17
IR_VERSION = 8  # what onnxruntime 1.14 and later read
_BIG = float(np.finfo(np.float32).max)


def build_model(manifest: AdapterManifest, weights: np.ndarray, bias: np.ndarray | None = None) -> onnx.ModelProto:
    """The ONNX model of ``expression = clamp(W_e s + b_e)``, ``joints = W_j s + b_j`` for ``weights`` [T + 3J, S]
    (rows: the manifest's target expressions, then each target joint's x, y, z)."""
    s, t, j = manifest.num_source, manifest.num_expressions, manifest.num_joints
    w = np.asarray(weights, np.float64)
    if w.shape != (t + 3 * j, s):
        raise ValueError(f"weights must be [{t + 3 * j}, {s}], got {list(w.shape)}")
    b = np.zeros(t + 3 * j) if bias is None else np.asarray(bias, np.float64)

    def const(name: str, value: np.ndarray) -> TensorProto:
        return numpy_helper.from_array(np.ascontiguousarray(value, dtype=np.float32), name)

    inits = [const("W_e", w[:t].T), const("b_e", b[:t])]
    nodes = [helper.make_node("MatMul", [INPUT, "W_e"], ["e_lin"]), helper.make_node("Add", ["e_lin", "b_e"], ["e0"])]
    last = "e0"
    if manifest.expression_min is not None:
        inits.append(const("lo", np.clip(manifest.expression_min, -_BIG, _BIG)))
        nodes.append(helper.make_node("Max", [last, "lo"], ["e1"]))
        last = "e1"
    if manifest.expression_max is not None:
        inits.append(const("hi", np.clip(manifest.expression_max, -_BIG, _BIG)))
        nodes.append(helper.make_node("Min", [last, "hi"], ["e2"]))
        last = "e2"
    nodes.append(helper.make_node("Identity", [last], [OUTPUT_EXPRESSION]))
    outputs = [helper.make_tensor_value_info(OUTPUT_EXPRESSION, TensorProto.FLOAT, ["batch", t])]
    if j:
        inits += [const("W_j", w[t:].T), const("b_j", b[t:]),
                  numpy_helper.from_array(np.array([-1, j, 3], np.int64), "joint_shape")]
        nodes += [helper.make_node("MatMul", [INPUT, "W_j"], ["j_lin"]), helper.make_node("Add", ["j_lin", "b_j"],
                                                                                           ["j0"]),
                  helper.make_node("Reshape", ["j0", "joint_shape"], [OUTPUT_JOINTS])]
        outputs.append(helper.make_tensor_value_info(OUTPUT_JOINTS, TensorProto.FLOAT, ["batch", j, 3]))
    graph = helper.make_graph(nodes, f"adapter_{manifest.id}",
                              [helper.make_tensor_value_info(INPUT, TensorProto.FLOAT, ["batch", s])], outputs, inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="blendsplat",
                              ir_version=IR_VERSION)
    model.doc_string = f"blendsplat adapter {manifest.id}: {manifest.source_convention} -> {manifest.target_face_model}"
    onnx.checker.check_model(model)
    return model


def model_bytes(manifest: AdapterManifest, weights: np.ndarray, bias: np.ndarray | None = None) -> bytes:
    """The serialised model of :func:`build_model` (what is stored as ``<id>.onnx``)."""
    manifest.opset = OPSET
    return build_model(manifest, weights, bias).SerializeToString()
