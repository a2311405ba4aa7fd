"""Stage 3: the open head fitted to the landmarks - focal length, then per frame head pose and 52 expressions.

The points: :mod:`.correspond`'s fixed correspondence (MediaPipe points on the stable face, outline excluded, and
both iris centres) - each a barycentric point of the open head's surface, so with the joints at rest (the format
``data synth`` writes for the open head: the jaw is ``jawOpen``, the gaze ``eyeLook*``, blinks ``eyeBlink*``) a
point is LINEAR in the expressions: ``X(e) = T + d(r) + (B + D) e``, with the calibrated offsets of
:mod:`.calibrate` (``d(r)``: where MediaPipe puts the point at the head's rotation r; ``D``: how much more it moves
with each expression; ``d`` is evaluated at the current rotation each iteration and held constant in the Jacobian).
The head's pose lives in the camera, as the tracked-video
format has it: ``x = K (R X + t)`` with ``R = R0 Rh(r)`` (R0 the front view, Rh the head's rotation, axis-angle r).

Identity: the open head has no shape basis, so the template is kept (and the tracked-video format has no identity
offsets yet): a face of another shape than the template leaves its difference in the expressions and the residual.

Per frame, p = (r, t, e) (58 numbers) is solved by Gauss-Newton (a small fixed damping), batched over all
frames with torch (an analytic [N, 2L, 58] Jacobian per iteration; rotation steps on the right, Rh exp(d)): the
residuals are the reprojection errors in pixels (Huber weights by IRLS, so a few wild points - e.g. eye corners
through a blink - do not pull the fit), plus ``expression_weight`` x |e|^2, plus ``smooth`` x
|p_i - (p_{i-1} + p_{i+1}) / 2|^2 (temporal smoothing, the neighbours held at their last values: a Jacobi
step), e clamped to [0, 1] after each step. The focal
length (principal point: the image centre, or the crop's image of the frame centre) is found first, on up to
``keyframes`` frames spread over the video: a golden-section search on log f of the keyframes' error after a rigid
fit (:func:`search_focal`). A neutral head fitted rigidly to a face that smiles or raises its brows misfits, and
that misfit biases the search's focal length low (by 13% on average on the known-answer videos at 256 px), so once
all frames are fitted the search is run again (within 0.7-1.5x of the first) with each keyframe's fitted
expressions held, the frames' depths scaled with it and 4 more Gauss-Newton steps taken: the focal length 0.87 ->
0.96 of the truth (seeds 257, 311, 223 at 256 px), 0.88 -> 0.97 at 512 (223, 311, 602).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..rotation import matrix_to_quat
from .correspond import Correspondence, load_correspondence

R0 = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))  # the front view (camera on +z, y down)
EXPRESSION_WEIGHT = 100.0  # px^2 per unit^2 of an expression (measured best of 20, 100, 300 on held-out seeds)
P = 58  # per-frame parameters: rotation 3, translation 3, expressions 52


@dataclass
class FitResult:
    """Per frame: ``R [N, 3, 3]``, ``t [N, 3]``, ``expression [N, 52]``; ``K [3, 3]`` shared; ``reprojection_px
    [N]`` the median pixel error of each frame's points; ``focal_search`` the (focal, error) pairs tried."""

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    expression: np.ndarray
    reprojection_px: np.ndarray
    focal_search: list[tuple[float, float]]


def rodrigues(r: torch.Tensor) -> torch.Tensor:
    """Axis-angle ``[..., 3]`` -> rotation matrices ``[..., 3, 3]`` (smooth at 0, for jacfwd)."""
    theta2 = (r * r).sum(-1, keepdim=True)[..., None]
    theta = torch.sqrt(theta2 + 1e-24)
    x, y, z = r.unbind(-1)
    o = torch.zeros_like(x)
    k = torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).reshape(r.shape[:-1] + (3, 3))
    small = theta2 < 1e-12
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / (theta2 + 1e-30))
    eye = torch.eye(3, dtype=r.dtype).expand(k.shape)
    return eye + a * k + b * (k @ k)


class Problem:
    """The linear point model of the open head (module docstring) and the landmark observations."""

    def __init__(self, model, corr: Correspondence | None = None):
        corr = corr or load_correspondence()
        self.corr = corr
        dtype = torch.float64
        self.T = corr.points(model.template.to(dtype))  # [L, 3]
        self.B = corr.points(model.expression_basis.to(dtype))  # [52, L, 3]
        if corr.offsets is not None and corr.offsets.shape[-1] == 4 + self.B.shape[0]:
            self.B = self.B + corr.basis_correction(dtype)  # where MediaPipe puts the landmark (:mod:`.calibrate`)
        self.Bt = self.B.permute(1, 2, 0).contiguous()  # [L, 3, 52]: the basis as the Jacobian reads it
        self.L = self.T.shape[0]
        self.landmarks = torch.from_numpy(corr.landmarks)

    def anchors(self, rotation: torch.Tensor) -> torch.Tensor:
        """The points at rest, moved by the correspondence's calibrated offsets at each frame's head rotation
        (axis-angle ``[N, 3]``) -> ``[N, L, 3]``."""
        return self.corr.anchors(self.T, rotation)

    def observations(self, landmarks: np.ndarray, iris: np.ndarray) -> torch.Tensor:
        """``landmarks [N, 468, 3]`` and ``iris [N, 2, 5, 3]`` -> the observed points ``[N, L, 2]``."""
        both = np.concatenate([landmarks[..., :2], iris[:, :, 0, :2]], 1)
        return torch.from_numpy(both[:, self.corr.landmarks].astype(np.float64))

    def project(self, p: torch.Tensor, f: float, c: torch.Tensor) -> torch.Tensor:
        """Parameters ``[N, 58]`` -> projected points ``[N, L, 2]``."""
        R = R0 @ rodrigues(p[..., :3])
        X = self.anchors(p[:, :3]) + torch.einsum("...k,klc->...lc", p[..., 6:], self.B)
        Xc = X @ R.transpose(-1, -2) + p[..., None, 3:6]
        return f * Xc[..., :2] / Xc[..., 2:3] + c

    def initial(self, obs: torch.Tensor, f: float, c: torch.Tensor) -> torch.Tensor:
        """A frontal pose at the depth and place that match each frame's points' spread and centre."""
        n = obs.shape[0]
        p = torch.zeros(n, P, dtype=torch.float64)
        centre3 = self.T.mean(0)
        spread3 = (self.T[:, :2] - centre3[:2]).norm(dim=-1).mean()
        centre2 = obs.mean(1)
        spread2 = (obs - centre2[:, None]).norm(dim=-1).mean(1)
        depth = f * spread3 / spread2
        p[:, 3:6] = -(R0 @ centre3)
        p[:, 5] += depth
        p[:, 3] += (centre2[:, 0] - c[0]) * depth / f
        p[:, 4] += (centre2[:, 1] - c[1]) * depth / f
        return p


def matrix_to_axis_angle(m: torch.Tensor) -> torch.Tensor:
    q = matrix_to_quat(m)
    q = torch.where(q[..., :1] < 0, -q, q)  # w >= 0: the angle in [0, pi]
    v = q[..., 1:]
    s = v.norm(dim=-1, keepdim=True)
    angle = 2 * torch.atan2(s, q[..., :1])
    return v * torch.where(s > 1e-12, angle / s.clamp_min(1e-12), torch.full_like(s, 2.0))


def projection(Xc: torch.Tensor, f: float, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera points ``[N, M, 3]`` -> pixels ``[N, M, 2]`` and d(pixels)/d(camera point) ``[N, M, 2, 3]``
    (``f / z [[1, 0, -x/z], [0, 1, -y/z]]``)."""
    z = Xc[..., 2:3]
    dU = torch.zeros(Xc.shape[:-1] + (2, 3), dtype=Xc.dtype)
    dU[..., 0, 0] = dU[..., 1, 1] = f / z[..., 0]
    dU[..., :, 2] = -f * Xc[..., :2] / (z * z)
    return f * Xc[..., :2] / z + c, dU


def jacobian(dU: torch.Tensor, R: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """The reprojection's Jacobian in the pose ``[N, L, C, 6]``: rotation (a step on the right), then translation;
    ``dU [N, L, C, 3]`` = d(u, v)/d(camera point) (C = 2; 1 for a scalar of the point), ``X [N, L, 3]`` the points
    (head coordinates)."""
    return _pose_jacobian(dU, _head_derivative(dU, R), X)


def _head_derivative(dU: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """d(u, v)/d(head point) = ``dU R`` ``[N, L, C, 3]``: one [C L, 3] @ [3, 3] product per frame (the N L products
    of [C, 3] @ [3, 3] were 1.7x slower)."""
    return (dU.reshape(dU.shape[0], -1, 3) @ R).view_as(dU)


def _pose_jacobian(dU: torch.Tensor, dUR: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """:func:`jacobian` from ``dU`` and ``dUR`` (:func:`_head_derivative`): the rotation block, ``-dU R [X]x``, is
    ``X x (dU R)`` row by row."""
    return torch.cat([torch.linalg.cross(X.unsqueeze(-2).expand_as(dUR), dUR, dim=-1), dU], -1)


def normal_equations(dU: torch.Tensor, R: torch.Tensor, X: torch.Tensor, Bt: torch.Tensor | None, w: torch.Tensor,
                     r: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The weighted least squares' normal equations of the reprojection, ``J^T W J [N, A, A]`` and ``J^T W r [N, A,
    1]`` (float64), for weights ``w [N, L]`` and residuals ``r [N, L, 2]``: the pose (:func:`jacobian`) and, with
    ``Bt [L, 3, K]``, the expressions (A = 6 + K). ``sqrt(W) J`` is built in float32 (J is linear in ``dU``, so the
    weights scale ``dU`` first) and written once into one ``[N, 2L, A]`` buffer; its expression block is one matrix
    product per landmark over all frames (``[2N, 3] @ [3, K]``: N x L products of ``[2, 3] @ [3, K]`` were 4x
    slower). Most of a Gauss-Newton step is this: 4-5x faster than the float64 Jacobian concatenated then
    converted for the product (measured: 150 frames, 430 points); the known answer is unchanged."""
    n, L = dU.shape[:2]
    sw = w.sqrt()[..., None, None]
    dUw = (dU * sw).float()
    dURw = _head_derivative(dUw, R.float())
    J = torch.empty(n, L, 2, 6 + (0 if Bt is None else Bt.shape[-1]), dtype=torch.float32)
    J[..., :6] = _pose_jacobian(dUw, dURw, X.float())
    if Bt is not None:
        per_landmark = dURw.permute(1, 0, 2, 3).reshape(L, 2 * n, 3) @ Bt.float()  # [L, 2N, K]
        J[..., 6:] = per_landmark.view(L, n, 2, -1).permute(1, 0, 2, 3)
    J = J.view(n, 2 * L, -1)
    Jt = J.transpose(1, 2)
    return (Jt @ J).double(), (Jt @ (r * sw[..., 0]).float().reshape(n, -1, 1)).double()


def solve(problem: Problem, obs: torch.Tensor, f: float, c: torch.Tensor, p: torch.Tensor | None = None,
          iterations: int = 12, expressions: bool = True, expression_weight: float = EXPRESSION_WEIGHT,
          smooth: float = 0.0, huber_px: float = 1.5,
          weights: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Gauss-Newton / LM over all frames (module docstring); returns (p [N, 58], per-point pixel errors [N, L]).
    The rotation steps are increments on the right (Rh <- Rh exp(d)); the Jacobian is analytic."""
    p = problem.initial(obs, f, c) if p is None else p.clone()
    n, L = obs.shape[:2]
    w_pts = torch.ones(L, dtype=torch.float64) if weights is None else weights
    active = P if expressions else 6
    reg = torch.zeros(P, dtype=torch.float64)
    reg[6:] = expression_weight
    eye = torch.eye(active, dtype=torch.float64)
    Rh = rodrigues(p[:, :3])
    for _ in range(iterations):
        R = R0 @ Rh  # [N, 3, 3]
        X = problem.anchors(p[:, :3]) + torch.einsum("nk,klc->nlc", p[:, 6:], problem.B)  # [N, L, 3]
        u, dU = projection(X @ R.transpose(1, 2) + p[:, None, 3:6], f, c)
        r = u - obs  # [N, L, 2]
        err = r.norm(dim=-1)
        w = w_pts * torch.clamp(huber_px / err.clamp_min(1e-9), max=1.0)  # IRLS Huber weights [N, L]
        H, g = normal_equations(dU, R, X, problem.Bt if active > 6 else None, w, r)
        q = p[:, :active]
        H = H + torch.diag(reg[:active]) + 1e-6 * eye
        g = g + (reg[:active] * q)[..., None]
        g[:, :3] -= (reg[:3] * q[:, :3])[..., None]
        if smooth > 0 and n > 2:
            nb = q.clone()
            nb[1:-1] = (q[:-2] + q[2:]) / 2
            nb[0], nb[-1] = q[1], q[-2]
            H = H + smooth * eye
            g = g + smooth * (q - nb)[..., None]
        step = torch.linalg.solve(H, -g)[..., 0]
        Rh = Rh @ rodrigues(step[:, :3])
        p[:, 3:active] = q[:, 3:] + step[:, 3:]
        p[:, :3] = matrix_to_axis_angle(Rh)
        if active > 6:
            p[:, 6:] = p[:, 6:].clamp(0.0, 1.0)
    err = (problem.project(p, f, c) - obs).norm(dim=-1)
    return p, err


def search_focal(problem: Problem, obs: torch.Tensor, c: torch.Tensor, size: int,
                 lo: float = 0.6, hi: float = 6.0, steps: int = 8,
                 expressions: torch.Tensor | None = None) -> tuple[float, list[tuple[float, float]]]:
    """The focal length (pixels) minimising the keyframes' mean error after a rigid fit (pose only: expressions
    free to move would absorb the perspective that tells focal lengths apart - measured: 5-30% off, against 8-10%
    rigid): golden section on log f over [lo, hi] x ``size``. ``expressions [N, 52]``: the keyframes' expressions,
    held (default: the neutral face)."""
    tried = []

    def cost(logf: float) -> float:
        f = math.exp(logf)
        p = problem.initial(obs, f, c)
        if expressions is not None:
            p[:, 6:] = expressions
        _, err = solve(problem, obs, f, c, p, iterations=8, expressions=False)
        value = float(err.mean())
        tried.append((round(f, 2), round(value, 4)))
        return value

    a, b = math.log(lo * size), math.log(hi * size)
    g = (math.sqrt(5) - 1) / 2
    x1, x2 = b - g * (b - a), a + g * (b - a)
    f1, f2 = cost(x1), cost(x2)
    for _ in range(steps):
        if f1 < f2:
            b, x2, f2 = x2, x1, f1
            x1 = b - g * (b - a)
            f1 = cost(x1)
        else:
            a, x1, f1 = x1, x2, f2
            x2 = a + g * (b - a)
            f2 = cost(x2)
    return math.exp((a + b) / 2), tried


def fit_frames(model, landmarks: np.ndarray, iris: np.ndarray, width: int, height: int,
               principal: tuple[float, float] | None = None, focal: float | None = None, keyframes: int = 12,
               smooth: float = 0.5, expression_weight: float = EXPRESSION_WEIGHT,
               threads: int | None = None) -> FitResult:
    """Fit N frames' landmarks (``[N, 468, 3]``, ``iris [N, 2, 5, 3]``, pixels of a ``width`` x ``height`` image):
    module docstring. ``principal``: default the image centre; ``focal``: given, or searched on the keyframes."""
    from ..data.generate import torch_threads

    with torch_threads(threads):
        problem = Problem(model)
        obs = problem.observations(landmarks, iris)
        c = torch.tensor(principal if principal is not None else (width / 2, height / 2), dtype=torch.float64)
        tried: list[tuple[float, float]] = []
        search = focal is None
        if search:
            n = obs.shape[0]
            keys = np.unique(np.round(np.linspace(0, n - 1, min(keyframes, n))).astype(np.int64))
            focal, tried = search_focal(problem, obs[keys], c, max(width, height))
        rigid, _ = solve(problem, obs, focal, c, iterations=6, expressions=False)
        p, err = solve(problem, obs, focal, c, rigid, iterations=6, smooth=smooth,
                       expression_weight=expression_weight)
        if search:  # again with the fitted expressions held: the neutral face's misfit biases f low (module doc)
            again, more = search_focal(problem, obs[keys], c, max(width, height), lo=0.7 * focal / max(width, height),
                                       hi=1.5 * focal / max(width, height), expressions=p[keys, 6:])
            tried += more
            p[:, 3:6] *= again / focal  # the head as far away as the new focal length sees it the same size
            focal = again
            p, err = solve(problem, obs, focal, c, p, iterations=4, smooth=smooth,
                           expression_weight=expression_weight)
    R = (R0 @ rodrigues(p[:, :3])).numpy()
    K = np.array([[focal, 0.0, float(c[0])], [0.0, focal, float(c[1])], [0.0, 0.0, 1.0]])
    return FitResult(K, R, p[:, 3:6].numpy(), p[:, 6:].numpy(), err.median(1).values.numpy(), tried)
