"""The tracker's known answer: how far a tracking of the open head is from the truth (``data synth`` writes the
truth; the tracker tracks its frames back).

:func:`known_answer` poses the open head with both trackings (expressions, joints, eyelids) and projects its
surface vertices (the skin: eyeballs, teeth and tongue left out, front- and back-facing alike) with each one's
camera, frame by frame, and reports the median (and 90th percentile) pixel distance between the two, the head's
rotation error (the head joint's orientation in the camera, degrees) and the jaw's (the opening angle of the
chin about the jaw joint, from ``jawOpen`` - where the open head's trackings keep the jaw - and the jaw joint's
rotation, degrees), and the expressions' (the mean distance, mm, by which the two trackings' expression
coefficients move the open head's vertices apart, pose aside). :func:`encode_h264` makes the ordinary video a
phone would: the frames as H.264 (yuv420p); :func:`synth_video` a known-answer video: a ``data synth`` dataset (the
truth) and its frames so encoded.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

SKIPPED_GROUPS = ("eyeball_l", "eyeball_r", "teeth_upper", "teeth_lower", "tongue")


def _coefficients(model, tracking, dtype: torch.dtype) -> torch.Tensor:
    """A tracking's expression coefficients in the model's order ``[N, K]`` (matched by name, a missing one 0)."""
    e = torch.zeros(len(tracking.expression), model.num_expressions, dtype=dtype)
    for k, name in enumerate(model.expression_names):
        if name in tracking.expression_names:
            e[:, k] = torch.from_numpy(np.asarray(tracking.expression[:, tracking.expression_names.index(name)]))
    return e


def _posed(model, tracking) -> tuple[torch.Tensor, torch.Tensor]:
    """(Projected vertices ``[N, V, 2]``, the head's camera-space rotation ``[N, 3, 3]``) of a tracking."""
    from ..rotation import axis_angle_to_matrix

    n = len(tracking.expression)
    e = _coefficients(model, tracking, torch.float32)
    aa = torch.zeros(n, model.num_joints, 3)
    for j, name in enumerate(model.joint_names):
        if name in tracking.joint_names:
            aa[:, j] = torch.from_numpy(np.asarray(tracking.joint_rotations[:, tracking.joint_names.index(name)]))
    with torch.no_grad():
        v, transforms = model.evaluate(e, axis_angle_to_matrix(aa), torch.from_numpy(np.asarray(tracking.eyelids)))
    R, t, K = (torch.from_numpy(np.asarray(x, np.float32)) for x in (tracking.R, tracking.t, tracking.K))
    xc = v @ R.transpose(1, 2) + t[:, None]
    uv = xc[..., :2] / xc[..., 2:3] * torch.stack([K[:, 0, 0], K[:, 1, 1]], -1)[:, None] + K[:, None, :2, 2]
    head = model.joint_names.index("head") if "head" in model.joint_names else 0
    return uv, R @ transforms[:, head, :3, :3]


def _angle(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    rel = a.transpose(1, 2) @ b
    return torch.rad2deg(torch.arccos(((rel.diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2).clamp(-1, 1)))


def jaw_degrees(model, tracking) -> np.ndarray:
    """The jaw's opening per frame (degrees): the chin vertex (the one ``jawOpen`` moves most) about the jaw
    joint's x axis, moved by ``jawOpen`` and by the jaw joint's rotation about x."""
    k = model.expression_names.index("jawOpen")
    basis = model.expression_basis[k].double().numpy()
    v = int(np.linalg.norm(basis, axis=1).argmax())
    joint = model.joint_positions[model.joint_names.index("jaw")].double().numpy()
    rest = model.template[v].double().numpy() - joint
    names = list(tracking.expression_names)
    amount = tracking.expression[:, names.index("jawOpen")] if "jawOpen" in names else np.zeros(len(tracking.R))
    moved = rest[None] + np.asarray(amount, np.float64)[:, None] * basis[v][None]
    angle = np.arctan2(moved[:, 1], moved[:, 2]) - math.atan2(rest[1], rest[2])
    if "jaw" in tracking.joint_names:
        angle = angle + tracking.joint_rotations[:, tracking.joint_names.index("jaw"), 0]
    return np.degrees(angle)


def expression_mm(model, truth, tracked) -> np.ndarray:
    """Per frame, the mean distance (mm) over the open head's vertices between the two trackings' expressions
    (coefficients matched by name, a missing one 0), each applied to the template through the expression basis."""
    delta = _coefficients(model, tracked, torch.float64) - _coefficients(model, truth, torch.float64)
    moved = torch.einsum("nk,kvc->nvc", delta, model.expression_basis.double())
    return (moved.norm(dim=-1).mean(1) * 1000).numpy()


def known_answer(model, truth, tracked) -> dict:
    """The figures of the module docstring for two trackings of the same frames (``Tracking`` objects)."""
    if len(truth.expression) != len(tracked.expression):
        raise ValueError(f"the truth has {len(truth.expression)} frames, the tracking {len(tracked.expression)}")
    skin = torch.ones(model.num_vertices, dtype=torch.bool)
    for group in SKIPPED_GROUPS:
        if group in model.vertex_groups:
            skin[model.vertex_groups[group]] = False
    uv_truth, head_truth = _posed(model, truth)
    uv_tracked, head_tracked = _posed(model, tracked)
    err = (uv_truth - uv_tracked).norm(dim=-1)[:, skin]
    rotation = _angle(head_truth, head_tracked)
    jaw = np.abs(jaw_degrees(model, truth) - jaw_degrees(model, tracked))
    return {"frames": len(truth.expression), "median_vertex_px": round(float(err.median()), 3),
            "p90_vertex_px": round(float(err.quantile(0.9)), 3),
            "median_head_rotation_deg": round(float(rotation.median()), 3),
            "max_head_rotation_deg": round(float(rotation.max()), 3), "median_jaw_deg": round(float(np.median(jaw)), 3),
            "mean_expression_mm": round(float(expression_mm(model, truth, tracked).mean()), 3)}


def encode_h264(frames, path: str | Path, fps: int = 30, crf: int = 14) -> Path:
    """Frames (uint8 RGB ``[H, W, 3]``, even sizes) -> an H.264 MP4 (yuv420p, ``crf``, preset veryfast)."""
    import av

    path = Path(path)
    with av.open(str(path), "w") as out:
        stream = None
        for rgb in frames:
            if stream is None:
                stream = out.add_stream("libx264", rate=fps)
                stream.width, stream.height = rgb.shape[1], rgb.shape[0]
                stream.pix_fmt = "yuv420p"
                stream.options = {"crf": str(crf), "preset": "veryfast"}
            for packet in stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")):
                out.mux(packet)
        if stream is not None:
            for packet in stream.encode():
                out.mux(packet)
    return path


def synth_video(folder: str | Path, frames: int, size: int, seed: int, model=None):
    """``data synth``'s performance ``seed`` in ``folder/truth`` (the truth: a dataset) and its frames as the H.264
    video ``folder/clip.mp4``: (the truth's Dataset, the video's path)."""
    from ..data.generate import synth_dataset
    from ..data.portable import read_dataset
    from ..media.pixels import to_uint8

    folder = Path(folder)
    synth_dataset(folder / "truth", frames=frames, size=size, seed=seed, facemodel=model)
    truth = read_dataset(folder / "truth")
    rgb = (np.asarray(truth.frame(i)) for i in range(len(truth)))
    return truth, encode_h264((f if f.dtype == np.uint8 else to_uint8(f) for f in rgb), folder / "clip.mp4")
