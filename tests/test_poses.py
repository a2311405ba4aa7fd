"""Per-frame head poses refined with the avatar (render_core/train/poses.py, `train --refine-poses`)."""

from __future__ import annotations

import pytest
import torch

from render_core.camera import Cameras
from render_core.data.generate import synth_dataset
from render_core.evaluation.metrics import psnr
from render_core.train import Trainer, get_preset
from render_core.train.poses import FramePoses
from render_core.train.trainer import forward

TOY = get_preset("tiny").with_(gaussians=400, mouth=40, sh_every=15, checkpoint_every=1000, log_every=1,
                               final_eval_frames=2, xyz_decay_steps=50, densify=False)


@pytest.fixture(scope="module")
def toy(head, tmp_path_factory):
    out = tmp_path_factory.mktemp("poses") / "data"
    synth_dataset(out, frames=6, size=64, seed=1, facemodel=head)
    return out


def test_a_frame_moves_only_when_it_is_drawn():
    poses = FramePoses(4)
    w, u = poses.motion(2)
    loss = (w * torch.tensor([[1.0, -2.0, 0.5]])).sum() + (u * 3.0).sum() + poses.prior()
    loss.backward()
    poses.step()
    assert torch.count_nonzero(poses.wu[[0, 1, 3]]) == 0 and torch.count_nonzero(poses.m[[0, 1, 3]]) == 0
    assert (poses.wu[2, :3] * torch.tensor([1.0, -2.0, 0.5])).sum() < 0  # down the gradient
    assert (poses.wu[2, 3:] < 0).all() and poses.steps.tolist() == [0, 0, 1, 0]
    # Adam's first step is the learning rate, per parameter
    torch.testing.assert_close(poses.wu[2].abs(), poses.lr)
    before = poses.wu.clone()
    poses.motion(1)
    poses.step()  # no gradient reached it: nothing moves
    assert torch.equal(poses.wu, before)


def test_state_round_trip_and_refusal():
    poses = FramePoses(3)
    w, u = poses.motion(0)
    (w.sum() + u.sum()).backward()
    poses.step()
    other = FramePoses(3)
    other.load_state(poses.state())
    for key, value in poses.state().items():
        assert torch.equal(value, other.state()[key]), key
    with pytest.raises(ValueError, match="wu"):
        FramePoses(4).load_state(poses.state())


def test_the_corrections_fold_into_the_cameras(toy, head, tmp_path):
    """A trained correction renders the same through forward()'s motion as through the folded camera."""
    t = Trainer(toy, tmp_path / "w", TOY.with_(refine_poses=True, refine_poses_from=0), iterations=1, seed=0,
                facemodel=head)
    t.step()
    poses = t._poses
    j = int(torch.nonzero(poses.steps)[0])
    assert torch.count_nonzero(poses.wu[j]) == 6
    poses.wu[j] = torch.tensor([0.02, -0.01, 0.015, 0.003, -0.002, 0.001])  # a visible correction
    frame, cams = t._frames, t._cams
    one = type(frame)(frame.expression[j:j + 1], frame.joint_rotations[j:j + 1],
                      None if frame.eyelids is None else frame.eyelids[j:j + 1])
    cam = cams.index(j)
    with torch.no_grad():
        moved, _, posed = forward(t.model, one, cam, motion=(poses.wu[j:j + 1, :3], poses.wu[j:j + 1, 3:]))
        plain, _, _ = forward(t.model, one, cam)
        # every frame's camera folded (the pivots of the others do not matter here), frame j's taken
        R, tt = poses.cameras(cams, posed.means.mean(1).expand(len(poses), 3))
        folded, _, _ = forward(t.model, one, Cameras(cam.K, torch.from_numpy(R[j:j + 1]),
                                                     torch.from_numpy(tt[j:j + 1]), cam.width, cam.height))
    assert psnr(moved.double().clamp(0, 1), folded.double().clamp(0, 1)) > 60.0
    assert psnr(moved.double().clamp(0, 1), plain.double().clamp(0, 1)) < 40.0


def test_training_refines_poses_and_resumes_them(toy, head, tmp_path):
    cfg = TOY.with_(refine_poses=True, refine_poses_from=2)
    straight = Trainer(toy, tmp_path / "a", cfg, iterations=6, seed=3, facemodel=head)
    straight.run()
    summary = straight.summary()["poses"]
    assert summary["frames"] == 5 and summary["rotation_deg"]["max"] > 0
    assert int(straight._poses.steps.sum()) == 4  # iterations 3..6
    first = Trainer(toy, tmp_path / "b", cfg, iterations=6, seed=3, facemodel=head)
    for _ in range(4):
        first.step()
    first.checkpoint()
    second = Trainer(toy, tmp_path / "b", cfg, iterations=6, seed=3, facemodel=head)
    assert second.resume()
    while second.iteration < second.total:
        second.step()
    for key, value in straight._poses.state().items():
        assert torch.equal(value, second._poses.state()[key]), key
    off = Trainer(toy, tmp_path / "c", TOY, iterations=2, seed=3, facemodel=head)
    off.run()
    assert off.summary()["poses"] is None



def test_expression_corrections_move_only_the_drawn_frame_under_their_prior():
    poses = FramePoses(3, expressions=4)
    assert poses.wu.shape == (3, 10)
    poses.motion(1)
    base = torch.tensor([[0.2, 0.0, 0.5, 1.0]])
    corrected = poses.expression(base)
    assert torch.equal(corrected, base)  # no correction yet
    (corrected * torch.tensor([[1.0, -1.0, 0.0, 2.0]])).sum().backward()
    poses.step()
    assert torch.count_nonzero(poses.wu[[0, 2]]) == 0
    de = poses.wu[1, 6:]
    assert de[0] < 0 < de[1] and de[2] == 0 and de[3] < 0 and torch.count_nonzero(poses.wu[1, :6]) == 0
    frame, (w, u) = poses.applied(1, _frame(base))
    torch.testing.assert_close(frame.expression, base + de)
    assert w.shape == u.shape == (1, 3)
    assert poses.summary()["expression"]["max"] > 0
    # the prior alone pulls a correction back towards the tracker's coefficients
    fresh = FramePoses(3, expressions=4)
    fresh.wu[1, 6:] = torch.tensor([0.3, -0.3, 0.0, 0.1])
    fresh.motion(1)
    fresh.prior().backward()
    fresh.step()
    torch.testing.assert_close(fresh.wu[1, 6:], torch.tensor([0.3, -0.3, 0.0, 0.1]) - fresh.lr[6:] * torch.tensor(
        [1.0, -1.0, 0.0, 1.0]))
    assert "expression" not in FramePoses(3).summary()


def _frame(expression):
    from render_core.deform import Frame

    return Frame(expression, torch.zeros(1, 5, 3, 3), None)


def test_training_refines_expressions_and_the_final_psnr_renders_them(toy, head, tmp_path):
    cfg = TOY.with_(refine_poses=True, refine_expressions=True, refine_poses_from=0)
    t = Trainer(toy, tmp_path / "e", cfg, iterations=4, seed=3, facemodel=head)
    t.run()
    poses = t._poses
    K = t._frames.expression.shape[1]
    assert poses.wu.shape == (5, 6 + K) and poses.expressions == K
    drawn = torch.nonzero(poses.steps).flatten()
    assert torch.count_nonzero(poses.wu[drawn, 6:]) > 0
    assert t.summary()["poses"]["expression"]["mean_abs"] > 0
    final = t.final_psnr()["psnr"]
    poses.wu[:, 6:] += 0.5  # a large correction everywhere: the final figure must render it
    assert t.final_psnr()["psnr"] != final


def test_the_corrections_learning_rate_decays_from_their_start_to_the_final_fraction():
    """refine_lr: 1 until refine_poses_from, then an exponential decay to refine_lr_final at the last iteration
    (1.0: constant); FramePoses.step(scale) takes that fraction of the learning rates."""
    from render_core.train.trainer import refine_lr

    cfg = TOY.with_(refine_poses_from=100, refine_lr_final=0.04)
    assert refine_lr(cfg, 50, 1100) == 1.0 and refine_lr(cfg, 100, 1100) == 1.0
    assert refine_lr(cfg, 1100, 1100) == pytest.approx(0.04)
    assert refine_lr(cfg, 600, 1100) == pytest.approx(0.2)  # halfway: the geometric mean
    assert refine_lr(cfg.with_(refine_lr_final=1.0), 900, 1100) == 1.0
    poses = FramePoses(2)
    w, u = poses.motion(1)
    (w.sum() + u.sum()).backward()
    poses.step(0.25)
    torch.testing.assert_close(poses.wu[1].abs(), 0.25 * poses.lr)


def test_training_with_the_decay_ends_with_smaller_corrections_on_a_true_tracking(toy, head, tmp_path):
    """On the toy's TRUE tracking, whatever the corrections learn is noise: with the decay (the default) they end
    closer to zero than at a constant rate (refine_lr_final 1.0), the same frames drawn in the same order."""
    runs = {}
    for final in (1.0, TOY.refine_lr_final):
        t = Trainer(toy, tmp_path / str(final), TOY.with_(refine_poses=True, refine_poses_from=0,
                                                          refine_lr_final=final), iterations=30, seed=3,
                    facemodel=head)
        t.run()
        runs[final] = t._poses.wu[:, :3].norm(dim=1)
    assert TOY.refine_lr_final < 1.0
    assert float(runs[TOY.refine_lr_final].mean()) < 0.8 * float(runs[1.0].mean()), runs
