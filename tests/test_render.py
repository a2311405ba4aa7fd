"""The render() entry point on deformed avatars: rigid-motion equivalence, broadcasting, backend selection."""

import pytest
import torch

from render_core.camera import Cameras, orbit
from render_core.deform import Frame, deform
from render_core.errors import ShapeError
from render_core.evaluation.metrics import psnr
from render_core.raster import backend_names, render
from render_core.rotation import axis_angle_to_matrix


def test_global_head_rotation_equals_inverse_camera_rotation(avatar):
    cam = orbit(10.0, 5.0, width=96, height=96)
    aa = torch.tensor([[0.15, -0.35, 0.1]])
    rotated = render(deform(avatar, Frame.from_params(avatar, joints={"root": aa})), cam, mode=avatar.raster_mode)

    # Rotating the head about the root joint p by R is seeing the rest head from a camera moved by R^-1:
    # Rc (R (x - p) + p) + tc = (Rc R) x + Rc (p - R p) + tc.
    R = axis_angle_to_matrix(aa)[0]
    p = avatar.joint_positions[avatar.joint_index("root")]
    moved = Cameras(cam.K, cam.R @ R, (cam.R[0] @ (p - R @ p) + cam.t[0])[None], cam.width, cam.height)
    still = render(deform(avatar, Frame.neutral(avatar)), moved, mode=avatar.raster_mode)

    assert float(rotated.alpha.mean()) > 0.1  # the head is in view
    assert psnr(rotated.rgb, still.rgb) >= 40.0
    assert psnr(rotated.alpha, still.alpha) >= 40.0
    # And the rotation is not a no-op: the unrotated head from the original camera looks different.
    plain = render(deform(avatar, Frame.neutral(avatar)), cam, mode=avatar.raster_mode)
    assert psnr(rotated.rgb, plain.rgb) < 30.0


def test_one_splat_set_broadcasts_to_several_cameras(avatar):
    splats = deform(avatar, Frame.neutral(avatar))
    cams = orbit([0.0, 30.0], width=48, height=40)
    both = render(splats, cams)
    assert both.rgb.shape == (2, 40, 48, 3) and both.alpha.shape == (2, 40, 48) and both.depth.shape == (2, 40, 48)
    for i in range(2):
        single = render(splats, cams.index(i))
        assert torch.allclose(both.rgb[i], single.rgb[0], atol=1e-6)
    assert not torch.allclose(both.rgb[0], both.rgb[1])


def test_background_shows_where_alpha_is_zero(avatar):
    splats = deform(avatar, Frame.neutral(avatar))
    bg = torch.tensor([0.2, 0.4, 0.9])
    out = render(splats, orbit(0.0, width=64, height=64), background=bg)
    empty = out.alpha == 0
    assert empty.any() and (out.alpha > 0.9).any()
    assert torch.allclose(out.rgb[empty], bg.expand(int(empty.sum()), 3))


def test_unknown_backend_and_mismatched_batches_are_errors(avatar):
    splats = deform(avatar, Frame.from_params(avatar, expression=torch.zeros(2, avatar.num_expressions)))
    with pytest.raises(ValueError, match="reference"):
        render(splats, orbit(0.0, width=8, height=8), backend="nope")
    with pytest.raises(ShapeError, match="cameras"):
        render(splats, orbit([0.0, 1.0, 2.0], width=8, height=8))


@pytest.mark.parametrize("backend", backend_names())
def test_every_backend_refuses_an_unknown_raster_mode_naming_the_modes(avatar, backend):
    splats = deform(avatar, Frame.neutral(avatar))
    with pytest.raises(ValueError, match="classic.*antialiased.*'soft'"):
        render(splats, orbit(0.0, width=8, height=8), backend=backend, mode="soft")
