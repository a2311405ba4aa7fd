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
are not optimised (densification may look LBS weights and d up again in the lookup grid, :mod:`.densify`).

Storage is sparse where the method allows it (the blend, its backward and Adam scale with the pairs stored, not
with K x N): dG_init is stored for its non-zero (Gaussian, blendshape) pairs only (``init_k``, ``init_n``: about
13% of the pairs on the open head), and a *weighted* residual only for the pairs whose weight c is positive
(``hat_k``, ``hat_n``, ``hat_w``: about 8%); a residual with c = 0 could never change anything. Unweighted
residuals (the "none" and "positions" ablations) are dense [K, N, ...].
"""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor, nn

from ..avatar import Avatar, Gaussians, sh_coeff_count
from ..errors import OptionError
from ..facemodel import FaceModel
from .geometry import consistency_range, consistency_weights, displacement_magnitudes

CONSISTENCY = ("all", "positions", "none", "frozen")
PROPS = ("means", "quats", "log_scales", "opacity_logits", "sh")


class _AddRows(torch.autograd.Function):
    """x.index_add(0, index, src) whose backward gathers with advanced indexing (several times faster on the CPU
    than index_select, which the built-in backward uses)."""

    @staticmethod
    def forward(ctx, x: Tensor, index: Tensor, src: Tensor) -> Tensor:
        ctx.save_for_backward(index)
        return torch.index_add(x, 0, index, src)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor):
        (index,) = ctx.saved_tensors
        grad_src = grad[index] if ctx.needs_input_grad[2] else None
        return grad if ctx.needs_input_grad[0] else None, None, grad_src


def add_rows(x: Tensor, index: Tensor, src: Tensor) -> Tensor:
    """``torch.index_add(x, 0, index, src)`` (out of place, differentiable in x and src)."""
    return _AddRows.apply(x, index, src)


class TrainableAvatar(nn.Module):
    """Parameters (nn.Parameter) and constants (buffers) of an avatar being trained.

    Parameters: ``means, quats, log_scales, opacity_logits, sh_dc [N,1,3], sh_rest [N,C-1,3]`` (neutral),
    ``mouth_<same>`` (mouth interior) and ``hat_<prop>`` (dG_hat; [P, ...] over the pairs ``hat_k, hat_n`` when
    weighted, [K, N, ...] when not; absent when frozen).
    Buffers: ``init_<prop>`` [Pi, ...] over the pairs ``init_k, init_n`` (dG_init), ``d`` and ``weights`` [K, N]
    (c = max(f(d), 0)), ``hat_k, hat_n, hat_w`` (the weighted pairs and their c), ``lbs_weights``, ``lookup_at``
    [N, 3] (the neutral positions where ``lbs_weights`` and ``d`` were set: at initialisation, or the last grid
    lookup of :mod:`.densify`), ``joint_positions``, ``mouth_group``; plain attributes ``pose_correctives`` and
    ``eyelid_offsets`` (or None).
    """

    def __init__(self, avatar: Avatar, d: Tensor, eps: float, d_max: float, consistency: str = "all"):
        super().__init__()
        if consistency not in CONSISTENCY:
            raise OptionError(f"must be one of {', '.join(CONSISTENCY)}, got {consistency!r}", field="consistency")
        avatar = avatar.to(torch.float32)
        self.consistency = consistency
        self.eps, self.d_max = float(eps), float(d_max)
        self.meta = {
            "joint_names": list(avatar.joint_names), "joint_parents": list(avatar.joint_parents),
            "expression_names": list(avatar.expression_names), "mouth_joint_names": list(avatar.mouth_joint_names),
            "sh_degree": int(avatar.sh_degree), "face_model": avatar.face_model, "raster_mode": avatar.raster_mode,
            "default_camera": dict(avatar.default_camera), "provenance": dict(avatar.provenance),
            "num_expressions": avatar.num_expressions,
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
        deltas = avatar.dense_deltas()
        nonzero = torch.zeros(k, n, dtype=torch.bool)
        for prop in PROPS:
            t = getattr(deltas, prop)
            nonzero |= t.reshape(k, n, -1).ne(0).any(-1)
        ik, in_ = nonzero.nonzero(as_tuple=True)
        self.register_buffer("init_k", ik)
        self.register_buffer("init_n", in_)
        for prop in PROPS:
            self.register_buffer("init_" + prop, getattr(deltas, prop)[ik, in_].clone())
        self.register_buffer("d", d.float().clone())
        self.register_buffer("weights", consistency_weights(self.d, self.eps, self.d_max))
        hk, hn = (self.weights > 0).nonzero(as_tuple=True)
        self.register_buffer("hat_k", hk)
        self.register_buffer("hat_n", hn)
        self.register_buffer("hat_w", self.weights[hk, hn].clone())
        if consistency != "frozen":
            for prop in PROPS:
                tail = getattr(deltas, prop).shape[2:]
                shape = (len(hk), *tail) if self.weighted(prop) else (k, n, *tail)
                self.register_parameter("hat_" + prop, nn.Parameter(torch.zeros(shape)))
        self.register_buffer("lbs_weights", avatar.lbs_weights.clone())
        self.register_buffer("lookup_at", avatar.neutral.means.clone())  # where lbs_weights and d were set
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

    @classmethod
    def from_state(cls, state: dict) -> TrainableAvatar:
        """Rebuild from :meth:`state` (a checkpoint's): any N (densification changes it)."""
        model = cls.__new__(cls)
        nn.Module.__init__(model)
        model.consistency = state["consistency"]
        model.eps, model.d_max = float(state["eps"]), float(state["d_max"])
        model.meta = dict(state["meta"])
        params = set(state["parameters"])
        for name, t in state["tensors"].items():
            if name in ("pose_correctives", "eyelid_offsets"):
                continue
            if name in params:
                model.register_parameter(name, nn.Parameter(t.clone()))
            else:
                model.register_buffer(name, t.clone())
        model.pose_correctives = state["tensors"].get("pose_correctives")
        model.eyelid_offsets = state["tensors"].get("eyelid_offsets")
        if "lookup_at" not in state["tensors"]:  # a checkpoint from before the lookup grid
            model.register_buffer("lookup_at", model.means.detach().clone())
        return model

    def state(self) -> dict:
        """Everything needed to rebuild the model (tensors, numbers, strings: loadable with weights_only=True)."""
        tensors = {k: v.detach().cpu() for k, v in self.named_parameters()}
        tensors.update({k: v.detach().cpu() for k, v in self.named_buffers()})
        if self.pose_correctives is not None:
            tensors["pose_correctives"] = self.pose_correctives.cpu()
        if self.eyelid_offsets is not None:
            tensors["eyelid_offsets"] = self.eyelid_offsets.cpu()
        return {"tensors": tensors, "parameters": [k for k, _ in self.named_parameters()],
                "consistency": self.consistency, "eps": self.eps, "d_max": self.d_max, "meta": self.meta}

    def _apply(self, fn, recurse: bool = True):
        """``.to(device)`` and the like move the pose correctives and eyelid offsets (plain attributes) too."""
        super()._apply(fn, recurse)
        for name in ("pose_correctives", "eyelid_offsets"):
            t = getattr(self, name)
            if t is not None:
                setattr(self, name, fn(t))
        return self

    # ------------------------------------------------------------------------------------------------ state
    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    @property
    def num_expressions(self) -> int:
        return int(self.meta["num_expressions"])

    def weighted(self, prop: str) -> bool:
        """Whether the residual of ``prop`` is multiplied by the consistency weights (and stored sparse)."""
        return self.consistency == "all" or (self.consistency == "positions" and prop == "means")

    def hat(self, prop: str) -> Tensor | None:
        return getattr(self, "hat_" + prop, None)

    def _cut(self, t: Tensor, prop: str, sh_coeffs: int | None, dim: int) -> Tensor:
        if prop == "sh" and sh_coeffs is not None:
            return t.narrow(dim, 0, sh_coeffs)
        return t

    def delta(self, prop: str, sh_coeffs: int | None = None) -> Tensor:
        """The effective dG of ``prop``, dense [K, N, ...] (differentiable in dG_hat); SH cut to ``sh_coeffs``."""
        init = self._cut(getattr(self, "init_" + prop), prop, sh_coeffs, 1)
        k, n = self.num_expressions, self.num_gaussians
        out = init.new_zeros(k, n, *init.shape[1:]).index_put((self.init_k, self.init_n), init)
        hat = self.hat(prop)
        if hat is None:
            return out
        if self.weighted(prop):
            hat = self._cut(hat, prop, sh_coeffs, 1)
            w = self.hat_w.reshape(-1, *([1] * (hat.dim() - 1)))
            return out.index_put((self.hat_k, self.hat_n), w * hat, accumulate=True)
        return out + self._cut(hat, prop, sh_coeffs, 2)

    def blend(self, expression: Tensor, sh_degree: int | None = None) -> Gaussians:
        """Eq. 1 with Eq. 2's deltas, sparse: B0 + sum_k psi_k (dG_init_k + c_k dG_hat_k), [B, N, ...] (raw:
        quaternions unnormalised, log-scales, logits), SH cut to ``sh_degree``. Equal (to rounding) to
        ``deform.blend(self.avatar(sh_degree), expression)`` without building the dense deltas."""
        c = sh_coeff_count(self._degree(sh_degree))
        psi = expression.to(self.means.dtype)
        b, n = psi.shape[0], self.num_gaussians
        neutral = self._neutral(c)
        init_coef = psi[:, self.init_k].t()  # [Pi, B]
        hat_coef = (psi[:, self.hat_k] * self.hat_w).t() if self.consistency != "frozen" else None  # [Ph, B]
        out = {}
        for prop in PROPS:
            base = getattr(neutral, prop)
            tail = base.shape[1:]
            ones = [1] * len(tail)
            # Work on [N, B * D] rows: index_add along dim 0 of a 2-D tensor is the fast path on the CPU.
            x = base.unsqueeze(1).expand(n, b, *tail).reshape(n, -1)
            if prop in ("means", "quats", "sh"):  # scale and opacity have no init term
                init = self._cut(getattr(self, "init_" + prop), prop, c, 1)
                src = init_coef.reshape(-1, b, *ones) * init.unsqueeze(1)
                x = add_rows(x, self.init_n, src.reshape(src.shape[0], -1))
            hat = self.hat(prop)
            if hat is not None and self.weighted(prop):
                src = hat_coef.reshape(-1, b, *ones) * self._cut(hat, prop, c, 1).unsqueeze(1)
                x = add_rows(x, self.hat_n, src.reshape(src.shape[0], -1))
            x = x.reshape(n, b, *tail).movedim(1, 0)
            if hat is not None and not self.weighted(prop):
                flat = psi @ self._cut(hat, prop, c, 2).reshape(hat.shape[0], -1)
                x = x + flat.reshape(b, *base.shape)
            out[prop] = x
        return Gaussians(**out)

    # ------------------------------------------------------------------------------------------------ views
    def _degree(self, sh_degree: int | None) -> int:
        full = self.meta["sh_degree"]
        return full if sh_degree is None else min(sh_degree, full)

    def _neutral(self, c: int, prefix: str = "", detach: bool = False) -> Gaussians:
        def t(x: Tensor) -> Tensor:
            return x.detach() if detach else x

        dc, rest = getattr(self, prefix + "sh_dc"), getattr(self, prefix + "sh_rest")
        sh = t(dc) if c == 1 else t(torch.cat([dc, rest[:, : c - 1]], dim=1))
        return Gaussians(t(getattr(self, prefix + "means")), t(getattr(self, prefix + "quats")),
                         t(getattr(self, prefix + "log_scales")), t(getattr(self, prefix + "opacity_logits")), sh)

    def avatar(self, sh_degree: int | None = None, detach: bool = False, deltas: bool = True) -> Avatar:
        """The current avatar (differentiable unless ``detach``), its SH cut to ``sh_degree`` (default: all).

        ``deltas=False`` leaves the (costly) dense deltas out: zero-stride placeholders of the right shape, for
        :func:`render_core.deform.skin` after :meth:`blend`."""
        degree = self._degree(sh_degree)
        c = sh_coeff_count(degree)
        neutral = self._neutral(c, detach=detach)
        mouth = self._neutral(c, "mouth_", detach=detach)
        k = self.num_expressions
        if deltas:
            d = Gaussians(*((self.delta(p, c).detach() if detach else self.delta(p, c)) for p in PROPS))
        else:
            d = neutral.map(lambda x: x.detach().new_zeros(()).expand(k, *x.shape))
        m = self.meta
        return Avatar(
            neutral=neutral, deltas=d, lbs_weights=self.lbs_weights, joint_positions=self.joint_positions,
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
        av = replace(av, neutral=av.neutral.map(torch.Tensor.clone), mouth=av.mouth.map(torch.Tensor.clone),
                     lbs_weights=av.lbs_weights.clone(), joint_positions=av.joint_positions.clone(),
                     mouth_group=av.mouth_group.clone())
        if provenance:
            av.provenance = {**av.provenance, **provenance}
        av.validate()
        return av
