"""Running adapters: one onnxruntime session per adapter (CPU provider, one intra-op thread, no spinning), a batch
of frames [B, S] per call. A frame whose outputs are not all finite is refused on its own (an
:class:`AdapterError` naming ``adapter``), so NaN or infinity never reaches the renderer.

Limits of a session (the model's cost is bounded statically before it is stored: :mod:`.cost`): it computes on the
calling thread only (one intra-op thread, sequential), with no memory arena and no memory pattern, so what one run
allocates is given back when it ends instead of staying reserved for the session's life; a run may be given a
time limit (``limit_s``: onnxruntime's terminate flag, checked between nodes), as validation's probe run is."""

from __future__ import annotations

import threading

import numpy as np
import onnxruntime as ort

from .manifest import INPUT, OUTPUT_EXPRESSION, OUTPUT_JOINTS, AdapterError, AdapterManifest


def session_options() -> ort.SessionOptions:
    o = ort.SessionOptions()
    o.intra_op_num_threads = 1
    o.inter_op_num_threads = 1
    o.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    o.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    o.add_session_config_entry("session.intra_op.allow_spinning", "0")  # the renderer needs the cores
    o.enable_cpu_mem_arena = False  # a run's buffers are freed when it ends, not kept as the arena's high mark
    o.enable_mem_pattern = False  # no buffers planned ahead from the first run's shapes
    o.log_severity_level = 3
    return o


class AdapterRuntime:
    """One adapter, loaded (the model's bytes and its manifest; validate uploads first with
    :func:`render_core.adapters.validate.validate_model`)."""

    def __init__(self, model: bytes, manifest: AdapterManifest):
        self.manifest = manifest
        self.session = ort.InferenceSession(model, sess_options=session_options(), providers=["CPUExecutionProvider"])
        self._outputs = [OUTPUT_EXPRESSION] + ([OUTPUT_JOINTS] if manifest.num_joints else [])
        self._lock = threading.Lock()  # a session runs one call at a time here (one thread each)

    def run_raw(self, source: np.ndarray, limit_s: float | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """source [B, S] float32 -> (expression [B, T], joints [B, J, 3] or None), unchecked. With ``limit_s``, a
        run still going after that many seconds is stopped (onnxruntime raises) at its next node."""
        feed = {INPUT: np.ascontiguousarray(source, dtype=np.float32)}
        with self._lock:
            if limit_s is None:
                out = self.session.run(self._outputs, feed)
            else:
                options = ort.RunOptions()
                timer = threading.Timer(limit_s, setattr, (options, "terminate", True))
                timer.daemon = True
                timer.start()
                try:
                    out = self.session.run(self._outputs, feed, options)
                finally:
                    timer.cancel()
        return out[0], (out[1] if len(out) > 1 else None)

    def run(self, source: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[AdapterError | None]]:
        """source [B, S] -> (expression [B, T], joints [B, J, 3], per frame None or the error refusing it)."""
        m = self.manifest
        source = np.asarray(source, np.float32)
        if source.ndim != 2 or source.shape[1] != m.num_source:
            raise AdapterError(f"expected [B, {m.num_source}] source coefficients, got {list(source.shape)}",
                               field="source")
        expression, joints = self.run_raw(source)
        b = len(source)
        if joints is None:
            joints = np.zeros((b, 0, 3), np.float32)
        if expression.shape != (b, m.num_expressions) or joints.shape != (b, m.num_joints, 3):
            raise AdapterError(f"the model gave shapes {list(expression.shape)} and {list(joints.shape)}",
                               field="adapter")
        finite = np.isfinite(expression).all(1) & np.isfinite(joints).reshape(b, -1).all(1)
        errors: list[AdapterError | None] = [
            None if ok else AdapterError(f"adapter {m.id!r} gave a non-finite output (NaN or infinity) for this "
                                         "frame; it was not rendered", field="adapter") for ok in finite]
        return expression, joints, errors
