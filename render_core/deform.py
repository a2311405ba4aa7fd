"""Animation of a Gaussian blendshape avatar: frame parameters -> deformed splats (docs/method.md section 2).

Pipeline per frame (batched over B frames, never looping over Gaussians):

1. :func:`blend` - Eq. 1, B(psi) = B0 + sum_k psi_k dB_k for all five properties.
2. :func:`skin` - pose correctives, eyelids, linear blend skinning through :func:`joint_transforms`, rotation
   of the Gaussians (and optionally of their SH), activation of scales and opacities, and the rigid mouth
   interior.
3. :func:`shade` - view-dependent colour per Gaussian for given camera centres.

:func:`deform` runs 1 and 2 after validating the :class:`Frame`.

World conventions follow FLAME (metres, y up, face towards +z). Joint rotations are relative to the parent, in
the parent's rest frame whose axes are aligned with the world axes at rest (as FLAME does).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from . import host
from .avatar import Avatar, Gaussians
from .errors import FrameError, ShapeError
from .packed import SparseDeltas
from .rotation import axis_angle_to_matrix, matrix_to_quat, orthogonalize, quat_multiply, rot6d_to_matrix
from .sh import eval_sh
from .sh import rotate_sh as _rotate_sh

__all__ = [
    "Frame",
    "Splats",
    "blend",
    "deform",
    "joint_transforms",
    "pose_features",
    "shade",
    "skin",
]

# Tolerance on |R R^T - I| and det(R) for joint rotation matrices given to a Frame.
ROTATION_TOL = 1e-3


def _compute_dtype(dtype: torch.dtype) -> torch.dtype:
    """float64 stays float64 (gradient checks); everything else (fp16, bf16, fp32) computes in float32."""
    return torch.float64 if dtype == torch.float64 else torch.float32


def _device_of(avatar: Avatar) -> torch.device:
    return avatar.neutral.means.device


def _list(names: Sequence[str]) -> str:
    return ", ".join(names)


@dataclass
class Frame:
    """Animation parameters of B frames for one avatar.

    Attributes:
        expression: [B, K] expression (blendshape) coefficients psi, in ``avatar.expression_names`` order.
        joint_rotations: [B, J, 3, 3] rotation matrices of the avatar's joints (``joint_names`` order), each
            relative to its parent, in the parent's rest frame aligned with the world axes at rest (FLAME's
            convention). Identity everywhere is the rest pose.
        eyelids: [B, 2] eyelid coefficients (left, right) scaling the avatar's ``eyelid_offsets``, or None
            (no eyelid motion). Ignored by avatars without eyelid offsets.
    """

    expression: Tensor  # [B, K]
    joint_rotations: Tensor  # [B, J, 3, 3]
    eyelids: Tensor | None = None  # [B, 2] or None

    @property
    def batch_size(self) -> int:
        return int(self.expression.shape[0])

    def __len__(self) -> int:
        return self.batch_size

    @classmethod
    def neutral(cls, avatar: Avatar, batch: int = 1, dtype: torch.dtype = torch.float32) -> Frame:
        """B = ``batch`` frames of zero expression, rest pose and no eyelid motion, on the avatar's device."""
        device = _device_of(avatar)
        eye = torch.eye(3, dtype=dtype, device=device)
        return cls(
            expression=torch.zeros(batch, avatar.num_expressions, dtype=dtype, device=device),
            joint_rotations=eye.expand(batch, avatar.num_joints, 3, 3).clone(),
            eyelids=None,
        )

    @classmethod
    def from_params(
        cls,
        avatar: Avatar,
        expression: Tensor | Sequence[float] | Mapping[str, Any] | None = None,
        joints: Tensor | Mapping[str, Any] | None = None,
        eyelids: Tensor | Sequence[float] | None = None,
    ) -> Frame:
        """Build and validate a frame from user-facing parameters.

        Args:
            avatar: the avatar the frame animates (gives K, the joint names and the device).
            expression: [B, K] (or [K]) coefficients by position, or a mapping expression name -> value
                (a float or a [B] tensor); names not given are zero. None: all zero.
            joints: a mapping joint name -> [B, 3] (or [3]) axis-angle, [B, 6] (or [6]) 6D rotation (first
                two rows of the matrix, docs/method.md section 8) or [B, 3, 3] matrices; or a full [B, J, 3] or
                [B, J, 6] tensor (leading B optional) or [B, J, 3, 3] matrices. Joints not named stay at
                identity.
            eyelids: [B, 2] (or [2]) eyelid coefficients, or None.

        Inputs with a batch of 1 broadcast to the largest batch given. Computes in float32, or float64 when
        any tensor given is float64.

        Raises:
            FrameError: unknown expression or joint names, wrong sizes, or non-finite values (the message
                lists what is valid).
        """
        device = _device_of(avatar)
        names_k, names_j = avatar.expression_names, avatar.joint_names
        given = _tensors_in(expression, joints, eyelids)
        dtype = torch.float64 if any(t.dtype == torch.float64 for t in given) else torch.float32

        def as_tensor(value: Any, field: str) -> Tensor:
            try:
                t = torch.as_tensor(value)
            except (TypeError, ValueError, RuntimeError) as exc:
                raise FrameError(f"not a numeric tensor ({exc})", field=field) from None
            if t.is_complex() or not (t.is_floating_point() or t.dtype in (torch.int32, torch.int64)):
                raise FrameError(f"expected real numbers, got {t.dtype}", field=field)
            return t.to(device=device, dtype=dtype)

        # Every input as (field, tensor, rank without the optional leading batch dim).
        items: list[tuple[str, Tensor, int]] = []
        if isinstance(expression, Mapping):
            unknown = [repr(n) for n in expression if n not in names_k]
            if unknown:
                raise FrameError(
                    f"unknown expression name(s) {_list(unknown)}; valid names: {_list(names_k)}",
                    field="expression",
                )
            items += [(f"expression.{n}", as_tensor(v, f"expression.{n}"), 0) for n, v in expression.items()]
        elif expression is not None:
            items.append(("expression", as_tensor(expression, "expression"), 1))
        if isinstance(joints, Mapping):
            unknown = [repr(n) for n in joints if n not in names_j]
            if unknown:
                raise FrameError(f"unknown joint name(s) {_list(unknown)}; valid joints: {_list(names_j)}",
                                 field="joints")
            for name, value in joints.items():
                t = as_tensor(value, f"joints.{name}")
                matrix = t.dim() == 3 and t.shape[-2:] == (3, 3)
                if not matrix and (t.dim() not in (1, 2) or t.shape[-1] not in (3, 6)):
                    raise FrameError(
                        "expected [B, 3] axis-angle, [B, 6] 6D or [B, 3, 3] matrices, got shape "
                        f"{list(t.shape)}",
                        field=f"joints.{name}",
                    )
                items.append((f"joints.{name}", t, 2 if matrix else 1))
        elif joints is not None:
            t = as_tensor(joints, "joints")
            matrix = t.dim() == 4 and t.shape[-2:] == (3, 3)
            if not matrix and (t.dim() not in (2, 3) or t.shape[-1] not in (3, 6)):
                raise FrameError(f"expected [B, J, 3] axis-angle, [B, J, 6] 6D or [B, J, 3, 3] matrices for "
                                 f"joints {_list(names_j)}, got shape {list(t.shape)}", field="joints")
            if t.shape[-3 if matrix else -2] != len(names_j):
                raise FrameError(
                    f"expected {len(names_j)} joints ({_list(names_j)}), got shape {list(t.shape)}",
                    field="joints",
                )
            items.append(("joints", t, 3 if matrix else 2))
        if eyelids is not None:
            items.append(("eyelids", as_tensor(eyelids, "eyelids"), 1))

        batch = 1
        for field, t, rank in items:
            if not bool(torch.isfinite(t).all()):
                raise FrameError("values must be finite (no NaN or Infinity)", field=field)
            if t.dim() not in (rank, rank + 1):
                raise FrameError(f"expected {rank} dims, or {rank + 1} with a leading batch, got shape "
                                 f"{list(t.shape)}", field=field)
            if t.dim() == rank + 1 and t.shape[0] != 1:
                if batch not in (1, t.shape[0]):
                    raise FrameError(f"batch size {t.shape[0]} does not match {batch}", field=field)
                batch = int(t.shape[0])

        frame = cls.neutral(avatar, batch, dtype)
        named_joints: dict[tuple[bool, int], list[tuple[int, Tensor]]] = {}  # (matrix, size) -> [(joint, [B, ...])]
        for field, t, rank in items:
            t = (t.unsqueeze(0) if t.dim() == rank else t).expand(batch, *t.shape[t.dim() - rank:])
            if field == "expression":
                frame.expression = t.clone()
            elif field == "eyelids":
                frame.eyelids = t.clone()
            elif field == "joints":
                frame.joint_rotations = _to_matrix(t, rank == 3).clone()
            elif field.startswith("expression."):
                frame.expression[:, names_k.index(field.split(".", 1)[1])] = t
            else:
                key = (rank == 2, t.shape[-1])
                named_joints.setdefault(key, []).append((names_j.index(field.split(".", 1)[1]), t))
        for (matrix, _), group in named_joints.items():  # one conversion per kind, not per joint
            joint_ids = [j for j, _ in group]
            frame.joint_rotations[:, joint_ids] = _to_matrix(torch.stack([t for _, t in group], 1), matrix)
        frame.check(avatar)
        return frame

    @staticmethod
    def stack(frames: Sequence[Frame]) -> Frame:
        """Concatenate frames along the batch dimension. Eyelids missing from some frames become zeros."""
        if not frames:
            raise FrameError("cannot stack an empty list of frames", field="frames")
        eyelids = None
        if any(f.eyelids is not None for f in frames):
            ref = frames[0].expression
            eyelids = host.cat([
                f.eyelids if f.eyelids is not None
                else host.zeros((f.batch_size, 2), like=ref)
                for f in frames
            ])
        return Frame(
            expression=host.cat([f.expression for f in frames]),
            joint_rotations=host.cat([f.joint_rotations for f in frames]),
            eyelids=eyelids,
        )

    def to(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> Frame:
        """A copy with tensors cast to ``dtype`` and moved to ``device``."""
        return Frame(
            expression=self.expression.to(device=device, dtype=dtype),
            joint_rotations=self.joint_rotations.to(device=device, dtype=dtype),
            eyelids=None if self.eyelids is None else self.eyelids.to(device=device, dtype=dtype),
        )

    def check(self, avatar: Avatar) -> None:
        """Raise FrameError unless the frame fits the avatar: shapes [B, K], [B, J, 3, 3] and [B, 2]; finite
        values; rotation matrices orthonormal with determinant +1 (to 1e-3)."""
        k, j = avatar.num_expressions, avatar.num_joints
        e = self.expression
        if e.dim() != 2:
            raise FrameError(f"expected a [B, {k}] tensor, got shape {list(e.shape)}", field="expression")
        b = e.shape[0]
        if e.shape[1] != k:
            raise FrameError(
                f"expected {k} expression coefficients, got {e.shape[1]}; coefficients can also be given by "
                f"name (any subset of: {_list(avatar.expression_names)})",
                field="expression",
            )
        r = self.joint_rotations
        if r.dim() != 4 or r.shape[1:] != (j, 3, 3) or r.shape[0] != b:
            raise FrameError(
                f"expected [B={b}, J={j}, 3, 3] rotations for joints {_list(avatar.joint_names)}, got shape "
                f"{list(r.shape)}",
                field="joint_rotations",
            )
        if self.eyelids is not None and tuple(self.eyelids.shape) != (b, 2):
            raise FrameError(f"expected shape [{b}, 2] (left, right), got {list(self.eyelids.shape)}",
                             field="eyelids")
        for field, t in (("expression", e), ("joint_rotations", r), ("eyelids", self.eyelids)):
            if t is not None and not host.finite(t):
                raise FrameError("contains non-finite values (NaN or inf)", field=field)
        if b and j:  # on the host, in numpy (render_core.host: a render thread's checks keep the GIL)
            rd = host.array(r, np.float64)
            per_joint = np.abs(rd @ rd.swapaxes(-1, -2) - np.eye(3)).max(axis=(0, 2, 3))
            det = np.linalg.det(rd).min(axis=0)
            bad_mask = (per_joint > ROTATION_TOL) | (det < 1 - ROTATION_TOL)
            if bad_mask.any():
                bad = [avatar.joint_names[i] for i in np.flatnonzero(bad_mask).tolist()]
                raise FrameError(f"not rotation matrices for joint(s) {_list(bad)}", field="joint_rotations")


def _tensors_in(*values: Any) -> list[Tensor]:
    out: list[Tensor] = []
    for v in values:
        if isinstance(v, Tensor):
            out.append(v)
        elif isinstance(v, Mapping):
            out.extend(x for x in v.values() if isinstance(x, Tensor))
    return out


def _to_matrix(t: Tensor, matrix: bool) -> Tensor:
    """Matrices [..., 3, 3] (when ``matrix``), axis-angle [..., 3] or 6D [..., 6] -> matrices [..., 3, 3]."""
    if matrix:
        return t
    if t.shape[-1] == 3:
        return axis_angle_to_matrix(t)
    return rot6d_to_matrix(t)


@dataclass
class Splats:
    """Deformed Gaussians of B frames, ready to shade and splat (face Gaussians first, then the mouth's).

    Attributes:
        means: [B, N, 3] world-space centres.
        quats: [B, N, 4] unit quaternions, w first (gsplat's convention), world-space orientation.
        scales: [B, N, 3] standard deviations along the Gaussian's axes (exp of the log-scales).
        opacities: [B, N] in (0, 1) (sigmoid of the logits).
        sh: [B, N, C, 3] SH colour coefficients, C = (sh_degree + 1)^2, DC first (:mod:`render_core.sh`).
        sh_rotations: [B, N, 3, 3] or None. When set, ``sh`` is in each Gaussian's rest frame and the colour
            seen along the world direction d is ``eval_sh(sh, R^T d)`` with R = ``sh_rotations``; when None,
            ``sh`` is already in world space (colour ``eval_sh(sh, d)``).
        sh_degree: SH degree of ``sh``.

    N counts the face Gaussians followed by the mouth-interior Gaussians. B may be 1 with tensors broadcast.
    :meth:`render_core.raster.ShadedSplats.from_splats` evaluates the colours for B cameras, giving what every
    rasterizer backend takes.
    """

    means: Tensor  # [B, N, 3]
    quats: Tensor  # [B, N, 4] wxyz, unit
    scales: Tensor  # [B, N, 3]
    opacities: Tensor  # [B, N]
    sh: Tensor  # [B, N, C, 3]
    sh_rotations: Tensor | None  # [B, N, 3, 3] or None
    sh_degree: int

    @property
    def batch_size(self) -> int:
        return int(self.means.shape[0])

    @property
    def count(self) -> int:
        return int(self.means.shape[1])

    def to(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> Splats:
        """A copy with tensors cast to ``dtype`` and moved to ``device``."""
        def cast(t: Tensor | None) -> Tensor | None:
            return None if t is None else t.to(device=device, dtype=dtype)

        return Splats(cast(self.means), cast(self.quats), cast(self.scales), cast(self.opacities),
                      cast(self.sh), cast(self.sh_rotations), self.sh_degree)

    def expand(self, batch: int) -> Splats:
        """A batch-1 set seen ``batch`` times (views, no copies)."""
        def grow(t: Tensor | None) -> Tensor | None:
            return None if t is None else t.expand(batch, *t.shape[1:])

        return Splats(grow(self.means), grow(self.quats), grow(self.scales), grow(self.opacities),
                      grow(self.sh), grow(self.sh_rotations), self.sh_degree)


def blend(avatar: Avatar, expression: Tensor) -> Gaussians:
    """Eq. 1: B(psi) = B0 + sum_k psi_k dB_k for all five properties (raw: quaternions unnormalised,
    log-scales, opacity logits).

    One matrix-matrix product per property, ``expression [B, K] @ deltas [K, N*D]``, added to the neutral; for
    sparse deltas (:class:`~render_core.packed.SparseDeltas`) only the stored pairs are multiplied. Storage
    (possibly fp16) is cast to float32, or to float64 when ``expression`` is float64. Differentiable
    with respect to ``expression`` and the avatar's tensors.

    Args:
        avatar: the avatar.
        expression: [B, K] coefficients.

    Returns:
        Gaussians with [B, N, ...] tensors.
    """
    if expression.dim() != 2 or expression.shape[1] != avatar.num_expressions:
        raise ShapeError(f"expected [B, {avatar.num_expressions}], got {list(expression.shape)}",
                         field="expression")
    dtype = _compute_dtype(expression.dtype)
    expr = expression.to(dtype)
    b, k, n = expr.shape[0], avatar.num_expressions, avatar.num_gaussians

    def one(base: Tensor, delta: Tensor) -> Tensor:
        tail = base.shape[1:]
        flat = expr @ delta.to(dtype).reshape(k, -1)  # [B, N*D]
        return base.to(dtype).unsqueeze(0) + flat.reshape(b, n, *tail)

    neutral, deltas = avatar.neutral, avatar.deltas
    if isinstance(deltas, SparseDeltas):
        geometry, color = deltas.blend(expr, dtype)
        g = geometry.split([3, 4, 3, 1], -1)
        return Gaussians(
            means=neutral.means.to(dtype) + g[0],
            quats=neutral.quats.to(dtype) + g[1],
            log_scales=neutral.log_scales.to(dtype) + g[2],
            opacity_logits=neutral.opacity_logits.to(dtype) + g[3][..., 0],
            sh=neutral.sh.to(dtype) + color.reshape(b, n, *neutral.sh.shape[1:]),
        )
    return Gaussians(
        means=one(neutral.means, deltas.means),
        quats=one(neutral.quats, deltas.quats),
        log_scales=one(neutral.log_scales, deltas.log_scales),
        opacity_logits=one(neutral.opacity_logits, deltas.opacity_logits),
        sh=one(neutral.sh, deltas.sh),
    )


def joint_transforms(avatar: Avatar, joint_rotations: Tensor) -> Tensor:  # or a FaceModel: any joint tree
    """Skinning transforms A_j of every joint: rest-pose world point -> posed world point.

    Forward kinematics through ``avatar.joint_parents`` from the rest ``joint_positions`` J:
    G_j = G_parent [R_j | J_j - J_parent] (root: [R_0 | J_0]) and A_j = G_j [I | -J_j]. Computed in the
    equivalent form A_j = A_parent [R_j | (I - R_j) J_j] (a rotation about J_j, then the parent's motion), so
    that identity rotations give exactly [I | 0].

    Args:
        avatar: the avatar (joint tree and rest positions).
        joint_rotations: [B, J, 3, 3] rotations relative to the parent.

    Returns:
        [B, J, 3, 4] transforms [R | t]: x_posed = R x_rest + t.
    """
    r = joint_rotations
    j = avatar.num_joints
    if r.dim() != 4 or r.shape[1:] != (j, 3, 3):
        raise ShapeError(f"expected [B, {j}, 3, 3], got {list(r.shape)}", field="joint_rotations")
    pos = avatar.joint_positions.to(device=r.device, dtype=r.dtype)  # [J, 3], or [B, J, 3] per frame
    pos = pos[None] if pos.dim() == 2 else pos
    eye = torch.eye(3, dtype=r.dtype, device=r.device)
    # Local transforms about each joint: [R_j | (I - R_j) J_j].
    local_t = ((eye - r) @ pos[..., None]).squeeze(-1)  # [B, J, 3]
    rots: list[Tensor] = []
    trans: list[Tensor] = []
    for i, parent in enumerate(avatar.joint_parents):
        if parent < 0:
            rots.append(r[:, i])
            trans.append(local_t[:, i])
        else:
            pr, pt = rots[parent], trans[parent]
            rots.append(pr @ r[:, i])
            trans.append((pr @ local_t[:, i, :, None]).squeeze(-1) + pt)
    return torch.cat([torch.stack(rots, 1), torch.stack(trans, 1).unsqueeze(-1)], dim=-1)


def pose_features(joint_rotations: Tensor) -> Tensor:
    """FLAME pose-corrective features: (R_j - I) of the non-root joints, flattened joint-major, row-major.

    Args:
        joint_rotations: [B, J, 3, 3].

    Returns:
        [B, 9 (J - 1)].
    """
    r = joint_rotations[:, 1:]
    eye = torch.eye(3, dtype=r.dtype, device=r.device)
    return (r - eye).reshape(r.shape[0], -1)


def _posed_quats(rot: Tensor, quats: Tensor) -> Tensor:
    """normalise(q(rot) * normalise(quats)): pre-multiply rest orientations by a rotation."""
    q = quat_multiply(matrix_to_quat(rot), torch.nn.functional.normalize(quats, dim=-1))
    return torch.nn.functional.normalize(q, dim=-1)


def skin(avatar: Avatar, blended: Gaussians, frame: Frame, rotate_sh: bool = False) -> Splats:
    """Pose blended Gaussians and append the mouth interior (docs/method.md section 2, steps 2-7).

    Steps, batched over B frames:

    1. Pose correctives: means += pose_features(R) @ pose_correctives (FLAME posedirs), if the avatar has
       them.
    2. Eyelids: means += sum_e eyelids[:, e] * eyelid_offsets[e], if both the avatar and the frame have them.
       Applied in the rest pose, *before* LBS, so the eyelids follow the head. (docs/method.md says "after LBS"
       because the tracker keeps the head still, where both orders give the same result.)
    3. LBS: T = I + sum_j w_j (A_j - I) (equal to sum_j w_j A_j since the weights sum to 1, and exactly the
       identity at rest); x' = T[:, :3] x + T[:, 3].
    4. Rotation: R_n = orthogonalize(T[:, :3]) (3 Newton iterations, as the reference code);
       q' = normalise(q(R_n) * normalise(q)).
    5. scales = exp(log_scales); opacities = sigmoid(logits).
    6. SH: ``rotate_sh`` True rotates the coefficients into world space (``sh_rotations`` None); False keeps
       them in the rest frame and returns ``sh_rotations`` = R_n (cheaper; colour via R_n^T d).
    7. Mouth: each mouth Gaussian moves rigidly with joint ``avatar.mouth_joint_names[mouth_group]``
       (0 upper, 1 lower), appended after the face Gaussians.

    Args:
        avatar: the avatar.
        blended: output of :func:`blend`, [B, N, ...] tensors (or [N, ...], broadcast to B).
        frame: the frame (its joint rotations and eyelids are used; the expression is already in ``blended``).
        rotate_sh: rotate SH coefficients instead of returning ``sh_rotations``.

    Returns:
        Splats with N + M Gaussians per frame, in ``blended``'s dtype.
    """
    dtype, device = blended.means.dtype, blended.means.device
    b = frame.batch_size
    if blended.means.dim() == 2:
        blended = blended.map(lambda t: t.unsqueeze(0).expand(b, *t.shape))
    if blended.means.shape[0] != b:
        raise ShapeError(f"blended batch {blended.means.shape[0]} does not match the frame's {b}",
                         field="blended")
    n = blended.means.shape[1]
    rots = frame.joint_rotations.to(device=device, dtype=dtype)
    a = joint_transforms(avatar, rots)  # [B, J, 3, 4]

    means = blended.means
    if avatar.pose_correctives is not None:
        pc = avatar.pose_correctives.to(device=device, dtype=dtype).reshape(-1, n * 3)  # [9(J-1), N*3]
        means = means + (pose_features(rots) @ pc).reshape(b, n, 3)
    if avatar.eyelid_offsets is not None and frame.eyelids is not None:
        off = avatar.eyelid_offsets.to(device=device, dtype=dtype).reshape(2, n * 3)
        means = means + (frame.eyelids.to(device=device, dtype=dtype) @ off).reshape(b, n, 3)

    # LBS, blended as offsets from the identity so that the rest pose is reproduced exactly.
    eye34 = torch.eye(3, 4, dtype=dtype, device=device)
    w = avatar.lbs_weights.to(device=device, dtype=dtype)  # [N, J]
    t = eye34 + torch.einsum("nj,bjrc->bnrc", w, a - eye34)  # [B, N, 3, 4]
    means = (t[..., :3] @ means.unsqueeze(-1)).squeeze(-1) + t[..., 3]
    rot = orthogonalize(t[..., :3])
    quats = _posed_quats(rot, blended.quats)

    # Mouth interior: rigid with its group's joint.
    mouth = avatar.mouth
    # Group 0 follows the first mouth joint, group 1 the second (no index tensor built on the host: a CUDA graph
    # can hold this).
    upper, lower = (avatar.joint_index(name) for name in avatar.mouth_joint_names)
    lower_group = avatar.mouth_group.to(device).eq(1)[None, :, None, None]
    am = torch.where(lower_group, a[:, lower, None], a[:, upper, None])  # [B, M, 3, 4]
    m_rot = orthogonalize(am[..., :3])
    m_x = mouth.means.to(device=device, dtype=dtype)
    m_means = (am[..., :3] @ m_x[None, :, :, None]).squeeze(-1) + am[..., 3]
    m_quats = _posed_quats(m_rot, mouth.quats.to(device=device, dtype=dtype))
    m = mouth.count
    m_sh = mouth.sh.to(device=device, dtype=dtype).unsqueeze(0).expand(b, m, *mouth.sh.shape[1:])

    all_rot = torch.cat([rot, m_rot], dim=1)
    sh = torch.cat([blended.sh, m_sh], dim=1)
    if rotate_sh:
        sh = _rotate_sh(sh, all_rot)
        sh_rotations = None
    else:
        sh_rotations = all_rot

    def cat(face: Tensor, mouth_t: Tensor) -> Tensor:
        mouth_t = mouth_t.to(device=device, dtype=dtype)
        return torch.cat([face, mouth_t.unsqueeze(0).expand(b, *mouth_t.shape)], dim=1)

    return Splats(
        means=torch.cat([means, m_means], dim=1),
        quats=torch.cat([quats, m_quats], dim=1),
        scales=cat(blended.log_scales, mouth.log_scales).exp(),
        opacities=torch.sigmoid(cat(blended.opacity_logits, mouth.opacity_logits)),
        sh=sh,
        sh_rotations=sh_rotations,
        sh_degree=avatar.sh_degree,
    )


def deform(avatar: Avatar, frame: Frame, rotate_sh: bool = False) -> Splats:
    """Animate B frames: ``skin(avatar, blend(avatar, frame.expression), frame, rotate_sh)`` after
    ``frame.check(avatar)``.

    Raises:
        FrameError: the frame does not fit the avatar.
    """
    frame.check(avatar)
    return skin(avatar, blend(avatar, frame.expression), frame, rotate_sh=rotate_sh)


def shade(splats: Splats, camera_centres: Tensor) -> Tensor:
    """View-dependent RGB of every Gaussian (docs/method.md section 9 step 6).

    colour = max(eval_sh(sh, d_local) + 0.5, 0), d = normalise(mean - camera_centre) in world space and
    d_local = R^T d when ``splats.sh_rotations`` is set (else d).

    Args:
        splats: deformed Gaussians with batch 1 (broadcast to every camera) or B.
        camera_centres: [B, 3] (or [3]) world-space camera centres.

    Returns:
        [B, N, 3] colours.
    """
    c = camera_centres
    if c.dim() == 1:
        c = c.unsqueeze(0)
    if c.dim() != 2 or c.shape[1] != 3:
        raise ShapeError(f"expected [B, 3], got {list(camera_centres.shape)}", field="camera_centres")
    if splats.batch_size not in (1, c.shape[0]) and c.shape[0] != 1:
        raise ShapeError(f"splats batch {splats.batch_size} does not match {c.shape[0]} cameras",
                         field="camera_centres")
    means = splats.means
    c = c.to(device=means.device, dtype=means.dtype)
    d = torch.nn.functional.normalize(means - c[:, None, :], dim=-1)
    if splats.sh_rotations is not None:
        d = (splats.sh_rotations.transpose(-1, -2) @ d.unsqueeze(-1)).squeeze(-1)
    return (eval_sh(splats.sh, d, splats.sh_degree) + 0.5).clamp_min(0.0)
