"""Per-frame head poses refined with the avatar (``Preset.refine_poses``; docs/method.md section 6).

A tracked video's poses carry the tracker's error, about a pixel on a phone video or a ``blendsplat track`` of one
(docs/method.md section 13), and the avatar cannot fit frames that disagree with each other: trained on such a
tracking it blurs. So each training frame gets a small rigid correction of its head, a rotation ``w`` about the
head's centre and a translation ``u`` (:func:`render_core.evaluation.align.moved_splats`, which folds exactly into
the frame's camera), learnt with the avatar from ``refine_poses_from`` on.

Each frame is seen only when its iteration draws it (about iterations / frames times), so its correction has an
Adam state of its own that moves only when the frame is drawn (a shared Adam would keep moving every unseen row on
its momentum), and a weak prior ``POSE_PRIOR |(w, u)|^2`` keeps the corrections from drifting together with the
avatar (the world frame is the tracker's).

With ``expressions`` (``Preset.refine_expressions``, ``train --refine-expressions``) each frame also gets a
correction ``de`` of its expression coefficients, under ``EXPRESSION_PRIOR |de|^2`` (the tracker's expressions
remain the avatar's vocabulary: the avatar is driven by the tracker's coefficients at run time): a blink the tracker
missed or a smile it underestimated in one frame no longer has to be explained by the avatar's blendshapes.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ..camera import Cameras
from ..deform import Frame
from ..evaluation.align import EXPRESSION_LR, EXPRESSION_PRIOR, ROTATION_LR, TRANSLATION_LR, moved_camera

BETAS = (0.9, 0.999)
EPS = 1e-8
POSE_PRIOR = 1e-3  # per unit of radians^2 and (metres x 10)^2, against the mean L1 image residual


def corrected(frame: Frame, row: Tensor) -> tuple[Frame, tuple[Tensor, Tensor]]:
    """One frame with its correction ``row [1, 6 (+ K)]`` (a row of :attr:`FramePoses.wu`): the frame with its
    expressions corrected (when the row has them) and its motion (w [1, 3], u [1, 3]) for moved_splats."""
    expression = frame.expression + row[:, 6:].to(frame.expression) if row.shape[1] > 6 else frame.expression
    return Frame(expression, frame.joint_rotations, frame.eyelids), (row[:, :3], row[:, 3:6])


class FramePoses:
    """Rigid corrections ``(w, u)`` of F frames' head poses and, with ``expressions`` K > 0, corrections of their
    K expression coefficients (``wu [F, 6 + K]``), each frame with its own Adam step count."""

    # lr_scale: x the test-time alignment's learning rates. 2.0 (was 0.5): held-out head PSNR of `blendsplat track`'s
    # output trained with --refine-expressions (data synth seed 257, tiny): 26.48 -> 27.00 dB at 1500 iterations,
    # 26.82 -> 27.63 at 3000; seed 311: 27.06 -> 27.10 at 1500; the training frames' fit unchanged
    def __init__(self, frames: int, lr_scale: float = 2.0, device: torch.device | str = "cpu", expressions: int = 0):
        width = 6 + expressions
        self.expressions = expressions
        self.wu = torch.zeros(frames, width, device=device)
        self.m = torch.zeros(frames, width, device=device)
        self.v = torch.zeros(frames, width, device=device)
        self.steps = torch.zeros(frames, dtype=torch.int64)
        self.lr = torch.tensor([ROTATION_LR] * 3 + [TRANSLATION_LR] * 3 + [EXPRESSION_LR] * expressions,
                               device=device) * lr_scale

    def __len__(self) -> int:
        return len(self.wu)

    def motion(self, j: int) -> tuple[Tensor, Tensor]:
        """(w [1, 3], u [1, 3]) of frame j, differentiable: pass them to moved_splats, then :meth:`step`."""
        wu = self.wu[j:j + 1].clone().requires_grad_(True)
        self._leaf = (j, wu)
        return wu[:, :3], wu[:, 3:6]

    def expression(self, expression: Tensor) -> Tensor:
        """``expression [1, K]`` of the frame last given by :meth:`motion` with its correction (differentiable);
        unchanged without expression corrections."""
        if not self.expressions:
            return expression
        return expression + self._leaf[1][:, 6:].to(expression)

    def applied(self, j: int, frame: Frame) -> tuple[Frame, tuple[Tensor, Tensor]]:
        """Frame j (``frame``, one frame) as training renders it now, not differentiable (:func:`corrected`)."""
        return corrected(frame, self.wu[j:j + 1])

    def prior(self) -> Tensor:
        """The prior on the frame last given by :meth:`motion` (add it to the loss)."""
        _, wu = self._leaf
        scaled = torch.cat([wu[:, :3], wu[:, 3:6] * 10.0], -1)
        return POSE_PRIOR * scaled.square().sum() + EXPRESSION_PRIOR * wu[:, 6:].square().sum()

    @torch.no_grad()
    def step(self, scale: float = 1.0) -> None:
        """One Adam step of the frame last given by :meth:`motion`, from its gradient, at ``scale`` x the learning
        rates."""
        j, wu = self._leaf
        if wu.grad is None:
            return
        g = wu.grad[0]
        self.steps[j] += 1
        t = int(self.steps[j])
        self.m[j] = BETAS[0] * self.m[j] + (1 - BETAS[0]) * g
        self.v[j] = BETAS[1] * self.v[j] + (1 - BETAS[1]) * g * g
        m_hat = self.m[j] / (1 - BETAS[0] ** t)
        v_hat = self.v[j] / (1 - BETAS[1] ** t)
        self.wu[j] -= (scale * self.lr) * m_hat / (v_hat.sqrt() + EPS)

    def state(self) -> dict:
        return {"wu": self.wu.clone(), "m": self.m.clone(), "v": self.v.clone(), "steps": self.steps.clone()}

    def load_state(self, state: dict) -> None:
        for name in ("wu", "m", "v", "steps"):
            value = state[name]
            if value.shape != getattr(self, name).shape:
                raise ValueError(f"pose state {name}: {list(value.shape)}, expected {list(getattr(self, name).shape)}")
            setattr(self, name, value.to(getattr(self, name).device).clone())

    def cameras(self, cams: Cameras, centres: Tensor) -> tuple[np.ndarray, np.ndarray]:
        """The F frames' cameras with their corrections folded in (``centres`` [F, 3]: each frame's head centre,
        the pivot the corrections turned about): (R [F, 3, 3], t [F, 3])."""
        R, t = moved_camera(cams, self.wu[:, :3], self.wu[:, 3:6], centres)
        return R.cpu().numpy(), t.cpu().numpy()

    def summary(self) -> dict:
        """The corrections' size over the frames: median and largest rotation (degrees) and translation (mm)."""
        deg = torch.rad2deg(self.wu[:, :3].norm(dim=1)).cpu()
        mm = (self.wu[:, 3:6].norm(dim=1) * 1e3).cpu()
        out = {"frames": len(self), "rotation_deg": {"median": round(float(deg.median()), 3),
                                                     "max": round(float(deg.max()), 3)},
               "translation_mm": {"median": round(float(mm.median()), 3), "max": round(float(mm.max()), 3)}}
        if self.expressions:
            de = self.wu[:, 6:].abs().cpu()
            out["expression"] = {"mean_abs": round(float(de.mean()), 4), "max": round(float(de.max()), 4)}
        return out
