"""Gaussians: the per-Gaussian properties every part of the library passes around (docs/method.md section 1).

Its own module, below both :mod:`render_core.packed` (the stored layout, which unpacks into Gaussians) and
:mod:`render_core.avatar` (the model, which holds Gaussians and packed deltas), so the dependency goes one way:
avatar -> packed -> gaussians. ``render_core.avatar`` re-exports the class.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

from torch import Tensor

from .errors import ShapeError


@dataclass
class Gaussians:
    """Per-Gaussian properties, with any leading dims (``[..., N, ...]``).

    Conventions: quaternions w-first (not necessarily normalised), scales as log-scales, opacity as a logit,
    SH coefficients ``[..., N, (D+1)^2, 3]`` with the DC term first.
    """

    means: Tensor  # [..., N, 3]
    quats: Tensor  # [..., N, 4] wxyz
    log_scales: Tensor  # [..., N, 3]
    opacity_logits: Tensor  # [..., N]
    sh: Tensor  # [..., N, C, 3]

    @property
    def count(self) -> int:
        return int(self.means.shape[-2])

    def tensors(self) -> dict[str, Tensor]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def map(self, fn) -> Gaussians:
        """A new set with ``fn`` applied to every tensor."""
        return Gaussians(**{k: fn(v) for k, v in self.tensors().items()})

    def check(self, name: str, lead: tuple[int, ...] = ()) -> None:
        """Raise ShapeError unless the tensors agree on the leading dims ``lead`` and N."""
        n = self.means.shape[len(lead)] if self.means.dim() > len(lead) else -1
        c = self.sh.shape[-2] if self.sh.dim() >= 2 else -1
        want = {
            "means": (*lead, n, 3),
            "quats": (*lead, n, 4),
            "log_scales": (*lead, n, 3),
            "opacity_logits": (*lead, n),
            "sh": (*lead, n, c, 3),
        }
        for key, shape in want.items():
            got = tuple(getattr(self, key).shape)
            if got != shape:
                raise ShapeError(f"expected shape {list(shape)}, got {list(got)}", field=f"{name}.{key}")
        if c not in (1, 4, 9, 16):
            raise ShapeError(f"SH coefficient count must be 1, 4, 9 or 16, got {c}", field=f"{name}.sh")
