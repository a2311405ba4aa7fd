"""A trainable Gaussian blendshape avatar with the blendshape-consistency parametrisation (Eq. 2).

dG_{i,k} = dG_init_{i,k} + c_{i,k} dG_hat_{i,k} for all five properties (position, rotation, log-scale, opacity
logit, SH), where dG_init is the constant deformation-gradient initialisation of :func:`init_avatar`, dG_hat the
optimised residual (zeros at start) and c_{i,k} = max(f(d_{i,k}), 0) the consistency weight from the face
model's displacement magnitudes (:mod:`.geometry`). Switches (``consistency``) for the paper's ablations:

- ``"all"``: c weights the residual of every property (the paper);
- ``"positions"``: c weights only the position residual; the other four use dG_init + dG_hat;
- ``"none"``: dG = dG_init + dG_hat for every property;
- ``"frozen"``: dG = dG_init, no residual is optimised.

The neutral Gaussians and the mouth interior are optimised too; LBS weights, pose correctives and eyelid offsets
stay at their initial values.
"""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor, nn

from ..avatar import Avatar, Gaussians, sh_coeff_count
from ..facemodel import FaceModel
from .geometry import consistency_range, consistency_weights, displacement_magnitudes

CONSISTENCY = ("all", "positions", "none", "frozen")
PROPS = ("means", "quats", "log_scales", "opacity_logits", "sh")


class TrainableAvatar(nn.Module):
    """Parameters (nn.Parameter) and constants (buffers) of an avatar being trained.

    Parameters: ``means, quats, log_scales, opacity_logits, sh_dc [N,1,3], sh_rest [N,C-1,3]`` (neutral),
    ``mouth_<same>`` (mouth interior) and ``hat_<prop>`` [K, N, ...] (dG_hat; absent when frozen).
    Buffers: ``init_<prop>`` [K, N, ...] (dG_init), ``weights`` [K, N] (c = max(f(d), 0)), ``d`` [K, N],
    ``lbs_weights``, ``pose_correctives``, ``eyelid_offsets``, ``mouth_group``, ``joint_positions``.
    """

    def __init__(self, avatar: Avatar, d: Tensor, eps: float, d_max: float, consistency: str = "all"):
        super().__init__()
        if consistency not in CONSISTENCY:
            raise ValueError(f"consistency must be one of {', '.join(CONSISTENCY)}, got {consistency!r}")
        avatar = avatar.to(torch.float32)
        self.consistency = consistency
        self.eps, self.d_max = float(eps), float(d_max)
        self.meta = {
            "joint_names": list(avatar.joint_names), "joint_parents": list(avatar.joint_parents),
            "expression_names": list(avatar.expression_names), "mouth_joint_names": list(avatar.mouth_joint_names),
            "sh_degree": int(avatar.sh_degree), "face_model": avatar.face_model, "raster_mode": avatar.raster_mode,
            "default_camera": dict(avatar.default_camera), "provenance": dict(avatar.provenance),
        }
        n, k = avatar.num_gaussians, avatar.num_expressions
        if tuple(d.shape) != (k, n):
            raise ValueError(f"d must be [K={k}, N={n}], got {list(d.shape)}")
        for prefix, g in (("", avatar.neutral), ("mouth_", avatar.mouth)):
            self.register_parameter(prefix + "means", nn.Parameter(g.means.clone()))
            self.register_parameter(prefix + "quats", nn.Parameter(g.quats.clone()))
            self.register_parameter(prefix + "log_scales", nn.Parameter(g.log_scales.clone()))
            self.register_parameter(prefix + "opacity_logits", nn.Parameter(g.opacity_logits.clone()))
            self.register_parameter(prefix + "sh_dc", nn.Parameter(g.sh[:, :1].clone()))
            self.register_parameter(prefix + "sh_rest", nn.Parameter(g.sh[:, 1:].clone()))
        for prop in PROPS:
            init = getattr(avatar.deltas, prop).clone()
            self.register_buffer("init_" + prop, init)
            if consistency != "frozen":
                self.register_parameter("hat_" + prop, nn.Parameter(torch.zeros_like(init)))
        self.register_buffer("d", d.float().clone())
        self.register_buffer("weights", consistency_weights(self.d, self.eps, self.d_max))
        self.register_buffer("lbs_weights", avatar.lbs_weights.clone())
        self.register_buffer("joint_positions", avatar.joint_positions.clone())
        self.register_buffer("mouth_group", avatar.mouth_group.clone())
        self.pose_correctives = avatar.pose_correctives.clone() if avatar.pose_correctives is not None else None
        self.eyelid_offsets = avatar.eyelid_offsets.clone() if avatar.eyelid_offsets is not None else None

    # ------------------------------------------------------------------------------------------ construction
    @classmethod
    def from_facemodel(cls, avatar: Avatar, model: FaceModel, consistency: str = "all") -> TrainableAvatar:
        """Wrap an :func:`init_avatar` result; d and (eps, d_max) from ``model`` (:mod:`.geometry`)."""
        eps, d_max = consistency_range(model)
        d = displacement_magnitudes(model, avatar.neutral.means)
        return cls(avatar, d, eps, d_max, consistency)

    # ------------------------------------------------------------------------------------------------ state
    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    def weighted(self, prop: str) -> bool:
        """Whether the residual of ``prop`` is multiplied by the consistency weights."""
        return self.consistency == "all" or (self.consistency == "positions" and prop == "means")

    def hat(self, prop: str) -> Tensor | None:
        return getattr(self, "hat_" + prop, None)

    def delta(self, prop: str, sh_coeffs: int | None = None) -> Tensor:
        """The effective dG of ``prop`` [K, N, ...] (differentiable in dG_hat); SH cut to ``sh_coeffs``."""
        init = getattr(self, "init_" + prop)
        hat = self.hat(prop)
        if prop == "sh" and sh_coeffs is not None:
            init = init[:, :, :sh_coeffs]
            hat = None if hat is None else hat[:, :, :sh_coeffs]
        if hat is None:
            return init
        if self.weighted(prop):
            w = self.weights.reshape(*self.weights.shape, *([1] * (hat.dim() - 2)))
            return init + w * hat
        return init + hat

    def state_tensors(self) -> dict[str, Tensor]:
        """Every tensor of the model (parameters, buffers and the optional constants), for checkpoints."""
        out = {k: v.detach() for k, v in self.named_parameters()}
        out.update({k: v for k, v in self.named_buffers()})
        if self.pose_correctives is not None:
            out["pose_correctives"] = self.pose_correctives
        if self.eyelid_offsets is not None:
            out["eyelid_offsets"] = self.eyelid_offsets
        return out

    # ------------------------------------------------------------------------------------------------ views
    def avatar(self, sh_degree: int | None = None, detach: bool = False) -> Avatar:
        """The current avatar (differentiable unless ``detach``), its SH cut to ``sh_degree`` (default: all)."""
        full = self.meta["sh_degree"]
        degree = full if sh_degree is None else min(sh_degree, full)
        c = sh_coeff_count(degree)

        def t(x: Tensor) -> Tensor:
            return x.detach() if detach else x

        def sh(prefix: str) -> Tensor:
            dc, rest = getattr(self, prefix + "sh_dc"), getattr(self, prefix + "sh_rest")
            return t(dc) if c == 1 else t(torch.cat([dc, rest[:, : c - 1]], dim=1))

        neutral = Gaussians(t(self.means), t(self.quats), t(self.log_scales), t(self.opacity_logits), sh(""))
        mouth = Gaussians(t(self.mouth_means), t(self.mouth_quats), t(self.mouth_log_scales),
                          t(self.mouth_opacity_logits), sh("mouth_"))
        deltas = Gaussians(*(t(self.delta(p, c)) for p in PROPS))
        m = self.meta
        return Avatar(
            neutral=neutral, deltas=deltas, lbs_weights=self.lbs_weights, joint_positions=self.joint_positions,
            joint_names=list(m["joint_names"]), joint_parents=list(m["joint_parents"]),
            expression_names=list(m["expression_names"]), mouth=mouth, mouth_group=self.mouth_group,
            mouth_joint_names=tuple(m["mouth_joint_names"]), pose_correctives=self.pose_correctives,
            eyelid_offsets=self.eyelid_offsets, sh_degree=degree, face_model=m["face_model"],
            raster_mode=m["raster_mode"], default_camera=dict(m["default_camera"]),
            provenance=dict(m["provenance"]),
        )

    def to_avatar(self, provenance: dict | None = None) -> Avatar:
        """A plain :class:`Avatar` (deltas = the effective dG, full SH degree), detached, float32, on the CPU."""
        with torch.no_grad():
            av = self.avatar(detach=True).to(torch.float32, "cpu")
        av = replace(av, neutral=av.neutral.map(torch.Tensor.clone), deltas=av.deltas.map(torch.Tensor.clone),
                     mouth=av.mouth.map(torch.Tensor.clone))
        if provenance:
            av.provenance = {**av.provenance, **provenance}
        av.validate()
        return av
