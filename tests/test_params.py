"""service.params: the wire's frame and camera built directly from the messages, each problem named by the wire
field the client sent, and the same frames and cameras as a driving file's line gives."""

import math

import numpy as np
import pytest
import torch

from blendsplat.v1 import render_pb2 as pb
from render_core import drive
from render_core.drive import parse_line
from render_core.errors import FrameError
from service import params
from service.errors import InvalidArgument

OUT = params.output(48, 32, pb.CODEC_JPEG, 0, 2048)


def test_a_wire_frame_equals_the_driving_line_with_the_same_values(avatar):
    names = list(avatar.expression_names)
    order = list(reversed(names))  # the client's own positional order
    values = [0.1 * (i + 1) for i in range(len(names))]
    msg = pb.FrameParams(coefficients=values, eyelids=[0.2, 0.4],
                         joints={"jaw": pb.Rotation(values=[0.2, 0.0, 0.0]),
                                 "neck": pb.Rotation(values=[1, 0, 0, 0, 0.8, 0.6])})
    got = params.frame(avatar, msg, order)
    want = parse_line(avatar, {"expression": dict(zip(order, values, strict=True)), "eyelids": [0.2, 0.4],
                               "joints": {"jaw": [0.2, 0.0, 0.0], "neck": [1, 0, 0, 0, 0.8, 0.6]}}, 8, 8).frame
    assert torch.equal(got.expression, want.expression) and torch.equal(got.eyelids, want.eyelids)
    torch.testing.assert_close(got.joint_rotations, want.joint_rotations)
    got.check(avatar)
    named = params.frame(avatar, pb.FrameParams(named_coefficients={names[1]: 0.5}), names)
    assert named.expression[0, 1] == 0.5 and named.expression.abs().sum() == 0.5 and named.eyelids is None


@pytest.mark.parametrize("msg,field", [
    (pb.FrameParams(coefficients=[math.nan] * 6), "coefficients"),
    (pb.FrameParams(coefficients=[0.0] * 5), "coefficients"),
    (pb.FrameParams(named_coefficients={"nope": 1.0}), "named_coefficients"),
    (pb.FrameParams(coefficients=[0.0] * 6, named_coefficients={"x": 1.0}), "coefficients"),
    (pb.FrameParams(eyelids=[0.1]), "eyelids"),
    (pb.FrameParams(eyelids=[0.1, math.inf]), "eyelids"),
    (pb.FrameParams(joints={"elbow": pb.Rotation(values=[0, 0, 0])}), "joints"),
    (pb.FrameParams(joints={"jaw": pb.Rotation(values=[0, 0])}), "joints.jaw"),
    (pb.FrameParams(joints={"jaw": pb.Rotation(values=[0, 0, 0, 0, 0, 0])}), "joints.jaw"),
    (pb.FrameParams(joints={"neck": pb.Rotation(values=[math.nan, 0, 0])}), "joints.neck"),
])
def test_each_wire_problem_names_the_field_the_client_sent(avatar, msg, field):
    with pytest.raises(InvalidArgument) as e:
        params.frame(avatar, msg, list(avatar.expression_names))
    assert e.value.field == field


def test_a_named_coefficient_that_is_not_finite_is_named(avatar):
    name = avatar.expression_names[2]
    with pytest.raises(InvalidArgument) as e:
        params.frame(avatar, pb.FrameParams(named_coefficients={name: math.nan}), list(avatar.expression_names))
    assert e.value.field == f"named_coefficients.{name}"


def test_wire_cameras_equal_the_driving_file_cameras(avatar):
    cases = [
        (pb.Camera(preset="left"), "left"),
        (pb.Camera(orbit=pb.Orbit(yaw_deg=20, pitch_deg=-10, distance=0.9)),
         {"yaw": 20, "pitch": -10, "distance": 0.9}),
        (pb.Camera(opencv=pb.OpenCVCamera(k=[60, 0, 24, 0, 60, 16, 0, 0, 1], r=[1, 0, 0, 0, 1, 0, 0, 0, 1],
                                          t=[0, 0, 0.7], width=48, height=32)),
         {"K": [[60, 0, 24], [0, 60, 16], [0, 0, 1]], "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "t": [0, 0, 0.7],
          "width": 48, "height": 32}),
    ]
    for cam, value in cases:
        got = params.camera(avatar, cam, OUT)
        want = drive.parse_camera(avatar, value, OUT.width, OUT.height)
        for key in ("K", "R", "t"):
            torch.testing.assert_close(getattr(got, key), getattr(want, key))
    assert torch.equal(params.camera(avatar, None, OUT).K, drive.default_camera(avatar, 48, 32).K)


@pytest.mark.parametrize("cam,field", [
    (pb.Camera(preset="behind"), "camera.preset"),
    (pb.Camera(orbit=pb.Orbit(pitch_deg=95)), "camera.orbit.pitch_deg"),
    (pb.Camera(orbit=pb.Orbit(yaw_deg=math.nan)), "camera.orbit.yaw_deg"),
    (pb.Camera(opencv=pb.OpenCVCamera(k=[60, 0, 24, 0, -60, 16, 0, 0, 1], r=[1, 0, 0, 0, 1, 0, 0, 0, 1],
                                      t=[0, 0, 0.7], width=48, height=32)), "camera.opencv.k"),
    (pb.Camera(opencv=pb.OpenCVCamera(k=[60, 0, 24, 0, 60, 16, 0, 0, 1], r=[2, 0, 0, 0, 1, 0, 0, 0, 1],
                                      t=[0, 0, 0.7], width=48, height=32)), "camera.opencv.r"),
    (pb.Camera(opencv=pb.OpenCVCamera(k=[60, 0, 24, 0, 60, 16, 0, 0, 1], r=[1, 0, 0, 0, 1, 0, 0, 0, 1],
                                      t=[0, 0, math.inf], width=48, height=32)), "camera.opencv.t"),
    (pb.Camera(opencv=pb.OpenCVCamera(k=[60] * 8)), "camera.opencv.k"),
])
def test_each_camera_problem_names_the_wire_field(avatar, cam, field):
    with pytest.raises((InvalidArgument, FrameError)) as e:
        params.camera(avatar, cam, OUT)
    assert e.value.field == field


def test_a_camera_is_parsed_without_a_frame(avatar, monkeypatch):
    """A camera alone never builds (and throws away) a neutral frame, on the wire or in a driving file."""
    def no_frame(*args, **kwargs):
        raise AssertionError("a frame was built for a camera")

    monkeypatch.setattr(drive, "parse_frame", no_frame)
    monkeypatch.setattr(drive.Frame, "from_params", no_frame)
    params.camera(avatar, pb.Camera(preset="up"), OUT)
    drive.parse_camera(avatar, {"yaw": 10}, 48, 32)


# ------------------------------------------------------------------------------- joints: one batched call per kind
def _joint_by_joint(avatar, msg):
    """The joints of ``msg`` as service.params built them before they were batched: each joint's own array,
    conversion and float64 check, in the message's order, the first problem raised (the reference)."""
    from service.errors import some

    rotations = torch.eye(3).expand(1, avatar.num_joints, 3, 3).clone()
    for name, rot in msg.joints.items():
        if name not in avatar.joint_names:
            raise InvalidArgument(f"unknown joint {some([name])}; this avatar's joints: "
                                  f"{some(avatar.joint_names, 10)}", field="joints")
        field, values = f"joints.{name}", list(rot.values)
        if len(values) not in (3, 6):
            raise InvalidArgument(f"expected axis-angle (3 values) or 6D (6 values), got {len(values)}", field=field)
        if not all(math.isfinite(v) for v in values):
            raise InvalidArgument("values must be finite (no NaN or Infinity)", field=field)
        v = np.array([values], np.float32)
        with np.errstate(all="ignore"):
            m = torch.from_numpy(params._axis_angle_np(v) if len(values) == 3 else params._rot6d_np(v))[0]
        md = m.double()
        ok = bool(torch.isfinite(md).all())
        ok = ok and float((md @ md.T - torch.eye(3, dtype=torch.float64)).abs().max()) <= 1e-3
        if not (ok and float(torch.linalg.det(md)) > 1 - 1e-3):
            raise InvalidArgument("not a rotation: 6D needs two non-zero, non-parallel 3-vectors (the first two rows "
                                  "of the matrix); axis-angle an angle in radians of moderate size", field=field)
        rotations[0, avatar.joint_names.index(name)] = m
    return rotations


_BAD_JOINTS = [  # (name, values): each a problem of its own kind
    ("elbow", [0.0, 0.0, 0.0]), (None, [0.1, 0.2]), (None, [0.0] * 7), (None, [math.nan, 0.0, 0.0]),
    (None, [0.0, 0.0, 0.0, math.inf, 1.0, 0.0]), (None, [0.0] * 6), (None, [1.0, 0.0, 0.0, 2.0, 0.0, 0.0]),
    (None, [1e20, 0.0, 0.0]), (None, [1e300, 0.0, 0.0, 0.0, 1.0, 0.0]),
]


def _random_joints(avatar, rng, bad: bool) -> dict:
    names = list(rng.permutation(avatar.joint_names)[: rng.integers(0, avatar.num_joints + 1)])
    joints = {}
    for name in names:
        if rng.random() < 0.5:
            angle = rng.choice([1e-6, 0.1, 1.0, 3.0])
            joints[name] = (rng.uniform(-1, 1, 3) * angle).tolist()
        else:
            joints[name] = rng.normal(0, 1, 6).tolist()
    if bad:
        for _ in range(rng.integers(1, 3)):
            name, values = _BAD_JOINTS[rng.integers(len(_BAD_JOINTS))]
            joints[name or avatar.joint_names[rng.integers(avatar.num_joints)]] = values
    return {name: pb.Rotation(values=values) for name, values in joints.items()}


def test_batched_joints_are_bit_identical_to_joint_by_joint_and_fail_alike(avatar):
    """Every joint is built and checked in one batched call per kind, yet each frame's rotations are bit for bit
    the ones a call per joint gives (random axis-angle, small angles included, and 6D, mixed), and a message with
    problems fails with the error (field and message) of the first joint in the message's order that has one."""
    rng = np.random.default_rng(7)
    names = list(avatar.expression_names)
    frames = errors = 0
    for i in range(400):
        msg = pb.FrameParams(joints=_random_joints(avatar, rng, bad=i % 2 == 1))
        try:
            want = _joint_by_joint(avatar, msg)
        except InvalidArgument as e:
            with pytest.raises(InvalidArgument) as got:
                params.frame(avatar, msg, names)
            assert (got.value.field, got.value.detail) == (e.field, e.detail), list(msg.joints)
            errors += 1
            continue
        got = params.frame(avatar, msg, names).joint_rotations
        assert got.dtype == torch.float32 and torch.equal(got, want), list(msg.joints)
        frames += 1
    assert frames > 150 and errors > 150


def test_the_pose_conversions_are_render_core_rotations_to_float32_rounding():
    """The service converts a pose's joints with numpy (no torch call on the event loop, see params._axis_angle_np);
    the matrices are render_core.rotation's (torch) to a few float32 ulps, small angles exactly identity-close."""
    from render_core.rotation import axis_angle_to_matrix, rot6d_to_matrix

    rng = np.random.default_rng(3)
    for scale in (1e-6, 1e-3, 0.1, 1.0, 3.0):
        aa = (rng.uniform(-1, 1, (2000, 3)) * scale).astype(np.float32)
        got = params._axis_angle_np(aa)
        assert got.dtype == np.float32
        np.testing.assert_allclose(got, axis_angle_to_matrix(torch.from_numpy(aa)).numpy(), rtol=0, atol=1e-6)
    r6 = rng.normal(0, 1, (2000, 6)).astype(np.float32)
    got = params._rot6d_np(r6)
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, rot6d_to_matrix(torch.from_numpy(r6)).numpy(), rtol=0, atol=2e-5)


def test_a_pose_is_built_without_torch_calls_that_give_up_the_gil(avatar, monkeypatch):
    """Building a frame from a message (coefficients, joints of both kinds, eyelids, a background) calls no torch
    function but torch.from_numpy: most torch calls release the GIL and wait up to the switch interval (5 ms) to get
    it back while another Python thread runs, which stalls the event loop that builds every pose."""
    import sys

    calls = []

    def hook(frame, event, arg):
        if event == "c_call" and (getattr(arg, "__module__", None) or "").startswith("torch") \
                or event == "c_call" and type(getattr(arg, "__self__", None)).__module__.startswith("torch"):
            calls.append(getattr(arg, "__qualname__", getattr(arg, "__name__", repr(arg))))

    msg = pb.FrameParams(coefficients=[0.1] * avatar.num_expressions, eyelids=[0.2, 0.3], joints={
        avatar.joint_names[1]: pb.Rotation(values=[0.1, 0.2, 0.0]),
        avatar.joint_names[2]: pb.Rotation(values=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0])})
    sys.setprofile(hook)
    try:
        frame = params.frame(avatar, msg, list(avatar.expression_names))
        background = params.background(pb.Color(r=0.5, g=0.5, b=0.5))
    finally:
        sys.setprofile(None)
    assert frame.joint_rotations.dtype == torch.float32 and background.dtype == torch.float32
    assert calls and {c.rsplit(".", 1)[-1] for c in calls} == {"from_numpy"}, calls


def test_a_problem_names_the_first_joint_in_the_message_order(avatar):
    """The batch groups the axis-angle joints before the 6D ones; the error still names the first joint of the
    message with a problem, of whichever kind, and a problem found before the batch (an unknown name, the wrong
    count, NaN) does not hide a joint before it that is not a rotation."""
    parallel, nan_aa, huge_aa = [1.0, 0.0, 0.0, 2.0, 0.0, 0.0], [math.nan, 0.0, 0.0], [1e20, 0.0, 0.0]
    for a, b in (("jaw", "neck"), ("neck", "jaw"), ("eye_l", "root"), ("root", "eye_l")):
        msg = pb.FrameParams(joints={a: pb.Rotation(values=parallel), b: pb.Rotation(values=huge_aa)})
        first = list(msg.joints)[0]  # the message's order (the map's), not the order given here
        with pytest.raises(InvalidArgument) as e:
            params.frame(avatar, msg, list(avatar.expression_names))
        assert e.value.field == f"joints.{first}" and e.value.detail.startswith("not a rotation")
        msg = pb.FrameParams(joints={a: pb.Rotation(values=parallel), b: pb.Rotation(values=nan_aa)})
        first = list(msg.joints)[0]
        with pytest.raises(InvalidArgument) as e:
            params.frame(avatar, msg, list(avatar.expression_names))
        assert e.value.field == f"joints.{first}"
        assert e.value.detail.startswith("not a rotation" if first == a else "values must be finite")


def test_joints_are_converted_and_checked_once_per_kind_not_per_joint(avatar, monkeypatch):
    calls = []

    def counted(fn):
        def wrapper(x):
            calls.append((fn.__name__, tuple(x.shape)))
            return fn(x)
        return wrapper

    monkeypatch.setattr(params, "_axis_angle_np", counted(params._axis_angle_np))
    monkeypatch.setattr(params, "_rot6d_np", counted(params._rot6d_np))
    joints = {"root": [0.1, 0, 0], "neck": [0, 0.2, 0], "jaw": [1, 0, 0, 0, 1, 0], "eye_l": [0, 0, 0.1],
              "eye_r": [0, 1, 0, -1, 0, 0]}
    frame = params.frame(avatar, pb.FrameParams(joints={n: pb.Rotation(values=v) for n, v in joints.items()}),
                         list(avatar.expression_names))
    assert sorted(calls) == [("_axis_angle_np", (3, 3)), ("_rot6d_np", (2, 6))]
    frame.check(avatar)
    calls.clear()
    params.frame(avatar, pb.FrameParams(), list(avatar.expression_names))
    assert calls == []
