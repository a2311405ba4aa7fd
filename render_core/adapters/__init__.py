"""Retargeting adapters: any coefficient stream drives any avatar (docs/method.md section 12).

An adapter maps a tracker's coefficients (ARKit-52 blendshapes, FLAME expression and jaw/eye pose, ...) to an
avatar's face-model coefficients and joint rotations. It is an ONNX model plus a manifest:

- :mod:`.manifest`: the manifest (source convention and names, target face model, names, clamp, provenance);
- :mod:`.register`: dense correspondence between face models of different topologies (rigid, non-rigid ICP,
  closest-point projection);
- :mod:`.fit`: the least-squares linear map between two face models, with clamping and jaw/eye rotations;
- :mod:`.onnx_model`: the ONNX graph of a linear adapter (MatMul + Add, clamp; opset pinned);
- :mod:`.validate`: checks of any uploaded ONNX model (size, opsets, operator allow-list, no external data,
  names and shapes that match the manifest, loads in onnxruntime);
- :mod:`.runtime`: one onnxruntime session per adapter (CPU, one intra-op thread), batched, non-finite output
  refused per frame;
- :mod:`.smoothing`: the One Euro filter for noisy tracker input;
- :mod:`.vocabularies`: capture vocabularies (MediaPipe's 52 blendshapes, Live Link Face's columns), their
  mapping onto the open head's ARKit names, and the adapters made from them without a fit.
"""

from .manifest import AdapterError, AdapterManifest

__all__ = ["AdapterError", "AdapterManifest"]
