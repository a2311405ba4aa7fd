"""service.params: the wire's frame and camera built directly from the messages, each problem named by the wire
field the client sent, and the same frames and cameras as a driving file's line gives."""

import math

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
