"""The Gaussian blendshape avatar (docs/method.md sections 1 and 11).

An :class:`Avatar` holds the neutral Gaussians B0, K expression deltas dB_k for all five properties, per-Gaussian
LBS weights over a named joint tree, optional pose correctives and eyelid offsets, and the mouth-interior Gaussians
(upper group bound to the skull's joint, lower group to the jaw). Tensors may be stored in fp16, and the deltas in
int8 with float32 scales (:mod:`render_core.packed`); every compute path casts to float32.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Literal

import torch
from torch import Tensor

from .errors import OptionError, ShapeError
from .gaussians import Gaussians  # defined below packed (which unpacks into it); public here as before
from .packed import SparseDeltas

RasterMode = Literal["classic", "antialiased"]
RASTER_MODES: tuple[str, ...] = ("classic", "antialiased")
# Storage of the blendshape deltas (Avatar.precision, Avatar.with_precision): the dtype of the stored values.
PRECISIONS: dict[str, torch.dtype] = {"fp32": torch.float32, "fp16": torch.float16, "int8": torch.int8}


def check_raster_mode(mode: str) -> None:
    """ValueError unless ``mode`` is one of :data:`RASTER_MODES` (what every rasterizer backend takes)."""
    if mode not in RASTER_MODES:
        raise OptionError(f"must be one of {RASTER_MODES}, got {mode!r}", field="raster_mode")

# FLAME's joints (docs/method.md section 11) and the open head's.
FLAME_JOINTS: tuple[str, ...] = ("root", "neck", "jaw", "eye_l", "eye_r")
FLAME_PARENTS: tuple[int, ...] = (-1, 0, 1, 1, 1)
FLAME_MOUTH_JOINTS: tuple[str, str] = ("neck", "jaw")


def sh_coeff_count(degree: int) -> int:
    """Number of SH coefficients per channel for an SH degree (0..3)."""
    if degree not in (0, 1, 2, 3):
        raise OptionError(f"SH degree must be 0..3, got {degree}", field="sh_degree")
    return (degree + 1) ** 2


@dataclass
class Avatar:
    """A Gaussian blendshape head avatar, ready to deform and render.

    Shapes (N face Gaussians, K blendshapes, J joints, M mouth Gaussians, C = (sh_degree+1)^2):
      neutral           Gaussians with [N, ...] tensors (B0)
      deltas            Gaussians with [K, N, ...] tensors (dB_k = B_k - B0, all five properties), or the same
                        stored sparsely (:class:`~render_core.packed.SparseDeltas`, as schema-2 bundles load)
      lbs_weights       [N, J]      rows sum to 1
      joint_positions   [J, 3]      rest positions of the joints, world space (metres)
      pose_correctives  [9 (J-1), N, 3] or None  (FLAME posedirs layout: (R_j - I) of the non-root joints)
      eyelid_offsets    [2, N, 3] or None        (left, right)
      mouth             Gaussians with [M, ...] tensors (no blendshapes)
      mouth_group       [M] int64   0 = upper (follows mouth_joint_names[0]), 1 = lower (mouth_joint_names[1])
    """

    neutral: Gaussians
    deltas: Gaussians | SparseDeltas
    lbs_weights: Tensor
    joint_positions: Tensor
    joint_names: list[str]
    joint_parents: list[int]
    expression_names: list[str]
    mouth: Gaussians
    mouth_group: Tensor
    mouth_joint_names: tuple[str, str] = FLAME_MOUTH_JOINTS
    pose_correctives: Tensor | None = None
    eyelid_offsets: Tensor | None = None
    sh_degree: int = 3
    face_model: str = "synthetic"
    raster_mode: RasterMode = "classic"
    default_camera: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)

    @property
    def num_gaussians(self) -> int:
        return self.neutral.count

    @property
    def num_expressions(self) -> int:
        return len(self.expression_names)

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    @property
    def num_mouth(self) -> int:
        return self.mouth.count

    @property
    def precision(self) -> str:
        """Storage of the blendshape deltas: "fp32", "fp16" or "int8" (:data:`PRECISIONS`; with int8 deltas the
        pose correctives and eyelid offsets are fp16)."""
        dtype = self.deltas.dtype if isinstance(self.deltas, SparseDeltas) else self.deltas.means.dtype
        return {torch.float16: "fp16", torch.int8: "int8"}.get(dtype, "fp32")

    def dense_deltas(self) -> Gaussians:
        """The deltas as dense [K, N, ...] Gaussians (built from sparse deltas: K N (11 + 3C) values)."""
        return self.deltas.to_dense() if isinstance(self.deltas, SparseDeltas) else self.deltas

    def sparse_deltas(self, dtype: torch.dtype | None = None) -> SparseDeltas:
        """The deltas as stored (Gaussian, blendshape) pairs in ``dtype`` (default theirs): no copy when they
        already are."""
        if isinstance(self.deltas, SparseDeltas):
            return self.deltas if dtype in (None, self.deltas.dtype) else self.deltas.to(dtype=dtype)
        return SparseDeltas.from_dense(self.deltas, dtype)

    def _map_deltas(self, dtype: torch.dtype | None, device: torch.device | str | None = None):
        """The deltas moved to ``device`` and stored as ``dtype`` (int8: sparse and quantised; int8 deltas cast to
        a float dtype are dequantised)."""
        if isinstance(self.deltas, SparseDeltas):
            return self.deltas.to(device, dtype)
        if dtype == torch.int8:
            return SparseDeltas.from_dense(self.deltas, torch.int8).to(device)
        return self.deltas.map(lambda t: t.to(device=device, dtype=dtype or t.dtype))

    def with_precision(self, precision: str) -> Avatar:
        """A copy whose blendshape data (deltas, pose correctives, eyelid offsets: the bulk of an avatar, read
        every frame) is stored in ``precision``; the neutral and mouth Gaussians stay float32 (positions need it:
        fp16 moves a point 0.1 m from the origin by up to 30 um, a tenth of a pixel at 512 px).

        "int8" quantises the deltas (sparse pairs, :meth:`~render_core.packed.Pairs.quantize`: |error| <= half a
        step of each value's scale) and stores the pose correctives and eyelid offsets in fp16."""
        if precision not in PRECISIONS:
            raise OptionError(f"must be one of {', '.join(PRECISIONS)}, got {precision!r}", field="precision")
        store = PRECISIONS[precision]
        side = torch.float16 if store == torch.int8 else store  # pose correctives and eyelids

        def cast(t: Tensor | None, dtype: torch.dtype = torch.float32) -> Tensor | None:
            return None if t is None else t.to(dtype)

        return replace(
            self,
            neutral=self.neutral.map(cast),
            mouth=self.mouth.map(cast),
            lbs_weights=cast(self.lbs_weights),
            joint_positions=cast(self.joint_positions),
            deltas=self._map_deltas(store),
            pose_correctives=cast(self.pose_correctives, side),
            eyelid_offsets=cast(self.eyelid_offsets, side),
        )

    def joint_index(self, name: str) -> int:
        return self.joint_names.index(name)

    def to(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> Avatar:
        """A copy with floating-point tensors cast to ``dtype`` (int8 deltas dequantised to it) and everything
        moved to ``device``."""

        def cast(t: Tensor | None) -> Tensor | None:
            if t is None:
                return None
            return t.to(device=device, dtype=dtype if t.is_floating_point() and dtype else t.dtype)

        return replace(
            self,
            neutral=self.neutral.map(cast),
            deltas=self._map_deltas(dtype, device),
            lbs_weights=cast(self.lbs_weights),
            joint_positions=cast(self.joint_positions),
            mouth=self.mouth.map(cast),
            mouth_group=cast(self.mouth_group),
            pose_correctives=cast(self.pose_correctives),
            eyelid_offsets=cast(self.eyelid_offsets),
        )

    def validate(self) -> None:
        """Raise ShapeError (or ValueError for metadata) naming the first inconsistency."""
        n, k, j = self.num_gaussians, self.num_expressions, self.num_joints
        c = sh_coeff_count(self.sh_degree)
        self.neutral.check("neutral")
        if self.neutral.sh.shape[-2] != c:
            raise ShapeError(f"sh_degree {self.sh_degree} needs {c} coefficients", field="neutral.sh")
        if isinstance(self.deltas, SparseDeltas):
            if self.deltas.num_expressions != k:
                raise ShapeError(f"{k} names but {self.deltas.num_expressions} blendshapes in deltas",
                                 field="expression_names")
            self.deltas.check(n, k, c)
        else:
            if self.deltas.means.dim() != 3 or self.deltas.means.shape[0] != k:
                raise ShapeError(f"{k} names but {list(self.deltas.means.shape[:1])} blendshapes in deltas.means",
                                 field="expression_names")
            self.deltas.check("deltas", lead=(k,))
            if self.deltas.count != n or self.deltas.sh.shape[-2] != c:
                raise ShapeError(f"expected [K={k}, N={n}, ...] deltas", field="deltas")
        self.mouth.check("mouth")
        if self.mouth.sh.shape[-2] != c:
            raise ShapeError(f"sh_degree {self.sh_degree} needs {c} coefficients", field="mouth.sh")
        expect = {
            "lbs_weights": (n, j),
            "joint_positions": (j, 3),
            "mouth_group": (self.num_mouth,),
            "pose_correctives": (9 * (j - 1), n, 3),
            "eyelid_offsets": (2, n, 3),
        }
        for key, shape in expect.items():
            t = getattr(self, key)
            if t is not None and tuple(t.shape) != shape:
                raise ShapeError(f"expected shape {list(shape)}, got {list(t.shape)}", field=key)
        if len(self.joint_parents) != j:
            raise ShapeError(f"expected {j} parents, got {len(self.joint_parents)}", field="joint_parents")
        for i, p in enumerate(self.joint_parents):
            if not (-1 <= p < i):
                raise ShapeError(
                    f"joint {self.joint_names[i]!r} has parent {p}; parents must precede their children "
                    "and only the first joint is a root",
                    field="joint_parents",
                )
        if self.joint_parents and (self.joint_parents[0] != -1 or -1 in self.joint_parents[1:]):
            raise ShapeError("exactly one root joint, first in the list", field="joint_parents")
        if len(set(self.joint_names)) != j:
            raise ShapeError("joint names must be unique", field="joint_names")
        if len(set(self.expression_names)) != k:
            raise ShapeError("expression names must be unique", field="expression_names")
        for name in self.mouth_joint_names:
            if name not in self.joint_names:
                raise ShapeError(f"{name!r} is not a joint ({', '.join(self.joint_names)})",
                                 field="mouth_joint_names")
        if self.raster_mode not in RASTER_MODES:
            raise ShapeError(f"must be one of {RASTER_MODES}, got {self.raster_mode!r}", field="raster_mode")
        if self.mouth_group.dtype not in (torch.int32, torch.int64) or (
            self.num_mouth and not bool(((self.mouth_group == 0) | (self.mouth_group == 1)).all())
        ):
            raise ShapeError("mouth_group must be integers 0 (upper) or 1 (lower)", field="mouth_group")
        w = self.lbs_weights.float()
        if n and (bool((w < 0).any()) or float((w.sum(-1) - 1).abs().max()) > 1e-3):
            raise ShapeError("LBS weights must be non-negative and sum to 1 per Gaussian", field="lbs_weights")
