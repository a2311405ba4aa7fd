"""Pruning by contribution (render_core.train.prune): the score, the removal, the trainer's schedule and resume."""

from __future__ import annotations

import json
import math

import pytest
import torch

from render_core.camera import Cameras
from render_core.data.frames import frame_inputs
from render_core.data.generate import synth_dataset
from render_core.deform import Frame, deform
from render_core.evaluation.align import moved_splats
from render_core.raster import ShadedSplats, reference
from render_core.rotation import axis_angle_to_matrix, matrix_to_quat
from render_core.tools.cli import build_parser
from render_core.train import TrainableAvatar, Trainer, get_preset, train
from render_core.train.densify import DensifyStrategy
from render_core.train.initialize import init_avatar
from render_core.train.presets import PRESETS
from render_core.train.prune import (
    FIXED_PIXELS,
    ContributionPruner,
    blend_weights,
    contribution,
    footprints,
    prune_lowest,
    prune_mouth_lowest,
    step_fraction,
)
from render_core.train.trainer import make_optimizer, raster_step

# A toy schedule: no densification (the counts are the pruning's alone), the SH ramp and xyz decay over the run.
TOY = get_preset("tiny").with_(gaussians=400, mouth=40, sh_every=40, checkpoint_every=1000, log_every=10,
                               final_eval_frames=2, xyz_decay_steps=200, densify=False)


def reference_step(splats, cameras, background=None, mode="classic", *, threads=0):
    """The reference rasterizer as a differentiable training step."""
    out = reference.rasterize(splats, cameras, background, mode)
    return out.rgb, out.alpha


def camera(width: int = 48, height: int = 40, f: float = 60.0) -> Cameras:
    K = torch.tensor([[[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]]])
    return Cameras(K, torch.eye(3)[None], torch.zeros(1, 3), width, height)


def scene(n: int = 14, seed: int = 2) -> ShadedSplats:
    """Overlapping Gaussians in front of :func:`camera`, some nearly opaque (so the transmittance stop cuts pixels'
    lists short), one behind the camera and one off screen."""
    g = torch.Generator().manual_seed(seed)
    means = torch.cat([(torch.rand(n, 2, generator=g) - 0.5) * 0.5, 1.0 + torch.rand(n, 1, generator=g)], 1)
    means[0], means[1] = torch.tensor([0.0, 0.0, -1.0]), torch.tensor([5.0, 0.0, 1.0])
    means[2:5, :2] = 0.01 * torch.arange(3.0)[:, None]  # a stack at the centre
    quats = matrix_to_quat(axis_angle_to_matrix(torch.randn(n, 3, generator=g)))
    scales = 0.02 + 0.06 * torch.rand(n, 3, generator=g)
    opac = 0.3 + 0.6 * torch.rand(n, generator=g)
    opac[2:5] = 0.998
    return ShadedSplats(means[None], quats[None], scales[None], opac[None], torch.rand(1, n, 3, generator=g))


def brute_force_weights(splats: ShadedSplats, cameras: Cameras) -> torch.Tensor:
    """sum over pixels of alpha T per Gaussian [N], composited pixel by pixel in float64 from section 9's rules:
    alpha = min(o exp(-sigma), 0.999) where sigma >= 0 and alpha >= 1/255, front to back by (depth, index), each
    pixel's list cut where the next transmittance would be <= 1e-4. Every pixel is tested against every
    Gaussian: with opacities < 0.999 the eligible ellipse lies inside the box whose tiles section 9 visits."""
    s = splats.to(torch.float64)
    proj = reference.project(s.means, s.quats, s.scales, s.opacities, cameras.to(torch.float64))
    vis = proj.visible[0]
    ys, xs = torch.meshgrid(torch.arange(cameras.height), torch.arange(cameras.width), indexing="ij")
    px, py = xs.reshape(-1, 1) + 0.5, ys.reshape(-1, 1) + 0.5
    m, (a, b, c) = proj.means2d[0].detach(), proj.conics[0].detach().unbind(-1)
    dx, dy = m[:, 0] - px, m[:, 1] - py
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy  # [P, N]
    alpha = torch.clamp(proj.opacities[0].detach() * torch.exp(-sigma), max=0.999)
    ok = (sigma >= 0) & (alpha >= 1 / 255) & vis
    n = s.means.shape[1]
    order = sorted(range(n), key=lambda i: (float(proj.depths[0, i]), i))
    T = torch.ones(len(px), dtype=torch.float64)
    done = torch.zeros(len(px), dtype=torch.bool)
    out = torch.zeros(n, dtype=torch.float64)
    for i in order:
        a_i = torch.where(ok[:, i] & ~done, alpha[:, i], 0.0)
        nxt = T * (1 - a_i)
        stop = (a_i > 0) & (nxt <= 1e-4)
        take = (a_i > 0) & ~stop
        out[i] = (a_i * T)[take].sum()
        T = torch.where(take, nxt, T)
        done |= stop
    return out


@pytest.mark.parametrize("step", ["native", "reference"])
def test_blend_weights_are_the_brute_force_sum_of_alpha_t(step):
    splats, cams = scene(), camera()
    want = brute_force_weights(splats, cams)
    rasterize = raster_step("cpu") if step == "native" else reference_step
    got = blend_weights(splats, cams, rasterize)
    assert got.shape == (1, 14)
    assert float(want[0]) == float(want[1]) == 0 and float(want[3]) > 0  # behind, off screen; a stacked one
    torch.testing.assert_close(got[0].double(), want, rtol=2e-4, atol=1e-4)
    # With every colour 1 and a black background the image is the alpha map: the weights sum to its total.
    rgb, alpha = rasterize(ShadedSplats(*list(splats.tensors().values())[:4], torch.ones(1, 14, 3)), cams)
    assert math.isclose(float(got.sum()), float(alpha.sum()), rel_tol=1e-4)


@pytest.fixture(scope="module")
def data(head, tmp_path_factory):
    """A 64 x 64 synthetic dataset of 12 frames on the open head."""
    out = tmp_path_factory.mktemp("prune") / "data"
    synth_dataset(out, frames=12, size=64, seed=1, facemodel=head)
    return out


def three_frames(head, data):
    """A 300-Gaussian untrained avatar's model on the open head and three training frames of ``data``."""
    from render_core.data import read_dataset

    av = init_avatar(head, gaussians=300, mouth=30, seed=4, opacity=0.5)
    tracking = read_dataset(data).tracking
    return (TrainableAvatar.from_facemodel(av, head), *frame_inputs(av, tracking, list(tracking.train)[:3]))


def test_contribution_is_the_face_gaussians_weights_summed_over_frames(head, data):
    model, frames, cams = three_frames(head, data)
    got = contribution(model, frames, cams, raster_step("cpu"))
    # Frames whose heads training moves (refined poses): scored as training renders them.
    motions = torch.tensor([[0.0, 0.05, 0.0, 0.01, 0.0, 0.0]]).repeat(3, 1)
    got_moved = contribution(model, frames, cams, raster_step("cpu"), motions=motions)
    want, want_moved = torch.zeros(300, dtype=torch.float64), torch.zeros(300, dtype=torch.float64)
    for j in range(3):  # the dense blend of the exported avatar, the reference rasterizer
        frame = Frame(frames.expression[j:j + 1], frames.joint_rotations[j:j + 1],
                      None if frames.eyelids is None else frames.eyelids[j:j + 1])
        splats = deform(model.to_avatar(), frame)
        want += blend_weights(splats, cams.index(j), reference_step)[0, :300].double()
        moved = moved_splats(splats, cams.index(j), motions[j:j + 1, :3], motions[j:j + 1, 3:])
        want_moved += blend_weights(moved, cams.index(j), reference_step)[0, :300].double()
    assert float(want.sum()) > 10 and int((want > 0).sum()) > 100
    torch.testing.assert_close(got, want, rtol=1e-3, atol=2e-3)
    torch.testing.assert_close(got_moved, want_moved, rtol=1e-3, atol=2e-3)
    assert float((got_moved - got).abs().sum()) > 0.1 * float(got.sum())  # the motion matters


def test_footprints_are_the_pixels_a_splat_reaches_alpha_1_over_255():
    cams = camera(width=200, height=200, f=100.0)
    # Isotropic splats 2 m away: sigma 0.02 m -> 1 px, 0.1 m -> 5 px (0.3 px^2 of blur on the diagonal).
    means = torch.tensor([[[0.0, 0.0, 2.0], [0.1, 0.0, 2.0], [0.0, 0.1, 2.0], [0.0, 0.0, -1.0]]])
    scales = torch.tensor([0.02, 0.1, 0.1, 0.1])[None, :, None].expand(1, 4, 3)
    opac = torch.tensor([[0.9, 0.9, 0.02, 0.9]])
    quats = torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(1, 4, 4)
    got = footprints(ShadedSplats(means, quats, scales, opac, torch.zeros(1, 4, 3)), cams)[0]
    for i, (sigma_px, o) in enumerate([(1.0, 0.9), (5.0, 0.9), (5.0, 0.02)]):
        extent2 = min(2 * math.log(255 * o), 3.33 ** 2)
        var = sigma_px ** 2 + 0.3
        assert float(got[i]) == pytest.approx(math.pi * extent2 * var, rel=5e-3)  # off axis: skewed a little
        # Every pixel whose alpha reaches 1/255 lies in it: count them on the pixel grid.
        d2 = ((torch.arange(200.0) + 0.5 - 100 - [0, 50, 0][i]) ** 2)[None] + \
             ((torch.arange(200.0) + 0.5 - 100 - [0, 0, 50][i]) ** 2)[:, None]
        inside = (o * torch.exp(-0.5 * d2 / var) >= 1 / 255) & (d2 <= 3.33 ** 2 * var)
        assert int(inside.sum()) == pytest.approx(float(got[i]), rel=0.15, abs=3)
    assert float(got[3]) == 0  # behind the camera: culled, costs nothing


def test_efficiency_scores_the_weight_per_pixel_paid_for(head, data):
    model, frames, cams = three_frames(head, data)
    weight = contribution(model, frames, cams, raster_step("cpu"))
    got = contribution(model, frames, cams, raster_step("cpu"), by="efficiency")
    cost = torch.full((300,), 3 * FIXED_PIXELS, dtype=torch.float64)
    with torch.no_grad():
        avatar = model.avatar(0, detach=True, deltas=False)
    for j in range(3):
        frame = Frame(frames.expression[j:j + 1], frames.joint_rotations[j:j + 1],
                      None if frames.eyelids is None else frames.eyelids[j:j + 1])
        cost += footprints(deform(model.to_avatar(), frame), cams.index(j), avatar.raster_mode)[0, :300].double()
    torch.testing.assert_close(got, weight / cost, rtol=1e-3, atol=1e-6)
    # Not the same order as the weight alone: big faint Gaussians rank lower, small bright ones higher.
    assert not torch.equal(torch.argsort(got)[:100].sort().values, torch.argsort(weight)[:100].sort().values)
    with pytest.raises(ValueError, match="prune_by"):
        contribution(model, frames, cams, raster_step("cpu"), by="size")


def test_peak_scores_the_largest_weight_in_any_one_frame(head, data):
    model, frames, cams = three_frames(head, data)
    summed = contribution(model, frames, cams, raster_step("cpu"))
    got = contribution(model, frames, cams, raster_step("cpu"), by="peak")
    each = torch.stack([contribution(model, Frame(frames.expression[j:j + 1], frames.joint_rotations[j:j + 1],
                                                  None if frames.eyelids is None else frames.eyelids[j:j + 1]),
                                     cams.index(j), raster_step("cpu")) for j in range(3)])
    torch.testing.assert_close(each.sum(0), summed)  # the frames scored one at a time
    torch.testing.assert_close(got, each.amax(0))
    assert float((got - summed).abs().max()) > 0.1 * float(summed.max())  # not the sum
    # Gaussians that matter in one frame rank above ones with a larger sum spread over the frames: the lowest 100
    # by each score differ.
    assert not torch.equal(torch.argsort(got)[:100].sort().values, torch.argsort(summed)[:100].sort().values)


def stepped_model(head):
    """A 200 + 20 Gaussian model, its optimizer after one step on random gradients (Adam moments set), and the
    generator that made them."""
    av = init_avatar(head, gaussians=200, mouth=20, seed=4)
    model = TrainableAvatar.from_facemodel(av, head)
    opt = make_optimizer(model, TOY)
    g = torch.Generator().manual_seed(1)
    for p in model.parameters():
        p.grad = torch.randn(p.shape, generator=g)
    opt.step()
    return model, opt, g


def test_prune_lowest_keeps_the_survivors_state(head):
    model, opt, g = stepped_model(head)
    strategy = DensifyStrategy(200, 0.1)
    strategy.grad_accum = torch.rand(200, generator=g)
    psi = torch.rand(1, model.num_expressions, generator=g)
    with torch.no_grad():
        before = model.blend(psi)
    moments = opt.state[model.means]["exp_avg"].clone()
    accum = strategy.grad_accum.clone()
    score = torch.rand(200, generator=g, dtype=torch.float64)
    score[:10] = 0  # never seen
    counts = prune_lowest(model, opt, score, 150, strategy)
    keep = torch.argsort(score, descending=True)[:50].sort().values
    assert counts["before"] == 200 and counts["after"] == model.num_gaussians == 50 and counts["pruned"] == 150
    assert counts["unseen"] == 10 and math.isclose(counts["mass_kept"], float(score[keep].sum() / score.sum()),
                                                   rel_tol=1e-5)
    gone = torch.ones(200, dtype=torch.bool)
    gone[keep] = False
    assert float(score[keep].min()) >= float(score[gone].max())  # the highest 50 stayed
    assert set(keep.tolist()).isdisjoint(range(10))
    with torch.no_grad():
        after = model.blend(psi)
    for key in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        torch.testing.assert_close(getattr(after, key), getattr(before, key)[:, keep])
    torch.testing.assert_close(opt.state[model.means]["exp_avg"], moments[keep])
    assert torch.equal(strategy.grad_accum, accum[keep]) and len(strategy.max_radii) == 50
    assert len(model.hat_n) == int((model.weights > 0).sum()) and int(model.hat_n.max()) < 50
    assert model.mouth_means.shape[0] == 20  # prune_lowest leaves the mouth interior alone
    assert {grp["params"][0] for grp in opt.param_groups} == set(model.parameters())
    for p in model.parameters():
        p.grad = torch.ones_like(p)
    opt.step()  # the optimizer runs on the new parameters


def test_prune_mouth_lowest_keeps_the_survivors_state(head):
    model, opt, g = stepped_model(head)
    before = {k: v.detach().clone() for k, v in model.named_parameters() if k.startswith("mouth_")}
    moments = opt.state[model.mouth_means]["exp_avg"].clone()
    group = model.mouth_group.clone()
    score = torch.rand(20, generator=g, dtype=torch.float64)
    counts = prune_mouth_lowest(model, opt, score, 12)
    keep = torch.argsort(score, descending=True)[:8].sort().values
    assert counts == {"mouth_before": 20, "mouth_after": 8} and model.mouth_means.shape[0] == 8
    for key, value in before.items():
        torch.testing.assert_close(getattr(model, key), value[keep])
    torch.testing.assert_close(opt.state[model.mouth_means]["exp_avg"], moments[keep])
    assert torch.equal(model.mouth_group, group[keep]) and model.num_gaussians == 200  # the face untouched
    assert model.to_avatar().num_mouth == 8
    assert {grp["params"][0] for grp in opt.param_groups} == set(model.parameters())
    assert prune_mouth_lowest(model, opt, score[:8], 50)["mouth_after"] == 1  # one always stays


def test_pruning_the_mouth_interior_in_training_and_across_a_resume(head, data, tmp_path):
    cfg = TOY.with_pruning(0.5, (3, 5)).with_(prune_by="peak", prune_mouth=True)
    straight = Trainer(data, tmp_path / "a", cfg, iterations=7, seed=2, facemodel=head)
    events = [straight.step() for _ in range(7)]
    assert events[2].pruned["mouth_before"] == 40 and events[2].pruned["mouth_after"] == 28
    assert events[4].pruned["mouth_after"] == 20 and straight.summary()["mouth"] == 20
    assert [e.gaussians for e in events][-1] == 200
    first = Trainer(data, tmp_path / "b", cfg, iterations=7, seed=2, facemodel=head)
    for _ in range(4):
        first.step()
    first.checkpoint()
    second = Trainer(data, tmp_path / "b", TOY, iterations=7, facemodel=head)
    assert second.resume() and int(second.model.mouth_means.shape[0]) == 28
    while second.iteration < second.total:
        second.step()
    a, b = straight.model.state()["tensors"], second.model.state()["tensors"]
    for key in a:
        assert torch.equal(a[key], b[key]), key
    assert not ContributionPruner.from_preset(TOY.with_pruning(0.5).with_(prune_mouth=False)).mouth  # the switch


def test_the_schedule_and_its_switches():
    assert step_fraction(0.75, 2) == pytest.approx(0.5) and step_fraction(0.0, 3) == 0.0
    for preset in PRESETS.values():  # off unless asked for
        assert preset.prune_at == () and not ContributionPruner.from_preset(preset).enabled
    tiny = get_preset("tiny")
    assert tiny.with_pruning(0.5).prune_at == (2100, 2400) and tiny.with_pruning(0.5).prune_fraction == 0.5
    assert not ContributionPruner.from_preset(tiny.with_pruning(0.0)).enabled
    assert not ContributionPruner(at=(5,), fraction=0.0).enabled
    assert tiny.with_pruning(0.3, (50, 9000)).prune_at == (50,)  # past the end: dropped
    with pytest.raises(ValueError):
        tiny.with_pruning(1.0)
    p = ContributionPruner(at=(7, 3), fraction=0.5, frames=4)
    assert p.at == (3, 7) and p.due(3) and not p.due(4) and p.sample(10).tolist() == [0, 3, 6, 9]
    parser = build_parser()
    args = parser.parse_args(["train", "d", "--out", "x.bsplat", "--prune", "0.6", "--prune-at", "10,20"])
    assert args.prune == 0.6 and args.prune_at == (10, 20)
    assert parser.parse_args(["train", "d", "--out", "x.bsplat", "--prune", "off"]).prune == 0.0
    assert parser.parse_args(["train", "d", "--out", "x.bsplat", "--prune", "on"]).prune == 0.4
    assert parser.parse_args(["train", "d", "--out", "x.bsplat"]).prune == 0.0
    assert parser.parse_args(["train", "d", "--out", "x.bsplat"]).prune_by is None  # given or not: told apart
    assert tiny.prune_by == "peak" and tiny.prune_mouth  # what --prune uses without --prune-by
    assert ContributionPruner.from_preset(tiny.with_(prune_by="efficiency")).by == "efficiency"
    assert ContributionPruner.from_preset(tiny.with_(prune_by="peak")).by == "peak"
    assert parser.parse_args(["train", "d", "--out", "x.bsplat", "--prune", "on", "--prune-by", "peak"]).prune_by \
        == "peak"
    with pytest.raises(ValueError, match="prune_by"):  # refused when the trainer starts, not at the first pruning
        ContributionPruner.from_preset(tiny.with_pruning(0.5).with_(prune_by="size"))
    with pytest.raises(SystemExit):
        parser.parse_args(["train", "d", "--out", "x.bsplat", "--prune", "1.5"])


def test_pruning_in_training_and_across_a_resume(head, data, tmp_path):
    cfg = TOY.with_pruning(0.5, (3, 5))
    straight = Trainer(data, tmp_path / "a", cfg, iterations=7, seed=2, facemodel=head)
    events = [straight.step() for _ in range(7)]
    assert [e.gaussians for e in events] == [400, 400, 283, 283, 200, 200, 200]  # 1 - sqrt(0.5) at each
    assert events[2].pruned["before"] == 400 and events[2].pruned["after"] == 283 and events[3].pruned is None
    assert 0.5 < events[4].pruned["mass_kept"] <= 1 and events[4].pruned["frames"] == len(straight.train_idx)
    summary = straight.summary()
    assert [p["iteration"] for p in summary["pruned"]] == [3, 5] and summary["stage_ms"]["prune"] > 0
    straight.checkpoint()
    logged = [json.loads(s) for s in (tmp_path / "a" / "log.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in logged if "pruned" in r] == [3, 5]
    # Interrupted between the two prunings and resumed in another trainer: the same state, pruned once more.
    first = Trainer(data, tmp_path / "b", cfg, iterations=7, seed=2, facemodel=head)
    for _ in range(4):
        first.step()
    first.checkpoint()
    second = Trainer(data, tmp_path / "b", TOY, iterations=7, facemodel=head)
    assert second.resume() and second.preset.prune_at == (3, 5) and second.model.num_gaussians == 283
    while second.iteration < second.total:
        second.step()
    assert second.model.num_gaussians == 200
    assert [p["iteration"] for p in second.summary()["pruned"]] == [3, 5]
    a, b = straight.model.state()["tensors"], second.model.state()["tensors"]
    for key in a:
        assert torch.equal(a[key], b[key]), key
    # Resumed after the last pruning: nothing more goes.
    third = Trainer(data, tmp_path / "a", TOY, facemodel=head)
    assert third.resume() and third.iteration == 7 and third.model.num_gaussians == 200


def test_pruning_scores_refined_poses_as_training_renders_them(head, data, tmp_path, monkeypatch):
    from render_core.train import prune

    seen = []
    real = prune.contribution

    def spy(*args, motions=None, **kwargs):
        seen.append(None if motions is None else motions.clone())
        return real(*args, motions=motions, **kwargs)

    monkeypatch.setattr(prune, "contribution", spy)
    cfg = TOY.with_(refine_poses=True, refine_poses_from=1).with_pruning(0.5, (4,))
    t = Trainer(data, tmp_path / "w", cfg, iterations=5, seed=2, facemodel=head)
    for _ in range(4):
        t.step()
    assert t.model.num_gaussians == 200 and len(seen) == 1
    pick = torch.from_numpy(t._pruner.sample(len(t.train_idx)))
    torch.testing.assert_close(seen[0], t._poses.wu[pick])  # the corrections learnt so far (some non-zero)
    assert float(seen[0].abs().sum()) > 0
    t.step()  # training goes on


@pytest.mark.slow  # two 200-iteration trainings: about a minute on 2 cores, more on a busy machine
def test_a_pruned_tiny_run_keeps_its_held_out_quality(head, data, tmp_path):
    cfg = TOY.with_(iterations=200, sh_every=50, xyz_decay_steps=200)
    plain = train(data, tmp_path / "plain.bsplat", preset=cfg, facemodel=head, seed=0)
    pruned = train(data, tmp_path / "pruned.bsplat", preset=cfg.with_pruning(0.5, (100, 130)), facemodel=head,
                   seed=0)
    assert plain["gaussians"] == 400 and pruned["gaussians"] == 200
    assert [p["after"] for p in pruned["pruned"]] == [283, 200]
    assert pruned["pruned"][-1]["mass_kept"] > 0.8
    print("held-out head PSNR: plain", plain["eval"]["psnr_head"], "pruned", pruned["eval"]["psnr_head"])
    assert pruned["eval"]["psnr_head"] > plain["eval"]["psnr_head"] - 0.5


def test_train_cli_prunes_when_asked(tmp_path, head, capsys, monkeypatch):
    from service.cli import main

    monkeypatch.setenv("BLENDSPLAT_DATA_DIR", str(tmp_path / "data"))
    synth_dataset(tmp_path / "ds", frames=5, size=32, seed=1, facemodel=head)
    out = tmp_path / "a.bundle"
    assert main(["train", str(tmp_path / "ds"), "--out", str(out), "--iterations", "4", "--gaussians", "500",
                 "--prune", "0.5", "--prune-at", "2,3", "--prune-by", "efficiency", "--quiet"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["gaussians"] == 250 and [p["iteration"] for p in summary["pruned"]] == [2, 3]
    assert main(["train", str(tmp_path / "ds"), "--out", str(out), "--iterations", "2", "--prune-at", "1",
                 "--quiet"]) == 1  # --prune-at alone: an error
    assert "--prune-at needs --prune" in capsys.readouterr().err
    assert main(["train", str(tmp_path / "ds"), "--out", str(out), "--iterations", "2", "--prune-by", "efficiency",
                 "--quiet"]) == 1  # --prune-by alone: an error too
    assert "--prune-by needs --prune" in capsys.readouterr().err
    assert main(["train", str(tmp_path / "ds"), "--out", str(out), "--iterations", "2", "--prune-by",
                 "contribution", "--quiet"]) == 1  # the default score named alone: refused as well
    assert "--prune-by needs --prune" in capsys.readouterr().err
