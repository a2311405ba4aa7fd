"""The correspondence's calibration: where MediaPipe's landmarks really sit on the open head, learnt from renders
with a known answer.

A face-mesh landmark is not glued to one point of the surface. It sits a few millimetres off the point the
correspondence's front views gave it, and it slides as the head turns (MediaPipe's own mean face is not ours; its
cheek, nose-wing and lip-contour points follow what a 2D network sees, not a surface point). Uncorrected, that bias
is 1.3-1.9 px per landmark at 512x512 and comes out of the fit as a pose error: the head pitched by 2-3 degrees.

The calibration renders the open head through ``data synth``'s seeded performances (:func:`~render_core.data.
generate.make_script`: head turns, expressions, gaze; the known pose, expressions and camera of every frame), runs
the face mesh on each frame as the tracker does, and solves for every landmark ``l`` an offset in head coordinates
that is linear in the head's rotation (axis-angle ``r`` of the head relative to the front view) and in the
expressions ``e``::

    d_l(r, e) = D_l [1, r_x, r_y, r_z, e_1 .. e_K]        D_l: [3, 4 + K]

by least squares on the reprojection error (linearised: ``(u - c) z - f x = 0`` divided by the depth, so in
pixels), with a ridge (:data:`RIDGE_PER_FRAME` per frame seen) that keeps what the renders do not show at zero (an
offset along a viewing ray; an expression the performances never use). The result ships in the correspondence file
(``offsets``): :mod:`.fit` adds the rotation part at the current rotation to each landmark's surface point every
iteration, and the expression part to the landmarks' expression basis (the landmark as MediaPipe places it moves
with an expression by ``B_l + D_l[:, 4:]``; the fit stays linear in the expressions).

Honest limits: the offsets are learnt on the open head's own renders (the template identity, our skin shading), so
they remove MediaPipe's bias for heads like the template; on a real face they correct the part of the bias that
comes from MediaPipe's mean face and its view-dependent sliding, not what a different identity adds.
"""

from __future__ import annotations

import numpy as np
import torch

from .correspond import Correspondence

SEEDS = (1, 2, 3, 4, 5, 6, 7, 8)  # data synth seeds used for calibration (the checks draw theirs from 100-999)
FRAMES = 150
SIZE = 512
RIDGE_PER_FRAME = 5e4  # px^2 per m^2 per frame: ~0.2 px^2 for 2 mm


def _normal_equations(corr: Correspondence, rest: torch.Tensor, basis: torch.Tensor, obs: torch.Tensor,
                      expression: torch.Tensor, R: torch.Tensor, t: torch.Tensor, f: float,
                      c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """One video's contribution ``(A [L, 3F, 3F], b [L, 3F])`` to the offsets' least squares (module docstring).
    ``obs [N, L, 2]`` (NaN: not seen), the known ``expression [N, K]``, ``R [N, 3, 3]``, ``t [N, 3]``."""
    from .fit import R0, matrix_to_axis_angle

    X = rest + torch.einsum("nk,klc->nlc", expression, basis)  # [N, L, 3] the surface points
    Xc = X @ R.transpose(1, 2) + t[:, None]
    z = Xc[..., 2]
    phi = torch.cat([corr.offset_features(matrix_to_axis_angle(R0.T @ R)), expression], 1)  # [N, F]
    seen = ~torch.isnan(obs).any(-1)
    uc = torch.nan_to_num(obs - c)
    n = 3 * phi.shape[1]
    A = torch.zeros(rest.shape[0], n, n, dtype=torch.float64)
    b = torch.zeros(rest.shape[0], n, dtype=torch.float64)
    for k in range(2):
        row = (f * R[:, None, k, :] - uc[..., k:k + 1] * R[:, None, 2, :]) / z[..., None]  # [N, L, 3]
        y = (uc[..., k] * z - f * Xc[..., k]) / z
        M = torch.einsum("nli,nf->nlif", row, phi).flatten(2) * seen[..., None]  # [N, L, 3F]
        A += torch.einsum("nli,nlj->lij", M, M)
        b += torch.einsum("nli,nl->li", M, y * seen)
    return A, b


def calibrate(model, corr: Correspondence, seeds=SEEDS, frames: int = FRAMES, size: int = SIZE,
              progress=None) -> tuple[np.ndarray, dict]:
    """The offsets ``[L, 3, 4 + K]`` (module docstring) and a report: frames used, the median reprojection error at
    the known answer before and after."""
    from ..data.albedo import SkinAlbedo
    from ..data.generate import make_script, render_frames, script_cameras
    from .fit import Problem
    from .landmarks import track_landmarks

    plain = Correspondence(corr.landmarks, corr.triangles, corr.barycentric)
    problem = Problem(model, plain)
    L, F = problem.L, 4 + problem.B.shape[0]
    A = torch.zeros(L, 3 * F, 3 * F, dtype=torch.float64)
    b = torch.zeros(L, 3 * F, dtype=torch.float64)
    videos = []
    for seed in seeds:
        script = make_script(model, frames, seed)
        cams = script_cameras(model, script, size)
        rgb = (frame for frame, _ in render_frames(model, script, cams, SkinAlbedo(model, seed)))
        track = track_landmarks(rgb)
        obs = problem.observations(track.landmarks, track.iris)
        obs[torch.tensor([s not in ("detected", "tracked") for s in track.status])] = float("nan")
        known = (script.expression.double(), cams.R.double(), cams.t.double(), float(cams.K[0, 0, 0]),
                 cams.K[0, :2, 2].double())
        a_, b_ = _normal_equations(plain, problem.T, problem.B, obs, *known)
        A, b = A + a_, b + b_
        videos.append((obs, known))
        if progress:
            progress(f"calibration: seed {seed} ({len(videos)} of {len(seeds)})")
    n = sum(int((~torch.isnan(o).any(-1)).any(-1).sum()) for o, _ in videos)
    A += RIDGE_PER_FRAME * n * torch.eye(3 * F, dtype=torch.float64)
    offsets = torch.stack([torch.linalg.solve(A[k], b[k]) for k in range(L)]).reshape(L, 3, F)
    calibrated = Correspondence(corr.landmarks, corr.triangles, corr.barycentric, offsets.numpy().astype(np.float32))
    fitted = Problem(model, calibrated)
    before = [_residual(problem, obs, *known) for obs, known in videos]
    after = [_residual(fitted, obs, *known) for obs, known in videos]
    report = {"frames": n, "seeds": list(seeds), "median_px_before": round(float(np.median(before)), 3),
              "median_px_after": round(float(np.median(after)), 3),
              "offset_mm_median": round(float(offsets[..., 0].norm(dim=-1).median()) * 1000, 2)}
    return calibrated.offsets, report


def _residual(problem, obs, expression, R, t, f, c) -> float:
    """The median pixel distance between the landmarks and ``problem``'s points (its correspondence's, with the
    offsets it has) at the known answer."""
    from .fit import R0, matrix_to_axis_angle

    X = problem.anchors(matrix_to_axis_angle(R0.T @ R)) + torch.einsum("nk,klc->nlc", expression, problem.B)
    Xc = X @ R.transpose(1, 2) + t[:, None]
    uv = f * Xc[..., :2] / Xc[..., 2:3] + c
    err = (uv - obs).norm(dim=-1)
    return float(err[~torch.isnan(err)].median())
