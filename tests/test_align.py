"""Test-time alignment (render_core/evaluation/align.py): the rigid motion folds into the camera exactly, a known
pose error is recovered, and `eval --align` reports the aligned and the unaligned scores."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from render_core.camera import Cameras
from render_core.deform import Frame, deform
from render_core.evaluation.align import _render, align_frames, moved_camera
from render_core.evaluation.metrics import psnr
from render_core.raster import differentiable
from render_core.renderer import AvatarRenderer
from render_core.rotation import axis_angle_to_matrix

SIZE = 96


@pytest.fixture(scope="module")
def demo():
    from render_core.bundle import read_bundle
    from render_core.facemodel.open_head import DEMO_AVATAR
    from render_core.tools.bench import framed_camera

    avatar = read_bundle(DEMO_AVATAR).to(torch.float32)
    return avatar, framed_camera(avatar, SIZE)


def _frame(avatar, seed: int = 0) -> Frame:
    g = torch.Generator().manual_seed(seed)
    return Frame.from_params(avatar, expression=0.3 * torch.rand(1, avatar.num_expressions, generator=g))


def _render_with(avatar, frame, cams) -> torch.Tensor:
    return AvatarRenderer(avatar, "native").render(frame, cams, background=torch.zeros(3)).rgb


def test_the_head_motion_folds_into_the_camera_exactly(demo):
    """Moving the head by (w, u) about its centre and seeing it with the camera equals the unmoved head seen by
    the moved camera: what makes the aligned tracking a plain tracking any backend renders."""
    avatar, cams = demo
    frame = _frame(avatar)
    w, u = torch.tensor([[0.02, -0.03, 0.01]]), torch.tensor([[0.004, -0.002, 0.003]])
    moved_head = _render(avatar, cams, deform(avatar, frame), w, u, differentiable("native")).detach()
    centre = deform(avatar, frame).means.mean(1)
    R, t = moved_camera(cams, w, u, centre)
    seen = _render_with(avatar, frame, Cameras(cams.K, R, t, cams.width, cams.height))
    assert psnr(moved_head.double().clamp(0, 1), seen.double().clamp(0, 1)) > 60.0
    assert psnr(seen.double(), _render_with(avatar, frame, cams).double()) < 30.0  # it did move


def test_alignment_recovers_a_known_pose_error(demo):
    avatar, cams = demo
    frame = _frame(avatar, seed=1)
    target = _render_with(avatar, frame, cams).clamp(0, 1)
    # the tracking is off by 1.1 degrees and 3 mm
    Q = axis_angle_to_matrix(torch.tensor([[0.012, -0.015, 0.008]]))
    off = Cameras(cams.K, cams.R @ Q, cams.t + torch.tensor([[0.003, -0.002, 0.0]]), cams.width, cams.height)
    before = psnr(_render_with(avatar, frame, off).double().clamp(0, 1), target.double())
    a = align_frames(avatar, frame, off, target, iterations=60)
    fixed = Cameras(cams.K, torch.from_numpy(a.R), torch.from_numpy(a.t), cams.width, cams.height)
    after = psnr(_render_with(avatar, frame, fixed).double().clamp(0, 1), target.double())
    assert after > before + 8.0, (before, after)
    # the head's points land where the true camera puts them: within a tenth of a pixel
    x = deform(avatar, frame).means[0]

    def project(c: Cameras) -> torch.Tensor:
        xc = x @ c.R[0].T + c.t[0]
        return xc[:, :2] / xc[:, 2:] * c.K[0, 0, 0]

    assert (project(fixed) - project(cams)).norm(dim=-1).median() < 0.1
    assert (project(off) - project(cams)).norm(dim=-1).median() > 1.0
    np.testing.assert_array_equal(a.expression, frame.expression.numpy())  # not asked to move


def test_alignment_refuses_no_steps(demo):
    avatar, cams = demo
    frame = _frame(avatar)
    with pytest.raises(Exception, match="at least 1"):
        align_frames(avatar, frame, cams, torch.zeros(1, SIZE, SIZE, 3), iterations=0)


def test_eval_align_reports_aligned_and_unaligned_scores(head, tmp_path, capsys):
    from render_core.bundle import write_bundle
    from render_core.data.generate import synth_dataset
    from render_core.data.portable import read_dataset
    from render_core.tools.cli import main as cli
    from render_core.train.initialize import init_avatar

    synth_dataset(tmp_path / "ds", frames=4, size=48, seed=2, facemodel=head)
    avatar = init_avatar(head, gaussians=600, mouth=20, opacity=0.9, seed=0)
    write_bundle(avatar, tmp_path / "a.bsplat")
    assert cli(["eval", "--bundle", str(tmp_path / "a.bsplat"), "--data", str(tmp_path / "ds"), "--split", "all",
                "--align", "3", "--align-expressions", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["aligned"] == {"iterations": 3, "expressions": True}
    assert set(r["unaligned"]) == {"psnr", "ssim", "psnr_head"} and math.isfinite(r["unaligned"]["psnr_head"])
    assert len(r["per_frame"]) == len(read_dataset(tmp_path / "ds")) == 4
    assert all("psnr_head_unaligned" in f for f in r["per_frame"])
    assert any("aligned" in n for n in r["notes"])
    assert cli(["eval", "--bundle", str(tmp_path / "a.bsplat"), "--data", str(tmp_path / "ds"), "--split", "all",
                "--json"]) == 0
    plain = json.loads(capsys.readouterr().out)
    assert "aligned" not in plain and "unaligned" not in plain
    assert plain["psnr_head"] == pytest.approx(r["unaligned"]["psnr_head"], abs=1e-9)
