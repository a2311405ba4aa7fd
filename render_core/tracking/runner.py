"""The model runner: the shipped TFLite models (``models/``, see :mod:`.fetch_models`) run with LiteRT on the CPU.

:func:`load_model` checks a model file's sha256 against ``models/manifest.json`` before loading it (a missing or
altered file is a :class:`~render_core.errors.TrackingError` on ``model``), and keeps one interpreter per model and
thread (an interpreter is not thread-safe), each on ``threads`` CPU threads (default 1: the models take a few ms).
"""

from __future__ import annotations

import hashlib
import json
import threading
from functools import cache
from pathlib import Path

import numpy as np

from ..errors import TrackingError

MODELS_DIR = Path(__file__).resolve().with_name("models")
NAMES = ("face_detection_short_range", "face_detection_full_range_sparse", "face_landmark", "iris_landmark",
         "selfie_segmentation")


@cache
def _manifest() -> dict:
    try:
        return json.loads((MODELS_DIR / "manifest.json").read_text())["files"]
    except (OSError, ValueError, KeyError) as e:
        raise TrackingError(f"cannot read the tracking models' manifest: {e}", field="model") from None


@cache
def model_path(name: str) -> Path:
    """The verified path of model ``name`` (one of NAMES)."""
    if name not in NAMES:
        raise TrackingError(f"unknown model {name!r}; one of {', '.join(NAMES)}", field="model")
    file = f"{name}.tflite"
    entry = _manifest().get(file)
    path = MODELS_DIR / file
    if entry is None or not path.is_file():
        raise TrackingError(f"{file} is missing from {MODELS_DIR} (python -m render_core.tracking.fetch_models)",
                            field="model")
    if hashlib.sha256(path.read_bytes()).hexdigest() != entry["sha256"]:
        raise TrackingError(f"{file} does not match its sha256 in manifest.json", field="model")
    return path


class Model:
    """One TFLite model: ``model(x)`` runs it on one float32 input of ``input_shape`` and returns its outputs
    (float32 arrays, in the model's output order, batch dimension kept)."""

    def __init__(self, name: str, threads: int = 1):
        from ai_edge_litert.interpreter import Interpreter

        self.name = name
        self._interpreter = Interpreter(model_path=str(model_path(name)), num_threads=threads)
        self._interpreter.allocate_tensors()
        inputs = self._interpreter.get_input_details()
        self._input = inputs[0]["index"]
        self.input_shape = tuple(int(d) for d in inputs[0]["shape"])
        self._outputs = [d["index"] for d in self._interpreter.get_output_details()]
        self.output_shapes = [tuple(int(d) for d in o["shape"]) for o in self._interpreter.get_output_details()]

    def __call__(self, x: np.ndarray) -> list[np.ndarray]:
        x = np.ascontiguousarray(x, dtype=np.float32).reshape(self.input_shape)
        self._interpreter.set_tensor(self._input, x)
        self._interpreter.invoke()
        return [self._interpreter.get_tensor(i).copy() for i in self._outputs]


_local = threading.local()


def load_model(name: str, threads: int = 1) -> Model:
    """Model ``name`` for this thread (created on first use, then kept)."""
    models = _local.__dict__.setdefault("models", {})
    key = (name, threads)
    if key not in models:
        models[key] = Model(name, threads)
    return models[key]


