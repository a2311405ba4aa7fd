"""``data synth``: a synthetic tracked video of a face model, rendered with the mesh rasterizer, as a portable dataset.

:func:`synth_dataset` scripts a smooth, seeded performance, renders it and writes it with
:func:`~render_core.data.portable.write_dataset` (PNG frames, exact masks, tracking). What the script uses - and the
tracking holds exactly that:

- Expressions: "actions" (a smile, a frown, raised brows, a pucker, talking, blinks, ...), each a fixed pattern of
  ARKit-named coefficients scaled by a smooth envelope (raised ramps, a plateau); a few at once (an action's window
  overlaps at most three others; blinks come on top). With a model lacking the ARKit names, actions are random
  disjoint subsets of one or two coefficients. Values are clamped to [0, 1].
- Jaw: the ``jawOpen`` coefficient when the model has one (the open head; its jaw joint stays at rest, as
  docs/method.md section 11 has it), else the ``jaw`` joint, opening about +x (up to 0.3 rad).
- Gaze: the eight ``eyeLook*`` coefficients when the model has them (they move the open head's eyeballs, and are
  what ARKit clients stream; its eye joints stay at rest), else the ``eye_l``/``eye_r`` joints (yaw about +y,
  pitch about -x, both eyes alike); fixations joined by 3-frame saccades.
- Blinks: ``eyeBlinkLeft/Right`` when present, else the eyelid basis when present; ``eyelids`` are zeros otherwise.
- Head pose: in the CAMERA extrinsics, as a metrical tracker stores it (docs/method.md section 7): the head's rotation
  R_h about the pivot p (the ``head`` joint, else the skull joint) becomes R = R0 R_h, t = t0 + R0 (p - R_h p) for
  the front camera (R0, t0). Root, neck and head joints stay at rest. Since the light is fixed in the face model's
  frame, shading moves with the head (a head-mounted light, as a tracker's canonical space sees it).
- Identity: fixed; empty for a model without a shape basis, else the first ten coefficients N(0, 0.5^2).

Train/test split: the last 15% of the frames (at least one) are the test set and hold NOVEL combinations and poses:

- expressions: the actions come in "conflict pairs" (smile + raised brows, frown + talking, pucker + sneer, ...).
  In training the two actions of a pair never overlap (their envelopes have disjoint support); every test frame has
  at least one pair both at activation >= 0.4 (pairs cross-fade; amplitudes 0.85-1.0, training 0.45-0.85), so
  coefficient values also go a little beyond the training range;
- head pose: training keeps (yaw / 25 deg, pitch / 12 deg) inside the L1 diamond |y| + |p| <= 1 (large yaw and large
  pitch never co-occur) and roll within +-4 deg; test poses move on the ring |y| + |p| in [1.12, 1.25] (corners
  never seen, and up to 25% beyond either range) with roll up to +-5 deg;
- gaze: training fixations within +-1 (normalised), test fixations up to +-1.15.

Rendering: :mod:`render_core.data.meshraster` at size x size, RGB = procedural albedo (:mod:`.albedo`, a function of the
rest surface position, never written to the dataset) x Lambert shading (one fixed light + ambient) from the posed
mesh's interpolated vertex normals, over black; the mask is the exact coverage of the mesh. The camera frames the
head (the skull joint's vertices) at 65% of the image height, 0.7 m away, front view.
"""

from __future__ import annotations

import math
import os
import time
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..camera import Cameras, look_at
from ..errors import OptionError
from ..facemodel.model import FaceModel
from ..media.files import write_image
from ..media.pixels import to_uint8
from ..rotation import axis_angle_to_matrix
from .albedo import SkinAlbedo, lambert
from .meshraster import interpolate, rasterize, vertex_normals

__all__ = ["Script", "contact_sheet", "make_script", "render_frames", "script_cameras", "synth_dataset",
           "held_out_count"]

FPS = 30.0
TEST_FRACTION = 0.15
HEAD_FILL = 0.65  # head height / image height
DISTANCE = 0.7  # metres from the camera to the head's centre
YAW_RANGE, PITCH_RANGE, ROLL_RANGE = 25.0, 12.0, 4.0  # training, degrees
TEST_RING = (1.12, 1.25)  # test poses: |yaw / YAW_RANGE| + |pitch / PITCH_RANGE| in this range
TEST_ROLL = 5.0
TRAIN_AMPLITUDE, TEST_AMPLITUDE = (0.45, 0.85), (0.85, 1.0)
TEST_GAZE = 1.15
JAW_ANGLE = 0.30  # radians of jaw joint opening at full "jaw" activation (models without jawOpen)
GAZE_ANGLES = (0.35, 0.22)  # radians of eye joint yaw / pitch at gaze 1 (models without eyeLook*)
GAZE_COEFFICIENT = 0.6  # eyeLook* value at gaze 1
TALK_JAW = 0.5  # jawOpen at full talking activation

# Actions on ARKit names: coefficient -> weight. "talk" and "blink" are special (see _action_values).
ARKIT_ACTIONS: dict[str, dict[str, float]] = {
    "smile": {"mouthSmileLeft": 0.8, "mouthSmileRight": 0.8, "cheekSquintLeft": 0.4, "cheekSquintRight": 0.4,
              "eyeSquintLeft": 0.25, "eyeSquintRight": 0.25},
    "smirk": {"mouthDimpleLeft": 0.6, "mouthLeft": 0.3, "mouthSmileLeft": 0.5},
    "frown": {"mouthFrownLeft": 0.7, "mouthFrownRight": 0.7, "browDownLeft": 0.5, "browDownRight": 0.5,
              "mouthShrugLower": 0.3},
    "brows_up": {"browInnerUp": 0.8, "browOuterUpLeft": 0.7, "browOuterUpRight": 0.7, "eyeWideLeft": 0.4,
                 "eyeWideRight": 0.4},
    "worried": {"browInnerUp": 0.7, "mouthStretchLeft": 0.45, "mouthStretchRight": 0.45},
    "pucker": {"mouthPucker": 0.85, "mouthFunnel": 0.3},
    "sneer": {"noseSneerLeft": 0.7, "noseSneerRight": 0.7, "mouthUpperUpLeft": 0.45, "mouthUpperUpRight": 0.45},
    "cheek_puff": {"cheekPuff": 0.8},
    "press": {"mouthPressLeft": 0.6, "mouthPressRight": 0.6, "mouthRollLower": 0.4, "mouthRollUpper": 0.3},
    "jaw_left": {"jawLeft": 0.6, "mouthLeft": 0.3},
    "jaw_right": {"jawRight": 0.6, "mouthRight": 0.3},
    "tongue": {"tongueOut": 0.7, "jawOpen": 0.3},
    "wink": {"eyeBlinkLeft": 1.0, "cheekSquintLeft": 0.3, "mouthSmileLeft": 0.15},
    "talk": {},
    "blink": {"eyeBlinkLeft": 1.0, "eyeBlinkRight": 1.0},
}
ARKIT_CONFLICTS = [("smile", "brows_up"), ("frown", "talk"), ("pucker", "sneer"), ("cheek_puff", "wink"),
                   ("smirk", "worried"), ("press", "jaw_left"), ("tongue", "jaw_right")]
VISEMES = ("mouthFunnel", "mouthPucker", "mouthStretchLeft", "mouthStretchRight", "mouthLowerDownLeft",
           "mouthLowerDownRight", "mouthUpperUpLeft", "mouthUpperUpRight", "mouthRollLower", "mouthClose")
GAZE_NAMES = ("eyeLookOutLeft", "eyeLookInLeft", "eyeLookUpLeft", "eyeLookDownLeft",
              "eyeLookInRight", "eyeLookOutRight", "eyeLookUpRight", "eyeLookDownRight")
DURATIONS = {"talk": (30, 80), "blink": (4, 6), "wink": (6, 12)}  # frames; others (12, 40)
ACTION_WEIGHTS = {"talk": 4.0}  # how often an action is picked in training (others 1)


@dataclass
class Script:
    """A scripted performance of N frames for one face model (what is rendered and what the tracking holds)."""

    expression: Tensor  # [N, K]
    joint_rotations: Tensor  # [N, J, 3] axis-angle
    eyelids: Tensor  # [N, 2]
    shape: Tensor  # [S]
    head: Tensor  # [N, 3] yaw, pitch, roll in degrees (applied through the camera)
    gaze: Tensor  # [N, 2] normalised gaze (yaw: + towards the subject's left; pitch: + up)
    actions: list[str]  # A action names
    activation: Tensor  # [N, A] envelope x amplitude of each action
    conflicts: list[tuple[int, int]]  # pairs of action indices never overlapping in training
    train: Tensor  # int64 indices
    test: Tensor  # int64 indices
    jaw_mode: str  # "coefficient", "joint" or "none"
    gaze_mode: str  # "coefficients", "joints" or "none"
    notes: dict = field(default_factory=dict)

    @property
    def frames(self) -> int:
        return int(self.expression.shape[0])


def held_out_count(frames: int) -> int:
    """Frames in the test set: the last 15% (rounded, at least 1)."""
    return max(1, int(round(TEST_FRACTION * frames)))


def _envelope(n: int, start: int, length: int, ramp: int, hard_start: bool = False, hard_end: bool = False) -> Tensor:
    """[n] smooth bump: 0 outside [start, start + length), smoothstep ramps of ``ramp`` frames, plateau 1."""
    t = torch.arange(n, dtype=torch.float64)
    r = float(max(ramp, 0) + 1)

    def s(x: Tensor) -> Tensor:
        x = x.clamp(0.0, 1.0)
        return x * x * (3 - 2 * x)

    up = torch.ones(n, dtype=torch.float64) if hard_start else s((t - start + 1) / r)
    down = torch.ones(n, dtype=torch.float64) if hard_end else s((start + length - t) / r)
    inside = (t >= start) & (t < start + length)
    return torch.where(inside, up * down, torch.zeros_like(t))


def _smooth_noise(n: int, g: torch.Generator, periods: tuple[float, float] = (40.0, 160.0), terms: int = 3) -> Tensor:
    """[n] smooth signal in [-1, 1]: a normalised sum of sinusoids with random periods (frames) and phases."""
    t = torch.arange(n, dtype=torch.float64)
    out = torch.zeros(n, dtype=torch.float64)
    total = 0.0
    for _ in range(terms):
        period = periods[0] + (periods[1] - periods[0]) * float(torch.rand(1, generator=g))
        amp = 0.5 + float(torch.rand(1, generator=g))
        out += amp * torch.sin(2 * math.pi * t / period + 2 * math.pi * float(torch.rand(1, generator=g)))
        total += amp
    return out / total


def _randint(g: torch.Generator, lo: int, hi: int) -> int:
    """Uniform integer in [lo, hi]."""
    return lo + int(torch.randint(hi - lo + 1, (1,), generator=g))


def _uniform(g: torch.Generator, lo: float, hi: float) -> float:
    return lo + (hi - lo) * float(torch.rand(1, generator=g))


def _actions_for(model: FaceModel, g: torch.Generator) -> tuple[dict[str, dict[int, float]], list[tuple[str, str]]]:
    """Action name -> {coefficient index: weight}, and the conflict pairs, for ``model``."""
    names = {n: i for i, n in enumerate(model.expression_names)}
    has_jaw = "jawOpen" in names or "jaw" in model.joint_names
    actions: dict[str, dict[int, float]] = {}
    if any(n in names for n in ("mouthSmileLeft", "browInnerUp", "eyeBlinkLeft", "jawOpen")):
        for a, pattern in ARKIT_ACTIONS.items():
            coeffs = {names[c]: w for c, w in pattern.items() if c in names}
            if a == "talk" and has_jaw:
                actions[a] = {}
            elif a == "blink":
                if coeffs:
                    actions[a] = coeffs
                elif model.eyelid_basis is not None:
                    actions[a] = {}
            elif coeffs:
                actions[a] = coeffs
        conflicts = [(a, b) for a, b in ARKIT_CONFLICTS if a in actions and b in actions]
        return actions, conflicts
    # Random disjoint subsets of one or two coefficients; consecutive actions conflict pairwise.
    order = torch.randperm(model.num_expressions, generator=g).tolist()
    k = 0
    while k < len(order):
        size = min(_randint(g, 1, 2), len(order) - k)
        actions[f"e{len(actions)}"] = {i: _uniform(g, 0.6, 1.0) for i in order[k:k + size]}
        k += size
    generic = list(actions)
    if has_jaw:
        actions["talk"] = {}
    if model.eyelid_basis is not None:
        actions["blink"] = {}
    conflicts = [(generic[i], generic[i + 1]) for i in range(0, len(generic) - 1, 2)]
    return actions, conflicts


def _gaze_track(n: int, lo: int, hi: int, limit: float, g: torch.Generator) -> Tensor:
    """[hi - lo, 2] fixations within +-limit joined by 3-frame smoothstep saccades."""
    out = torch.zeros(hi - lo, 2, dtype=torch.float64)
    cur = torch.tensor([_uniform(g, -limit, limit), _uniform(g, -limit, limit)], dtype=torch.float64)
    t = 0
    while t < hi - lo:
        hold = _randint(g, 8, 40)
        nxt = torch.tensor([_uniform(g, -limit, limit), _uniform(g, -limit, limit)], dtype=torch.float64)
        for k in range(hold):
            if t + k >= hi - lo:
                break
            x = min(k / 3.0, 1.0)
            out[t + k] = cur + (nxt - cur) * (x * x * (3 - 2 * x))
        cur = nxt
        t += hold
    return out


def make_script(model: FaceModel, frames: int, seed: int) -> Script:
    """The seeded performance of ``frames`` frames for ``model`` (module docstring: what moves, and the split).

    One generator draws everything, in this order: the actions, the training events and blinks, the test's
    conflict pairs, talking, gaze, head pose, identity shape (the helpers below, called in that order)."""
    if frames < 2:
        raise OptionError(f"need at least 2 (one training, one test), got {frames}", field="frames")
    g = torch.Generator().manual_seed(int(seed))
    n = frames
    n_test = held_out_count(n)
    n_train = n - n_test
    actions, conflict_names = _actions_for(model, g)
    action_names = list(actions)
    a_index = {a: i for i, a in enumerate(action_names)}
    conflicts = [(a_index[a], a_index[b]) for a, b in conflict_names]
    act = torch.zeros(n, len(action_names), dtype=torch.float64)
    _schedule_training(act, a_index, conflict_names, n_train, g)
    _schedule_test(act, conflicts, n_train, g)
    expr, rot, eyelids, jaw_mode = _action_values(model, actions, act, a_index, g)
    expr = expr.clamp(0.0, 1.0)
    gaze, gaze_mode = _apply_gaze(model, expr, rot, n_train, g)
    head = _head_pose(n_train, n_test, g)

    shape = torch.zeros(model.num_shape, dtype=torch.float64)
    if model.num_shape:
        shape[: min(10, model.num_shape)] = 0.5 * torch.randn(min(10, model.num_shape), generator=g,
                                                              dtype=torch.float64)
    return Script(
        expression=expr.float(), joint_rotations=rot.float(), eyelids=eyelids.float(), shape=shape.float(),
        head=head.float(), gaze=gaze.float(), actions=action_names, activation=act.float(), conflicts=conflicts,
        train=torch.arange(n_train), test=torch.arange(n_train, n), jaw_mode=jaw_mode, gaze_mode=gaze_mode,
    )


def _schedule_training(act: Tensor, a_index: dict[str, int], conflict_names: list[tuple[str, str]], n_train: int,
                       g: torch.Generator) -> None:
    """Add the training frames' events to ``act [N, A]``: scheduled greedily, conflicting actions never overlap, an
    event overlaps at most 3 others; then blinks every 2-5 s, in training and test alike (no conflict has one)."""
    n = act.shape[0]
    partners: dict[str, set[str]] = {a: set() for a in a_index}
    for a, b in conflict_names:
        partners[a].add(b)
        partners[b].add(a)
    events: list[tuple[str, int, int]] = []  # (action, start, end)
    pool = [a for a in a_index if a != "blink"]
    weights = torch.tensor([ACTION_WEIGHTS.get(a, 1.0) for a in pool], dtype=torch.float64)
    t = 0
    while pool and t < n_train:
        for _ in range(6):
            a = pool[int(torch.multinomial(weights, 1, generator=g))]
            lo, hi = DURATIONS.get(a, (12, 40))
            start = t + _randint(g, 0, 4)
            end = min(start + _randint(g, lo, hi), n_train)
            if end <= start:
                break
            overlapping = [e for e in events if e[1] < end and start < e[2]]
            if any(e[0] == a or e[0] in partners[a] for e in overlapping) or len(overlapping) >= 3:
                continue
            events.append((a, start, end))
            ramp = min(4, (end - start) // 3)
            act[:, a_index[a]] += _envelope(n, start, end - start, ramp) * _uniform(g, *TRAIN_AMPLITUDE)
            break
        t += _randint(g, 4, 12)
    if "blink" in a_index:
        t = _randint(g, 5, 60)
        while t < n:
            length = _randint(g, *DURATIONS["blink"])
            end = min(t + length, n_train if t < n_train else n)
            act[:, a_index["blink"]] += _envelope(n, t, end - t, 2)
            t += _randint(g, 60, 150)


def _schedule_test(act: Tensor, conflicts: list[tuple[int, int]], n_train: int, g: torch.Generator) -> None:
    """Add the test frames' conflict pairs to ``act [N, A]``, in turn, cross-faded (the two nearest pairs' weights
    sum to 1). A blink in training may have been clipped to the test boundary; conflicts never involve blinks."""
    if not conflicts:
        return
    n_test = act.shape[0] - n_train
    pairs = [conflicts[i] for i in torch.randperm(len(conflicts), generator=g).tolist()]
    seg = max(6, min(30, math.ceil(n_test / max(1, min(len(pairs), n_test // 6 or 1)))))
    count = math.ceil(n_test / seg)
    tt = torch.arange(n_test, dtype=torch.float64)
    # c(t): plateaus at integers k (combo k) with 4-frame linear transitions centred on the boundaries.
    c = torch.zeros(n_test, dtype=torch.float64)
    for k in range(1, count):
        c += ((tt - (k * seg - 2.0)) / 4.0).clamp(0.0, 1.0)
    for k in range(count):
        wk = (1.0 - (c - k).abs()).clamp_min(0.0)
        a, b = pairs[k % len(pairs)]
        for i in (a, b):
            act[n_train:, i] += wk * _uniform(g, *TEST_AMPLITUDE)


def _action_values(model: FaceModel, actions: dict[str, dict[int, float]], act: Tensor, a_index: dict[str, int],
                   g: torch.Generator) -> tuple[Tensor, Tensor, Tensor, str]:
    """Expression coefficients ``[N, K]`` (not clamped yet), joint rotations ``[N, J, 3]`` and eyelids ``[N, 2]``
    from the activations, with talking (jaw and visemes) and blinks; and how the jaw opens."""
    n = act.shape[0]
    names = {nm: i for i, nm in enumerate(model.expression_names)}
    expr = torch.zeros(n, model.num_expressions, dtype=torch.float64)
    rot = torch.zeros(n, model.num_joints, 3, dtype=torch.float64)
    eyelids = torch.zeros(n, 2, dtype=torch.float64)
    for a, coeffs in actions.items():
        w = act[:, a_index[a]]
        for i, c in coeffs.items():
            expr[:, i] += w * c
    jaw_mode = "coefficient" if "jawOpen" in names else "joint" if "jaw" in model.joint_names else "none"
    if "talk" in a_index:
        _talk(model, act[:, a_index["talk"]], expr, rot, jaw_mode, g)
    if "blink" in a_index and not actions["blink"] and model.eyelid_basis is not None:
        eyelids += act[:, a_index["blink"], None]
    return expr, rot, eyelids, jaw_mode


def _talk(model: FaceModel, w: Tensor, expr: Tensor, rot: Tensor, jaw_mode: str, g: torch.Generator) -> None:
    """Add talking at activation ``w [N]``: a syllable-rate jaw oscillation (a coefficient or the jaw joint) and
    noisy visemes, to ``expr`` and ``rot``."""
    n = w.shape[0]
    names = {nm: i for i, nm in enumerate(model.expression_names)}
    tt = torch.arange(n, dtype=torch.float64)
    rate = _uniform(g, 3.0, 4.5) / FPS  # syllables per frame
    osc = 0.5 + 0.5 * torch.sin(2 * math.pi * rate * tt + 2 * math.pi * float(torch.rand(1, generator=g)))
    osc = 0.35 + 0.65 * osc * (0.7 + 0.3 * _smooth_noise(n, g, (15.0, 50.0)))
    jaw = w * osc
    if jaw_mode == "coefficient":
        expr[:, names["jawOpen"]] += TALK_JAW * jaw
    elif jaw_mode == "joint":
        rot[:, model.joint_names.index("jaw"), 0] += JAW_ANGLE * jaw
    for v in VISEMES:
        if v in names:
            level = (0.5 + 0.5 * _smooth_noise(n, g, (8.0, 30.0))).clamp(0, 1) ** 2
            # mouthClose never exceeds the jaw opening (ARKit: it only closes the lips of an open jaw).
            cap = TALK_JAW * jaw if v == "mouthClose" else 0.35
            expr[:, names[v]] += w * level * cap


def _apply_gaze(model: FaceModel, expr: Tensor, rot: Tensor, n_train: int,
                g: torch.Generator) -> tuple[Tensor, str]:
    """The gaze track ``[N, 2]`` (fixations and saccades; wider in the test frames), written into ``expr``'s
    eyeLook* coefficients or ``rot``'s eye joints; and which of the two (or neither)."""
    n = expr.shape[0]
    names = {nm: i for i, nm in enumerate(model.expression_names)}
    gaze = torch.cat([_gaze_track(n, 0, n_train, 1.0, g), _gaze_track(n, n_train, n, TEST_GAZE, g)])
    gaze_mode = ("coefficients" if all(nm in names for nm in GAZE_NAMES)
                 else "joints" if "eye_l" in model.joint_names and "eye_r" in model.joint_names else "none")
    if gaze_mode == "coefficients":
        gy, gp = gaze[:, 0], gaze[:, 1]
        pos_y, neg_y = gy.clamp_min(0) * GAZE_COEFFICIENT, (-gy).clamp_min(0) * GAZE_COEFFICIENT
        up, down = gp.clamp_min(0) * GAZE_COEFFICIENT, (-gp).clamp_min(0) * GAZE_COEFFICIENT
        # Looking towards the subject's left (+x): the left eye looks out, the right eye in.
        for nm, v in zip(GAZE_NAMES, (pos_y, neg_y, up, down, pos_y, neg_y, up, down), strict=True):
            expr[:, names[nm]] = v.clamp(0.0, 1.0)
    elif gaze_mode == "joints":
        for j in ("eye_l", "eye_r"):
            ji = model.joint_names.index(j)
            rot[:, ji, 0] = -GAZE_ANGLES[1] * gaze[:, 1]  # rotation about -x looks up
            rot[:, ji, 1] = GAZE_ANGLES[0] * gaze[:, 0]  # about +y looks towards +x
    return gaze, gaze_mode


def _head_pose(n_train: int, n_test: int, g: torch.Generator) -> Tensor:
    """Head pose ``[N, 3]`` (yaw, pitch, roll in degrees; applied through the camera): the training frames inside
    the L1 diamond of YAW_RANGE x PITCH_RANGE, the test frames on the ring outside it (TEST_RING)."""
    yaw_n = _smooth_noise(n_train, g, (60.0, 200.0))
    pitch_n = _smooth_noise(n_train, g, (50.0, 180.0))
    l1 = (yaw_n.abs() + pitch_n.abs()).clamp_min(1.0)
    roll = ROLL_RANGE * _smooth_noise(n_train, g, (70.0, 220.0))
    head_train = torch.stack([YAW_RANGE * yaw_n / l1, PITCH_RANGE * pitch_n / l1, roll], -1)
    tt = torch.arange(n_test, dtype=torch.float64)
    angle = 2 * math.pi * float(torch.rand(1, generator=g)) + tt * (2 * math.pi / max(60.0, 2.0 * n_test))
    radius = TEST_RING[0] + (TEST_RING[1] - TEST_RING[0]) * (0.5 + 0.5 * torch.sin(tt / 9.0))
    cs, sn = torch.cos(angle), torch.sin(angle)
    unit = torch.stack([cs, sn], -1) / (cs.abs() + sn.abs())[:, None]  # on the unit L1 circle
    head_test = torch.stack([YAW_RANGE * radius * unit[:, 0], PITCH_RANGE * radius * unit[:, 1],
                             TEST_ROLL * _smooth_noise(n_test, g, (40.0, 120.0))], -1)
    return torch.cat([head_train, head_test])


def _rotation(yaw: Tensor, pitch: Tensor, roll: Tensor) -> Tensor:
    """Head rotations [N, 3, 3] from degrees: yaw about +y (face turns towards +x), pitch up, roll about +z."""
    ry = axis_angle_to_matrix(torch.stack([torch.zeros_like(yaw), torch.deg2rad(yaw), torch.zeros_like(yaw)], -1))
    rx = axis_angle_to_matrix(torch.stack([-torch.deg2rad(pitch), torch.zeros_like(pitch), torch.zeros_like(pitch)],
                                          -1))
    rz = axis_angle_to_matrix(torch.stack([torch.zeros_like(roll), torch.zeros_like(roll), torch.deg2rad(roll)], -1))
    return ry @ rx @ rz


def _head_frame(model: FaceModel, shape: Tensor) -> tuple[Tensor, float, Tensor]:
    """(centre of the head's rest bounding box, its height, the head-pose pivot) in the model's frame."""
    template, joints = model.shaped(shape if shape.numel() else None)
    skull = model.joint_names.index(model.skull_joint)
    carried = {skull}
    for j, p in enumerate(model.joint_parents):
        if p in carried:
            carried.add(j)
    w = model.lbs_weights[:, sorted(carried)].sum(1)
    pts = template[w > 0.5] if bool((w > 0.5).any()) else template
    lo, hi = pts.min(0).values, pts.max(0).values
    pivot_joint = model.joint_names.index("head") if "head" in model.joint_names else skull
    return ((lo + hi) / 2).double(), float(hi[1] - lo[1]), joints[pivot_joint].double()


def script_cameras(model: FaceModel, script: Script, size: int) -> Cameras:
    """Per-frame OpenCV cameras (K, R, t) at size x size holding the script's head pose (module docstring)."""
    centre, height, pivot = _head_frame(model, script.shape)
    focal = HEAD_FILL * size * DISTANCE / max(height, 1e-6)
    R0, t0 = look_at(centre + torch.tensor([0.0, 0.0, DISTANCE], dtype=torch.float64), centre)
    h = script.head.double()
    Rh = _rotation(h[:, 0], h[:, 1], h[:, 2])
    R = R0 @ Rh
    t = t0 + (R0 @ (pivot[None, :, None] - Rh @ pivot[None, :, None])).squeeze(-1)
    K = torch.tensor([[focal, 0.0, size / 2], [0.0, focal, size / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    n = script.frames
    return Cameras(K.expand(n, 3, 3).float().clone(), R.float(), t.float(), size, size)


@contextmanager
def torch_threads(n: int | None):
    """torch's intra-op thread count set to ``n`` (None: unchanged) inside the block, restored after (small tensor
    work, such as the tracker's crops, is slowed down by extra threads on a busy machine)."""
    before = torch.get_num_threads()
    if n is not None and n != before:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        if torch.get_num_threads() != before:
            torch.set_num_threads(before)


def render_frames(model: FaceModel, script: Script, cameras: Cameras, albedo: SkinAlbedo,
                  batch: int = 8) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Yield (RGB uint8 [H, W, 3], mask uint8 [H, W] (255 = mesh coverage)) per frame of ``script``."""
    faces = model.faces
    base = albedo.vertex_attributes()  # [V, 6]
    shape = script.shape if script.shape.numel() else None
    H, W = cameras.height, cameras.width
    for s in range(0, script.frames, batch):
        e = min(s + batch, script.frames)
        with torch.no_grad():
            posed, _ = model.evaluate(script.expression[s:e], axis_angle_to_matrix(script.joint_rotations[s:e]),
                                      script.eyelids[s:e], shape)
            cams = cameras.index(slice(s, e))
            normals = vertex_normals(posed, faces)
            attrs = torch.cat([base[None].expand(e - s, -1, -1), posed, normals], -1)
            c = base.shape[1]
            frags = rasterize(posed, faces, cams)
            px = interpolate(frags, faces, attrs)  # [b, H, W, 12]
            centres = cams.centres
            for b in range(e - s):
                mask = frags.face_id[b] >= 0
                rgb = torch.zeros(H, W, 3)
                if bool(mask.any()):
                    a = px[b][mask]
                    footprint = frags.depth[b][mask] / float(cams.K[b, 0, 0])
                    colour = albedo(a[:, :c], footprint)
                    view = centres[b][None] - a[:, c:c + 3]
                    rgb[mask] = lambert(colour, a[:, c + 3:c + 6], view)
                yield to_uint8(rgb), mask.to(torch.uint8).mul(255).numpy()


def synth_dataset(out_dir, frames: int, size: int, seed: int, facemodel: FaceModel | str | os.PathLike | None = None,
                  *, threads: int | None = 1) -> dict:
    """Render a synthetic tracked video of ``frames`` frames at ``size`` x ``size`` and write it to ``out_dir``.

    ``facemodel``: a FaceModel, the path of a face-model file (:func:`render_core.facemodel.read_facemodel`), or
    None for the open head (:func:`render_core.facemodel.open_head.open_head`, shipped with the package).
    ``threads``: torch's intra-op threads while rendering (default 1: the work is
    many small tensor operations, which extra threads slow down on a busy machine; None leaves torch's setting).
    Returns a summary: out, frames, train, test, size, seed, face_model, fps,
    jaw/gaze modes, render_ms_per_frame and seconds."""
    from .portable import Tracking, write_dataset

    if size < 8:
        raise OptionError(f"must be at least 8 pixels, got {size}", field="size")
    if facemodel is None:
        from ..facemodel.open_head import open_head

        facemodel = open_head()
    elif not isinstance(facemodel, FaceModel):
        from ..facemodel.io import read_facemodel

        facemodel = read_facemodel(facemodel)
    t_start = time.perf_counter()
    script = make_script(facemodel, frames, seed)
    cameras = script_cameras(facemodel, script, size)
    albedo = SkinAlbedo(facemodel, seed)
    tracking = Tracking(
        face_model=facemodel.name, expression_names=list(facemodel.expression_names),
        joint_names=list(facemodel.joint_names), expression=script.expression.numpy(),
        joint_rotations=script.joint_rotations.numpy(), eyelids=script.eyelids.numpy(), K=cameras.K.numpy(),
        R=cameras.R.numpy(), t=cameras.t.numpy(), shape=script.shape.numpy(), train=script.train.numpy(),
        test=script.test.numpy(), width=size, height=size, fps=FPS,
    )
    masks: deque[np.ndarray] = deque()
    render_s = 0.0

    def rgb_frames() -> Iterator[np.ndarray]:
        nonlocal render_s
        it = render_frames(facemodel, script, cameras, albedo)
        while True:
            t0 = time.perf_counter()
            with torch_threads(threads):
                item = next(it, None)
            render_s += time.perf_counter() - t0
            if item is None:
                return
            masks.append(item[1])
            yield item[0]

    def mask_frames() -> Iterator[np.ndarray]:
        while masks:
            yield masks.popleft()

    out = write_dataset(out_dir, rgb_frames(), mask_frames(), tracking, image_format="png")
    return {
        "out": str(out), "frames": frames, "train": int(script.train.numel()), "test": int(script.test.numel()),
        "size": size, "seed": int(seed), "face_model": facemodel.name, "fps": FPS, "jaw": script.jaw_mode,
        "gaze": script.gaze_mode, "render_ms_per_frame": round(1000.0 * render_s / frames, 1),
        "seconds": round(time.perf_counter() - t_start, 2),
    }


def contact_sheet(dataset_dir, out_png, count: int = 12, columns: int | None = None) -> Path:
    """Write a grid of ``count`` frames of a dataset, evenly spaced over the video, to ``out_png``.

    Test frames get a 2-pixel red border, training frames a grey one."""
    from .portable import read_dataset

    ds = read_dataset(dataset_dir)
    n = len(ds)
    count = max(1, min(count, n))
    idx = sorted({int(round(i * (n - 1) / max(count - 1, 1))) for i in range(count)})
    test = set(np.asarray(ds.tracking.test).tolist())
    cols = columns or math.ceil(math.sqrt(len(idx) * 4 / 3))
    rows = math.ceil(len(idx) / cols)
    h, w = ds.tracking.height, ds.tracking.width
    pad = 2
    sheet = np.zeros((rows * (h + 2 * pad), cols * (w + 2 * pad), 3), dtype=np.uint8)
    for k, i in enumerate(idx):
        r, c = divmod(k, cols)
        y, x = r * (h + 2 * pad), c * (w + 2 * pad)
        sheet[y:y + h + 2 * pad, x:x + w + 2 * pad] = (220, 40, 40) if i in test else (90, 90, 90)
        sheet[y + pad:y + pad + h, x + pad:x + pad + w] = to_uint8(ds.frame(i))
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    write_image(out_png, sheet)
    return out_png
