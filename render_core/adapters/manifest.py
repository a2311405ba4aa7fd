"""The adapter manifest: what an adapter's ONNX model maps from and to (docs/method.md section 12).

An adapter is an ONNX model plus this manifest (JSON, beside the model: ``<id>.onnx`` and ``<id>.json``)::

    format        "blendsplat-adapter"
    version       1
    id            the adapter's id
    source        {"convention": "arkit-52" | "flame" | "mediapipe-52" | "live-link-face" | "custom",
                   "face_model": name or "",
                   "names": [S input names]}   expression names, and "<joint>.x/.y/.z" for a source joint's
                                              axis-angle components (e.g. FLAME's jaw pose: jaw.x, jaw.y, jaw.z)
    target        {"face_model": name, "expression_names": [T], "joint_names": [J],
                   "expression_min": [T], "expression_max": [T]}   the clamp the model applies (may be +-inf)
    opset         the ONNX opset the model was written for
    provenance    {"tool", "method", "source_model", "target_model", "created", "fit": {...}} (free-form)

The model's interface: input ``source`` float32 [B, S]; outputs ``expression`` float32 [B, T] and, when J > 0,
``joints`` float32 [B, J, 3] (axis-angle of each target joint, relative to its parent, as frames take them).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any

from ..errors import BlendsplatError

FORMAT = "blendsplat-adapter"
VERSION = 1
INPUT = "source"
OUTPUT_EXPRESSION = "expression"
OUTPUT_JOINTS = "joints"
CONVENTIONS = ("arkit-52", "flame", "mediapipe-52", "live-link-face", "custom")
AXES = ("x", "y", "z")
MAX_NAMES = 1024
_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.:-]{0,127}$")


class AdapterError(BlendsplatError):
    """An adapter (manifest, ONNX model, fit inputs or its output for one frame) is invalid; ``field`` names the
    part at fault (``manifest.source.names``, ``model.opset``, ``model.graph.node``, ``output``...)."""


def joint_component(name: str) -> tuple[str, int] | None:
    """``"jaw.y"`` -> ("jaw", 1): a source name that is an axis-angle component of a joint; None otherwise."""
    base, dot, axis = name.rpartition(".")
    return (base, AXES.index(axis)) if dot and base and axis in AXES else None


def convention_of(names: list[str]) -> str:
    """The convention a list of source names follows: "arkit-52" (the 52 ARKit blendshape names, any order),
    "flame" (exp_00... and optionally jaw/eye pose components), a capture vocabulary's ("mediapipe-52",
    "live-link-face": exactly its names, any order; :mod:`.vocabularies`), else "custom"."""
    from ..facemodel.open_head import ARKIT_52
    from .vocabularies import convention_of_names

    if set(names) == set(ARKIT_52) and len(names) == len(ARKIT_52):
        return "arkit-52"
    if (vocabulary := convention_of_names(names)) is not None:
        return vocabulary
    if names and all(re.fullmatch(r"exp_\d{2,3}", n) or (joint_component(n) or ("",))[0] in ("jaw", "eye_l", "eye_r",
                                                                                             "neck")
                     for n in names):
        return "flame"
    return "custom"


@dataclass
class AdapterManifest:
    id: str
    source_names: list[str]
    target_face_model: str
    target_expression_names: list[str]
    target_joint_names: list[str] = field(default_factory=list)
    expression_min: list[float] | None = None  # [T]; None: unclamped
    expression_max: list[float] | None = None
    source_convention: str = "custom"
    source_face_model: str = ""
    opset: int = 17
    provenance: dict[str, Any] = field(default_factory=dict)

    @property
    def num_source(self) -> int:
        return len(self.source_names)

    @property
    def num_expressions(self) -> int:
        return len(self.target_expression_names)

    @property
    def num_joints(self) -> int:
        return len(self.target_joint_names)

    def to_dict(self) -> dict[str, Any]:
        def num(v: float) -> float | str:  # JSON has no infinity: "inf" / "-inf"
            return v if math.isfinite(v) else ("inf" if v > 0 else "-inf")

        lo = None if self.expression_min is None else [num(v) for v in self.expression_min]
        hi = None if self.expression_max is None else [num(v) for v in self.expression_max]
        return {
            "format": FORMAT, "version": VERSION, "id": self.id,
            "source": {"convention": self.source_convention, "face_model": self.source_face_model,
                       "names": list(self.source_names)},
            "target": {"face_model": self.target_face_model, "expression_names": list(self.target_expression_names),
                       "joint_names": list(self.target_joint_names),
                       "expression_min": lo, "expression_max": hi},
            "opset": self.opset, "provenance": self.provenance,
        }

    @classmethod
    def from_dict(cls, d: Any) -> AdapterManifest:
        """Parse and validate (AdapterError naming the manifest field)."""
        if not isinstance(d, dict):
            raise AdapterError("expected a JSON object", field="manifest")
        if d.get("format") != FORMAT:
            raise AdapterError(f"format must be {FORMAT!r}", field="manifest.format")
        if d.get("version") != VERSION:
            raise AdapterError(f"version {d.get('version')!r}; this build reads version {VERSION}",
                               field="manifest.version")
        source, target = d.get("source"), d.get("target")
        if not isinstance(source, dict):
            raise AdapterError("expected an object", field="manifest.source")
        if not isinstance(target, dict):
            raise AdapterError("expected an object", field="manifest.target")
        opset = d.get("opset", 17)
        if not isinstance(opset, int) or isinstance(opset, bool):
            raise AdapterError("expected an integer", field="manifest.opset")
        provenance = d.get("provenance", {})
        if not isinstance(provenance, dict):
            raise AdapterError("expected an object", field="manifest.provenance")
        m = cls(
            id=_text(d.get("id"), "manifest.id"),
            source_names=_names(source.get("names"), "manifest.source.names"),
            source_convention=_text(source.get("convention", "custom"), "manifest.source.convention"),
            source_face_model=_text(source.get("face_model", ""), "manifest.source.face_model", empty=True),
            target_face_model=_text(target.get("face_model"), "manifest.target.face_model"),
            target_expression_names=_names(target.get("expression_names"), "manifest.target.expression_names"),
            target_joint_names=_names(target.get("joint_names", []), "manifest.target.joint_names", empty=True),
            expression_min=_bounds(target.get("expression_min"), "manifest.target.expression_min"),
            expression_max=_bounds(target.get("expression_max"), "manifest.target.expression_max"),
            opset=opset, provenance=provenance,
        )
        m.validate()
        return m

    def validate(self) -> None:
        if self.source_convention not in CONVENTIONS:
            raise AdapterError(f"{self.source_convention!r}; conventions: {', '.join(CONVENTIONS)}",
                               field="manifest.source.convention")
        t = self.num_expressions
        for name, b in (("expression_min", self.expression_min), ("expression_max", self.expression_max)):
            if b is not None and len(b) != t:
                raise AdapterError(f"expected {t} values (one per target expression), got {len(b)}",
                                   field=f"manifest.target.{name}")
        if self.expression_min is not None and self.expression_max is not None and any(
                lo > hi for lo, hi in zip(self.expression_min, self.expression_max, strict=True)):
            raise AdapterError("a minimum is above its maximum", field="manifest.target.expression_min")


def _text(v: Any, field: str, empty: bool = False) -> str:
    if not isinstance(v, str) or (not v and not empty) or len(v) > 256:
        raise AdapterError("expected a non-empty string of at most 256 characters", field=field)
    return v


def _names(v: Any, field: str, empty: bool = False) -> list[str]:
    if not isinstance(v, list) or (not v and not empty) or len(v) > MAX_NAMES:
        raise AdapterError(f"expected a list of 1 to {MAX_NAMES} names", field=field)
    for n in v:
        if not isinstance(n, str) or not _NAME.match(n):
            raise AdapterError(f"{str(n)[:40]!r} is not a name (letters, digits, '_', '.', ':', '-')", field=field)
    if len(set(v)) != len(v):
        raise AdapterError("names repeat", field=field)
    return list(v)


def _bounds(v: Any, field: str) -> list[float] | None:
    if v is None:
        return None
    if not isinstance(v, list) or len(v) > MAX_NAMES:
        raise AdapterError("expected a list of numbers", field=field)
    out = []
    for x in v:
        if x in ("inf", "-inf"):
            out.append(float(x))
        elif isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x):
            out.append(float(x))
        else:
            raise AdapterError("expected numbers (or \"inf\" / \"-inf\")", field=field)
    return out
