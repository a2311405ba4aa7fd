"""Capture vocabularies: the coefficient names common trackers send, and adapters made from them with nothing but
the install (``blendsplat adapter make``; docs/method.md section 12).

A vocabulary is a tracker's names in the order it sends them, and what each name is on the open head (the face
model the package ships, ARKit's 52 expression names), or None for a name that has no expression there:

- ``mediapipe``: MediaPipe FaceLandmarker's 52 face blendshape categories, in its output order (index 0 to 51).
  They are ARKit's names except that ``_neutral`` (index 0, the score of a neutral face) stands where ARKit has
  ``tongueOut``; ``_neutral`` maps to nothing, and nothing drives ``tongueOut``.
- ``live-link-face``: Live Link Face's columns (its CSV after ``Timecode`` and ``BlendShapeCount``, and its Live
  Link curves): ARKit's 52 blendshapes with a capital first letter (``EyeBlinkLeft``) in ARKit's enumeration
  order (Unreal's EARFaceBlendShape), then the head and eye rotations (``HeadYaw`` ... ``RightEyeRoll``). The
  rotations map to nothing: send the head's pose as the frame's joints.

:func:`make_adapter` turns a vocabulary into an adapter for a target face model: when the target's expression
names are ARKit's (the open head), each name drives its own expression with weight 1 (a known mapping, no fit);
otherwise that mapping is composed with the least-squares fit from the open head to the target
(:func:`render_core.adapters.fit.fit`), e.g. onto FLAME.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..facemodel.model import FaceModel
from ..facemodel.open_head import ARKIT_52
from ..facemodel.open_head import NAME as OPEN_HEAD
from .fit import ARKIT_RANGE, Fit
from .manifest import AdapterError, AdapterManifest

# MediaPipe FaceLandmarker's face blendshape categories (output index = position): ARKit's names in alphabetical
# order, with "_neutral" first and no "tongueOut".
MEDIAPIPE_52 = ["_neutral"] + [n for n in ARKIT_52 if n != "tongueOut"]

# Live Link Face: ARKit's blendshapes in ARKit's enumeration order, capitalised, then the head and eye rotations.
LIVE_LINK_FACE_BLENDSHAPES = [
    "EyeBlinkLeft", "EyeLookDownLeft", "EyeLookInLeft", "EyeLookOutLeft", "EyeLookUpLeft", "EyeSquintLeft",
    "EyeWideLeft", "EyeBlinkRight", "EyeLookDownRight", "EyeLookInRight", "EyeLookOutRight", "EyeLookUpRight",
    "EyeSquintRight", "EyeWideRight", "JawForward", "JawLeft", "JawRight", "JawOpen", "MouthClose", "MouthFunnel",
    "MouthPucker", "MouthLeft", "MouthRight", "MouthSmileLeft", "MouthSmileRight", "MouthFrownLeft",
    "MouthFrownRight", "MouthDimpleLeft", "MouthDimpleRight", "MouthStretchLeft", "MouthStretchRight",
    "MouthRollLower", "MouthRollUpper", "MouthShrugLower", "MouthShrugUpper", "MouthPressLeft", "MouthPressRight",
    "MouthLowerDownLeft", "MouthLowerDownRight", "MouthUpperUpLeft", "MouthUpperUpRight", "BrowDownLeft",
    "BrowDownRight", "BrowInnerUp", "BrowOuterUpLeft", "BrowOuterUpRight", "CheekPuff", "CheekSquintLeft",
    "CheekSquintRight", "NoseSneerLeft", "NoseSneerRight", "TongueOut",
]
LIVE_LINK_FACE_ROTATIONS = ["HeadYaw", "HeadPitch", "HeadRoll", "LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll",
                            "RightEyeYaw", "RightEyePitch", "RightEyeRoll"]
LIVE_LINK_FACE = LIVE_LINK_FACE_BLENDSHAPES + LIVE_LINK_FACE_ROTATIONS


@dataclass(frozen=True)
class Vocabulary:
    """A tracker's coefficient names in its order, and the open head's (ARKit) name of each, or None."""

    name: str
    convention: str  # the manifest's source convention
    description: str
    names: tuple[str, ...]
    maps_to: tuple[str | None, ...]  # per name: an ARKit-52 name, or None (no expression; the value is ignored)

    def mapping(self) -> dict[str, str | None]:
        return dict(zip(self.names, self.maps_to, strict=True))

    def to_dict(self) -> dict:
        return {"name": self.name, "convention": self.convention, "description": self.description,
                "names": list(self.names), "maps_to": self.mapping(),
                "unmapped": [n for n, t in zip(self.names, self.maps_to, strict=True) if t is None],
                "open_head_names_not_driven": [n for n in ARKIT_52 if n not in self.maps_to]}


def _vocabulary(name: str, convention: str, description: str, names: list[str],
                maps_to: list[str | None]) -> Vocabulary:
    targets = [t for t in maps_to if t is not None]
    if not len(names) == len(maps_to) == len(set(names)) or len(set(targets)) != len(targets) or not set(
            targets) <= set(ARKIT_52):
        raise ValueError(f"vocabulary {name}: names must be unique and map to distinct ARKit names")
    return Vocabulary(name, convention, description, tuple(names), tuple(maps_to))


VOCABULARIES: dict[str, Vocabulary] = {
    "mediapipe": _vocabulary(
        "mediapipe", "mediapipe-52",
        "MediaPipe FaceLandmarker's 52 face blendshapes in output order; _neutral maps to nothing, tongueOut is not "
        "driven", MEDIAPIPE_52, [None if n == "_neutral" else n for n in MEDIAPIPE_52]),
    "live-link-face": _vocabulary(
        "live-link-face", "live-link-face",
        "Live Link Face's 52 ARKit blendshapes (capitalised, ARKit's order) then its 9 head and eye rotations, "
        "which map to nothing (send head pose as joints)",
        LIVE_LINK_FACE, [n[0].lower() + n[1:] for n in LIVE_LINK_FACE_BLENDSHAPES]
        + [None] * len(LIVE_LINK_FACE_ROTATIONS)),
}


def vocabulary(name: str) -> Vocabulary:
    """A vocabulary by name (AdapterError naming ``source`` for an unknown one)."""
    try:
        return VOCABULARIES[name]
    except KeyError:
        raise AdapterError(f"no vocabulary {str(name)[:40]!r}; vocabularies: {', '.join(VOCABULARIES)}",
                           field="source") from None


def convention_of_names(names: list[str]) -> str | None:
    """The convention of a vocabulary whose names are exactly ``names`` (any order), else None."""
    for v in VOCABULARIES.values():
        if len(names) == len(v.names) and set(names) == set(v.names):
            return v.convention
    return None


def arkit_matrix(vocab: Vocabulary) -> np.ndarray:
    """[52, S]: ARKit-52 coefficients (the open head's order) from the vocabulary's source vector."""
    p = np.zeros((len(ARKIT_52), len(vocab.names)))
    for i, target in enumerate(vocab.maps_to):
        if target is not None:
            p[ARKIT_52.index(target), i] = 1.0
    return p


def make_adapter(vocab: Vocabulary | str, target: FaceModel | None = None, adapter_id: str | None = None) -> Fit:
    """The adapter from ``vocab``'s names (in its order) to ``target``'s coefficients (default: the open head).

    A target whose expression names are all ARKit names gets the known mapping (weight 1 from each source name to
    its expression, clamped to [0, 1]); any other target gets that mapping composed with the least-squares fit
    from the open head to it (clamped and with jaw/eye rotations as :func:`~render_core.adapters.fit.fit` does).
    The returned :class:`~render_core.adapters.fit.Fit` writes its ONNX model with
    :func:`~render_core.adapters.onnx_model.model_bytes`."""
    from ..facemodel.open_head import open_head

    vocab = vocabulary(vocab) if isinstance(vocab, str) else vocab
    start = time.perf_counter()
    head = None
    if target is None:
        target = head = open_head()
    adapter_id = adapter_id or f"{vocab.name}-to-{'open-head' if target.name == OPEN_HEAD else target.name}"
    p = arkit_matrix(vocab)
    names = list(target.expression_names)
    if set(names) <= set(ARKIT_52):
        weights = p[[ARKIT_52.index(n) for n in names]]
        lo, hi = ARKIT_RANGE
        manifest = AdapterManifest(
            id=adapter_id, source_names=list(vocab.names), source_convention=vocab.convention,
            target_face_model=target.name, target_expression_names=names,
            expression_min=[lo] * len(names), expression_max=[hi] * len(names))
        method = f"known mapping ({vocab.name} names -> ARKit names)"
        stats: dict = {"method": "known mapping"}
    else:
        from .fit import fit

        via = fit(head or open_head(), target, adapter_id=adapter_id)
        weights = via.weights @ p  # [T + 3J, 52] @ [52, S]
        manifest = via.manifest
        manifest.source_names, manifest.source_convention = list(vocab.names), vocab.convention
        method = f"known mapping ({vocab.name} names -> ARKit names), then {via.manifest.provenance['method']}"
        stats = {"method": "known mapping + fit", "fit": via.stats}
    missing = [n for n in names if n in ARKIT_52 and n not in vocab.maps_to]
    stats.update({"not_driven": missing, "unmapped": [n for n, t in zip(vocab.names, vocab.maps_to, strict=True)
                                                      if t is None],
                  "seconds": round(time.perf_counter() - start, 3)})
    manifest.source_face_model = ""
    manifest.provenance = {"tool": "blendsplat adapter make", "method": method, "source_model": vocab.name,
                           "target_model": target.name,
                           "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "fit": stats}
    manifest.validate()
    return Fit(manifest=manifest, weights=weights, bias=np.zeros(len(weights)), stats=stats)
