import pytest
import torch

from render_core.camera import Cameras, front_camera, look_at, orbit
from render_core.errors import FrameError


def test_front_camera_is_opencv_looking_at_the_face():
    cam = front_camera(64, 48, distance=0.6)
    assert torch.allclose(cam.centres, torch.tensor([[0.0, 0.0, 0.6]]), atol=1e-6)
    # world origin projects to the principal point, in front of the camera
    p = cam.R[0] @ torch.zeros(3) + cam.t[0]
    assert p[2] > 0
    # world +y (up) appears towards smaller image y (OpenCV y points down); world +x to the right
    up = cam.R[0] @ torch.tensor([0.0, 1.0, 0.0])
    right = cam.R[0] @ torch.tensor([1.0, 0.0, 0.0])
    assert up[1] < 0 and right[0] > 0


def test_orbit_and_look_at_give_rotations_towards_the_target():
    cams = orbit([0.0, 90.0, -45.0], [0.0, 10.0, -20.0], distance=0.8)
    assert torch.allclose(cams.centres.norm(dim=-1), torch.full((3,), 0.8), atol=1e-5)
    assert torch.allclose(torch.det(cams.R), torch.ones(3), atol=1e-5)
    z_cam = (cams.R @ torch.zeros(3, 3, 1)).squeeze(-1) + cams.t
    assert torch.allclose(z_cam[:, :2], torch.zeros(3, 2), atol=1e-5)  # target on the optical axis
    assert cams.centres[1, 0] > 0.7  # yaw 90 moves the camera to +x
    R, t = look_at(torch.tensor([1.0, 0.0, 0.0]), torch.zeros(3))
    assert torch.allclose(R @ R.T, torch.eye(3), atol=1e-6)


def test_resize_scales_intrinsics_and_dict_round_trip():
    cam = front_camera(512, 512)
    small = cam.resized(128, 64)
    assert small.width == 128 and small.height == 64
    assert torch.allclose(small.K[0, 0], cam.K[0, 0] / 4) and torch.allclose(small.K[0, 1, 1], cam.K[0, 1, 1] / 8)
    back = Cameras.from_dict(cam.to_dict())
    assert torch.equal(back.K, cam.K) and torch.equal(back.R, cam.R) and torch.equal(back.t, cam.t)


def test_bad_cameras_are_named():
    with pytest.raises(FrameError, match="camera.R"):
        Cameras(torch.eye(3)[None], torch.eye(3)[None].repeat(2, 1, 1), torch.zeros(1, 3), 8, 8)
    with pytest.raises(FrameError, match="finite"):
        Cameras(torch.eye(3)[None], torch.eye(3)[None], torch.tensor([[0.0, float("nan"), 0.0]]), 8, 8)
    with pytest.raises(FrameError, match="camera"):
        Cameras.from_dict({"K": [[1, 0]], "width": 4, "height": 4})
