"""Stage 3b: the head's pose refined against the video's own pixels (direct alignment), after the landmark fit.

A landmark detector's points carry a bias of their own: on the known-answer videos the landmark fit's head rotation
is off by 1.5-2.5 degrees, mostly a per-video offset that follows the face's appearance (freckles, skin tone, brows)
and so cannot be calibrated away. The skin itself is a better witness: a point of the forehead, temple or cheek has
one colour in every frame where it is seen. So, per chunk of frames (:data:`CHUNK`, bounded memory), in
:data:`PASSES` passes over the video:

- the points: :data:`POINTS` skin vertices of the open head that the expressions move by less than
  :data:`MAX_EXPRESSION_MM` (forehead, temples, nose, upper cheeks, ears, scalp; eyes, lips and jaw left out), each
  posed with the frame's fitted expressions (held fixed here) and seen where its normal faces the camera at all
  (:data:`MIN_FACING`: the grazing points near the head's outline say the most about its rotation);
- their colour: the mean grey level over the frames that see it (at least :data:`MIN_VIEWS`), re-estimated at each
  pyramid level with the poses of that moment: on the first pass over the chunk's frames and those of the chunks
  before it, on the second over the whole video (the other chunks' sums kept from the first pass: a colour from
  more views and head turns; one chunk of 75 frames alone was 0.25 px worse than one of 150);
- the poses: Gauss-Newton on each frame's 6 pose parameters (rotation on the right, translation), coarse to fine
  over a 3-level image pyramid (:data:`SCHEDULE`), minimising ``PHOTOMETRIC_WEIGHT`` x (grey level - the point's
  colour)^2 (Huber at :data:`HUBER_GREY`) plus the landmark residuals of :mod:`.fit` (Huber at 1.5 px), which keep
  the fit where the pixels say little. The image gradient (central differences of one pixel of the level, sampled
  at the points only) gives the Jacobian.

Measured (the known-answer videos of ``data synth``, 512x512, 150 frames, seeds outside the calibration's): the
landmark fit's median head rotation error 1.5-2.5 -> 0.3-1.9 degrees with one pass and points facing the camera by
cos > 0.3 (median vertex error 2.1-2.9 -> 0.9-2.3 px); then, seeds 223, 311, 412, 523 and 602, mean vertex error
1.70 -> 1.31 px and rotation 1.05 -> 0.63 degrees with two passes and every point facing the camera (seeds 257, 777
and 888, held out of that choice: 1.87 -> 1.39 px, 0.99 -> 0.60 degrees); a third pass gave 1.25 px. About 1 s
per pass per 150 frames on 2 cores.

Then one more pass (:data:`EXPRESSION_PASSES`) refines each frame's pose and expressions together: the points are
:data:`EXPRESSION_POINTS` skin vertices the expressions DO move (brows, lids, cheeks, lips, chin) beside
:data:`EXPRESSION_RIGID` of the still ones, each posed with the frame's expressions as they stand (``X = T + B e``),
the Jacobian of a grey level with respect to an expression ``dG R B_k`` (:func:`pixel_jacobian`), the landmark fit's
residuals and its prior on the expressions (``EXPRESSION_WEIGHT``), the coefficients clamped to [0, 1], and a
shorter schedule (:data:`EXPRESSION_SCHEDULE`). The pixels weigh :data:`EXPRESSION_PIXEL_WEIGHT` here, a hundredth
of their weight in the pose passes (at 1e4 the 52 coefficients chase the H.264 noise: on seed 257 at 256 px their
error rose 0.85 -> 1.27 mm where 1e3 lowered it to 0.64).
The gaze (``eyeLook*``) stays the landmark fit's: the eyeballs are not among the points, and the irises say more.
On the known-answer videos at 256 px (seeds 257, 311, 223) the expressions' error (the mean distance by which they
move the head's vertices away from the truth's, ``known_answer``'s ``mean_expression_mm``) 0.81 -> 0.62 mm, their
correlation with the truth's (mean over the coefficients that vary) 0.34 -> 0.56, the median vertex error 0.76 ->
0.63 px, the head rotation 0.84 -> 0.85 deg; at 512 px (seeds 223, 311) 0.84 -> 0.82 mm, 0.34 -> 0.52, 1.41 -> 1.29
px, 0.64 -> 0.80 deg.

The focal length is refined too: at the end of each pose pass the pixels' and landmarks' Gauss-Newton terms of log
f, with every frame's pose free (:func:`marginal`, the Schur complement, per chunk at its last step), summed over
the chunks, give one step on log f (at most :data:`FOCAL_STEP`); every frame's translation is scaled with it so the
next pass starts from the same image. The colours, shared by the frames too, are not marginalised, so the step is a
little short: about +1-3% a pass toward the truth on the known-answer videos. With the second landmark search
(:mod:`.fit`), seeds 257, 311, 223 at 256 px: median vertex error 0.638 -> 0.571 px, head rotation 0.86 -> 0.66
deg, focal length 0.87 -> 0.98 of the truth (the TRUE focal length: 0.566 px, 0.655 deg); at 512 px (223, 311,
602) 1.40 -> 1.32 px, 0.94 -> 0.80 deg (the second search alone: 1.34 px, 0.82 deg). ``track --focal`` keeps a
known focal length.

Limits: it assumes a point's brightness stays put through the video (shading that moves with the head, as ``data
synth`` renders it, or soft, even light); a strong light fixed in the room while the head turns breaks that, and
the Huber weights then leave the landmarks in charge. Hair and the neck are not on the open head and are not used.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np
import torch
import torch.nn.functional as nnf

from .fit import (
    EXPRESSION_WEIGHT,
    R0,
    FitResult,
    Problem,
    jacobian,
    matrix_to_axis_angle,
    normal_equations,
    projection,
    rodrigues,
)
from .geometry import box_shrink

PASSES = 2
EXPRESSION_PASSES = 1
EXPRESSION_POINTS = 2000
EXPRESSION_RIGID = 500
EXPRESSION_PIXEL_WEIGHT = 1e3
CHUNK = 96  # frames refined together (their colours shared): ~130 MB of float32 image pyramid
POINTS = 1500
MAX_EXPRESSION_MM = 2.0
MIN_VIEWS = 3
MIN_FACING = 0.0  # cos of the angle between a point's normal and the ray to the camera: facing it at all
PHOTOMETRIC_WEIGHT = 1e5  # px^2 per grey level^2 (0-1): a 0.01 grey error weighs as a 3 px landmark error
HUBER_GREY = 0.05
SCHEDULE = ((2, 3), (1, 3), (0, 3))  # (pyramid level, Gauss-Newton steps), coarse to fine
EXPRESSION_SCHEDULE = ((1, 2), (0, 2))
GREY = (0.299, 0.587, 0.114)


def grey(rgb: np.ndarray) -> np.ndarray:
    """uint8 RGB ``[..., 3]`` -> the grey level ``[...]`` in [0, 1] (float32)."""
    return (rgb.astype(np.float32) @ np.array(GREY, np.float32)) / 255.0


def rigid_points(model, count: int = POINTS, moving: bool = False) -> torch.Tensor:
    """The indices of up to ``count`` skin vertices that the expressions hardly move (module docstring), or with
    ``moving`` those they move more; a fixed, seeded choice so that a run is repeatable."""
    disp = model.expression_basis.double().norm(dim=-1).amax(0)
    skin = torch.ones(model.num_vertices, dtype=torch.bool)
    for group in ("eyeball_l", "eyeball_r", "teeth_upper", "teeth_lower", "tongue"):
        if group in model.vertex_groups:
            skin[model.vertex_groups[group]] = False
    still = disp < MAX_EXPRESSION_MM / 1000
    idx = torch.nonzero(skin & (~still if moving else still))[:, 0]
    if len(idx) > count:
        idx = idx[torch.randperm(len(idx), generator=torch.Generator().manual_seed(0))[:count]]
    return idx


def _pyramid(images: torch.Tensor, levels: int) -> list[torch.Tensor]:
    """``[N, 1, H, W]`` -> the image at each level ``[N, 1, H / 2^l, W / 2^l]`` (2x2 means)."""
    out = [images]
    for _ in range(levels - 1):
        out.append(box_shrink(out[-1], 2))
    return out


# where each point is sampled: itself, then +-1 pixel of the level in x and in y (the central differences)
_TAPS = torch.tensor([[0.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])


def _sample(image: torch.Tensor, u: torch.Tensor, scale: int) -> torch.Tensor:
    """The grey level and its gradient (per full-resolution pixel) at the points ``u [N, M, 2]`` (full-resolution
    pixels) of a pyramid level whose pixels are ``scale`` wide: ``[N, M, 3]``."""
    H, W = image.shape[-2] * scale, image.shape[-1] * scale
    at = u[:, None] + scale * _TAPS[None, :, None]  # [N, 5, M, 2]
    grid = at * torch.tensor([2.0 / W, 2.0 / H]) - 1
    v = nnf.grid_sample(image, grid, align_corners=False)[:, 0]  # [N, 5, M]
    return torch.stack([v[:, 0], (v[:, 1] - v[:, 2]) / (2 * scale), (v[:, 3] - v[:, 4]) / (2 * scale)], -1)


def refined_expressions(model) -> torch.Tensor:
    """The indices of the expressions the pixels refine: all but the gaze (``eyeLook*``: the eyeballs are not among
    the points, and the irises of the landmark fit say more of it)."""
    return torch.tensor([k for k, name in enumerate(model.expression_names) if not name.startswith("eyeLook")],
                        dtype=torch.int64)


def pixel_jacobian(dG: torch.Tensor, R: torch.Tensor, X: torch.Tensor, B: torch.Tensor | None = None) -> torch.Tensor:
    """The grey levels' Jacobian ``[N, M, 6 (+ K)]`` from their gradient with respect to the camera-space points
    ``dG [N, M, 1, 3]``: the pose block (:func:`.fit.jacobian`: rotation on the right, translation) and, with the
    points' expression basis ``B [K, M, 3]``, the expressions' (``dG R B_k``: the points move by ``B_k`` in the
    head's frame)."""
    if B is None:
        return jacobian(dG, R, X)[:, :, 0]
    J = dG.new_empty(dG.shape[0], dG.shape[1], 6 + B.shape[0])
    J[..., :6] = jacobian(dG, R, X)[:, :, 0]
    a = dG[:, :, 0] @ R  # [N, M, 3]: d(grey)/d(head-frame point)
    Bm = B.permute(2, 1, 0)  # [3, M, K]
    torch.mul(a[..., 0:1], Bm[0], out=J[..., 6:])  # a sum over the 3 axes, without an [N, M, K, 3] product
    J[..., 6:].addcmul_(a[..., 1:2], Bm[1]).addcmul_(a[..., 2:3], Bm[2])
    return J


def refine_chunk(problem: Problem, model, p: torch.Tensor, obs: torch.Tensor, images: np.ndarray, f: float,
                 c: torch.Tensor, points: torch.Tensor, others: torch.Tensor | None = None, expressions: bool = False,
                 focal: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """One chunk: ``p [N, 58]`` (rotation, translation, expressions, as :func:`.fit.solve` has them), its landmark
    observations ``obs [N, L, 2]`` and grey frames ``images [N, H, W]`` -> (``p`` refined, the
    chunk's colour sums ``[levels, 2, M]``: per pyramid level, each point's summed grey level and its views, with the
    poses at the level's start). ``others``: such sums of other frames, added to the chunk's own for the colours.
    The pixel terms are computed in float32 (2x faster than float64; the poses agree to 1e-5), the steps in
    float64. ``expressions``: the 52 expressions are refined too (the points then include ones they move; their
    Jacobian through the basis, the landmark fit's prior and [0, 1] bounds), else they are held. ``focal``: the
    third value is the chunk's :func:`marginal` terms of log f at its last step (else None); ``f`` itself stays."""
    n, H, W = images.shape
    shared = None
    schedule = EXPRESSION_SCHEDULE if expressions else SCHEDULE
    levels = _pyramid(torch.from_numpy(images)[:, None], max(level for level, _ in schedule) + 1)
    normals = _normals(model)[points].float()
    T, B = model.template[points].float(), model.expression_basis[:, points].float()  # [M, 3], [52, M, 3]
    free = refined_expressions(model) if expressions else torch.zeros(0, dtype=torch.int64)
    Bf, Btf, active = B[free], problem.Bt[..., free].contiguous(), 6 + len(free)
    p, Rh, c32 = p.clone(), rodrigues(p[:, :3]), c.float()
    sums = []
    for li, (level, steps) in enumerate(schedule):
        scale, margin = 2 ** level, 3 * 2 ** level
        for step in range(steps):
            if step == 0 or expressions:
                X = T + torch.einsum("nk,kmc->nmc", p[:, 6:].float(), B)
                Xl_expr = torch.einsum("nk,klc->nlc", p[:, 6:], problem.B)
            R = R0 @ Rh
            R32 = R.float()
            Xc = X @ R32.transpose(1, 2) + p[:, None, 3:6].float()
            u, dU = projection(Xc, f, c32)
            facing = -((normals @ R32.transpose(1, 2)) * nnf.normalize(Xc, dim=-1)).sum(-1)
            seen = (facing > MIN_FACING) & (u[..., 0] > margin) & (u[..., 0] < W - margin) & (u[..., 1] > margin) \
                & (u[..., 1] < H - margin)
            sample = _sample(levels[level], u, scale)
            if step == 0:  # the points' colours, with the poses as they are at this level
                sums.append(torch.stack([(sample[..., 0] * seen).sum(0), seen.sum(0)]).double())
                total, views = sums[-1] if others is None else sums[-1] + others[li]
                colour = (total / views.clamp_min(1)).float()
                known = views >= MIN_VIEWS
            r = sample[..., 0] - colour
            w = (seen & known) * torch.clamp(HUBER_GREY / r.abs().clamp_min(1e-9), max=1.0)
            dG = (sample[..., 1:3, None] * dU).sum(2, keepdim=True)  # d(grey)/d(camera point) [N, M, 1, 3]
            sw = w.sqrt()  # the weights on both sides: sqrt(w) J, as fit.normal_equations has them
            J = pixel_jacobian(dG, R32, X, Bf if expressions else None).mul_(sw[..., None])
            weight = EXPRESSION_PIXEL_WEIGHT if expressions else PHOTOMETRIC_WEIGHT
            Hm = weight * (J.transpose(1, 2) @ J).double()
            g = weight * (J.transpose(1, 2) @ (r * sw)[..., None]).double()
            Xl = problem.anchors(p[:, :3]) + Xl_expr
            ul, dUl = projection(Xl @ R.transpose(1, 2) + p[:, None, 3:6], f, c)
            rl = ul - obs
            wl = torch.clamp(1.5 / rl.norm(dim=-1).clamp_min(1e-9), max=1.0)  # the landmarks' Huber weights [N, L]
            Hl, gl = normal_equations(dUl, R, Xl, Btf if expressions else None, wl, rl)
            Hm = Hm + Hl + 1e-3 * torch.eye(active, dtype=torch.float64)
            g = g + gl
            if expressions:  # the landmark fit's prior on the expressions
                Hm[:, 6:, 6:] += EXPRESSION_WEIGHT * torch.eye(len(free), dtype=torch.float64)
                g[:, 6:, 0] += EXPRESSION_WEIGHT * p[:, 6 + free]
            delta = torch.linalg.solve(Hm, -g)[..., 0]
            if focal and li == len(schedule) - 1 and step == steps - 1:  # the focal length's marginal terms
                jf = (sample[..., 1:3] * (u - c32)).sum(-1) * sw  # d(grey)/d(log f), weighted [N, M]
                dl = (ul - c) * wl[..., None]  # d(landmark)/d(log f), weighted once
                Hf = weight * (J.transpose(1, 2) @ jf[..., None]).double()[..., 0] \
                    + torch.einsum("nlca,nlc->na", jacobian(dUl, R, Xl), dl)
                hff = weight * (jf * jf).sum(1).double() + ((ul - c) * dl).sum((1, 2))
                gf = weight * (jf * r * sw).sum(1).double() + (rl * dl).sum((1, 2))
                shared = marginal(Hm, g[..., 0], Hf, hff, gf)
            Rh = Rh @ rodrigues(delta[:, :3])
            p[:, 3:6] += delta[:, 3:6]
            p[:, :3] = matrix_to_axis_angle(Rh)
            if expressions:
                p[:, 6 + free] = (p[:, 6 + free] + delta[:, 6:]).clamp(0.0, 1.0)
    return p, torch.stack(sums), shared


FOCAL_STEP = 0.1  # the largest change of log f between two passes


def marginal(H: torch.Tensor, g: torch.Tensor, Hf: torch.Tensor, hff: torch.Tensor, gf: torch.Tensor
             ) -> torch.Tensor:
    """The Gauss-Newton terms of one parameter that all frames share (log f), with each frame's own parameters
    free (the Schur complement): the frames' blocks ``H [N, A, A]``, ``g [N, A]``, their coupling to the shared
    parameter ``Hf [N, A]`` and its own ``hff [N]``, ``gf [N]`` -> ``[2]``: its curvature and gradient."""
    Hi = torch.linalg.solve(H, torch.stack([Hf, g], -1))  # [N, A, 2]
    return torch.stack([(hff - (Hf * Hi[..., 0]).sum(1)).sum(), (gf - (Hf * Hi[..., 1]).sum(1)).sum()])


def _refocus(terms: torch.Tensor, f: float, p: torch.Tensor) -> float:
    """The focal length after one Gauss-Newton step on log f from the pass's :func:`marginal` terms (summed over its
    chunks), at most :data:`FOCAL_STEP`; every frame's translation ``p[:, 3:6]`` scaled in place by as much (the
    head as far away as the new focal length sees it the same size, so the next pass starts where it ended)."""
    ratio = float(np.exp(np.clip(-float(terms[1]) / max(float(terms[0]), 1e-12), -FOCAL_STEP, FOCAL_STEP)))
    p[:, 3:6] *= ratio
    return f * ratio


def _normals(model) -> torch.Tensor:
    from ..data.meshraster import vertex_normals

    return vertex_normals(model.template.double()[None], model.faces)[0]


def refine_on_pixels(model, fit: FitResult, landmarks: np.ndarray, iris: np.ndarray,
                 chunks: Callable[[], Iterable[tuple[np.ndarray, np.ndarray]]], threads: int | None = None,
                 passes: int = PASSES, expression_passes: int = EXPRESSION_PASSES, focal: bool = True) -> FitResult:
    """The landmark fit ``fit`` of N frames (their ``landmarks [N, 468, 3]`` and ``iris [N, 2, 5, 3]``, as
    :func:`.fit.fit_frames` took them) with each frame's head pose refined on its pixels in ``passes`` passes,
    then its pose and expressions together in ``expression_passes`` more: ``chunks()`` yields (frame indices into
    the N, grey frames ``[n, H, W]`` float32 of the fitted size, :func:`grey`), once per pass. A point's colour is
    its mean over the frames of its chunk and of the chunks before it on the first pass of a kind, and over the
    whole video on the later ones (the other chunks' sums from the pass before). ``focal``: refine the focal
    length in the pose passes too (module docstring; False keeps ``fit``'s)."""
    from ..data.generate import torch_threads

    with torch_threads(threads):
        problem = Problem(model)
        obs = problem.observations(landmarks, iris)
        f, c = float(fit.K[0, 0]), torch.tensor(fit.K[:2, 2], dtype=torch.float64)
        R = torch.from_numpy(fit.R).double()
        p = torch.cat([matrix_to_axis_angle(R0.T @ R), torch.from_numpy(fit.t).double(),
                       torch.from_numpy(fit.expression).double()], 1)
        points = rigid_points(model)
        both = torch.cat([points[:EXPRESSION_RIGID], rigid_points(model, EXPRESSION_POINTS, moving=True)])
        before: list[torch.Tensor] = []  # each chunk's colour sums [levels, 2, M] in the pass before
        for pass_ in range(passes + expression_passes):
            expressions = pass_ >= passes
            if pass_ == passes:
                before = []  # other points: their colours start afresh
            total, running, sums_now, focal_terms = sum(before) if before else None, None, [], None
            for i, (idx, images) in enumerate(chunks()):
                k = torch.from_numpy(np.asarray(idx, np.int64))
                others = running if total is None else total - before[i]
                p[k], sums, terms = refine_chunk(problem, model, p[k], obs[k], images, f, c,
                                                 both if expressions else points, others, expressions=expressions,
                                                 focal=focal and not expressions)
                focal_terms = terms if focal_terms is None else focal_terms + terms
                sums_now.append(sums)
                running = sums if running is None else running + sums
            before = sums_now
            if focal_terms is not None:
                f = _refocus(focal_terms, f, p)
        err = (problem.project(p, f, c) - obs).norm(dim=-1)
    K = fit.K.copy()
    K[0, 0] = K[1, 1] = f
    return FitResult(K, (R0 @ rodrigues(p[:, :3])).numpy(), p[:, 3:6].numpy(), p[:, 6:].numpy(),
                     err.median(1).values.numpy(), fit.focal_search)
