"""Training (render_core.train): the consistency parametrisation, losses, the loop, exact resume, the bundle."""

from __future__ import annotations

import json
import math
import threading

import numpy as np
import pytest
import torch

from render_core.bundle import read_bundle, read_manifest, validate_bundle
from render_core.data import read_dataset
from render_core.data.frames import frame_inputs, targets
from render_core.data.generate import synth_dataset
from render_core.deform import blend
from render_core.evaluation.metrics import psnr, ssim
from render_core.renderer import AvatarRenderer
from render_core.rotation import matrix_to_quat, quat_multiply
from render_core.train import CONSISTENCY, Outcome, Progress, TrainableAvatar, Trainer, get_preset, train
from render_core.train.geometry import closest_points, consistency_range, displacement_magnitudes
from render_core.train.initialize import init_avatar
from render_core.train.losses import MouthCylinder
from render_core.train.trainer import (
    dataset_digest,
    forward,
    last_checkpoint,
    load_checkpoint,
    make_optimizer,
    raster_step,
)
from tests.test_initialize import tetra_model

TOY = get_preset("tiny").with_(gaussians=400, mouth=40, sh_every=15, checkpoint_every=1000, log_every=1,
                               final_eval_frames=2, xyz_decay_steps=50)


@pytest.fixture(scope="module")
def toy(head, tmp_path_factory):
    """A 64 x 64 synthetic dataset of 6 frames (5 train, 1 test) on the open head."""
    out = tmp_path_factory.mktemp("toy") / "data"
    synth_dataset(out, frames=6, size=64, seed=1, facemodel=head)
    return out


@pytest.fixture(scope="module")
def small(head):
    return init_avatar(head, gaussians=300, mouth=20, seed=4)


@pytest.fixture(scope="module")
def trained(toy, head, tmp_path_factory):
    """One short training run (50 iterations) shared by the loss and bundle tests."""
    out = tmp_path_factory.mktemp("run")
    summary = train(toy, out / "toy.bsplat", workdir=out / "work", preset=TOY, iterations=50, facemodel=head)
    return summary, out




# ------------------------------------------------------------------------------------------------ the model
@pytest.mark.parametrize("consistency", CONSISTENCY)
def test_zero_residual_equals_the_initialisation(small, head, consistency):
    model = TrainableAvatar.from_facemodel(small, head, consistency)
    av = model.to_avatar()
    for part in ("neutral", "deltas", "mouth"):
        for key, want in getattr(small, part).tensors().items():
            assert torch.equal(getattr(getattr(av, part), key), want), f"{part}.{key}"
    assert torch.equal(av.lbs_weights, small.lbs_weights) and torch.equal(av.mouth_group, small.mouth_group)
    psi = torch.rand(2, small.num_expressions, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        got, want = blend(model.avatar(), psi), blend(small, psi)
    for key in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        assert torch.equal(getattr(got, key), getattr(want, key))


def test_rigid_rotation_gives_that_rotation():
    """A blendshape rotating the whole mesh by 30 degrees: the model's initial blendshape (dG_hat = 0) rotates every
    Gaussian's position and orientation by exactly that rotation, and d is the displacement magnitude."""
    fm, r = tetra_model()
    av = init_avatar(fm, gaussians=200, mouth=2, seed=0)
    model = TrainableAvatar.from_facemodel(av, fm, "all")
    out = model.to_avatar()
    q0 = out.neutral.quats
    q1 = torch.nn.functional.normalize(q0 + out.deltas.quats[0], dim=-1)
    want = quat_multiply(matrix_to_quat(r).expand_as(q0), q0)
    assert float(torch.minimum((q1 - want).norm(dim=1), (q1 + want).norm(dim=1)).max()) < 1e-5
    torch.testing.assert_close(out.neutral.means + out.deltas.means[0], out.neutral.means @ r.T, atol=1e-6, rtol=0)
    # d: |displacement| at the Gaussians' surface points; a rotation about z moves a point by 2 sin(15 deg) r_xy at
    # the vertices, and d interpolates the vertices' magnitudes.
    at_vertices = displacement_magnitudes(fm, fm.template)[0]
    torch.testing.assert_close(at_vertices, fm.expression_basis[0].norm(dim=1), atol=1e-7, rtol=0)
    assert float(model.d.max()) <= float(at_vertices.max()) + 1e-7 and float(model.d.min()) >= 0


def test_closest_points_on_and_off_the_surface(head):
    g = torch.Generator().manual_seed(2)
    tri = torch.randint(len(head.faces), (200,), generator=g)
    bary = torch.distributions.Dirichlet(torch.ones(3)).sample((200,))
    corners = head.template.double()[head.faces[tri]]
    x = (corners * bary.double()[..., None]).sum(1)
    normal = torch.nn.functional.normalize(torch.linalg.cross(corners[:, 1] - corners[:, 0],
                                                              corners[:, 2] - corners[:, 0]), dim=1)
    q = x + 1e-4 * normal
    got_t, got_b = closest_points(head.template, head.faces, q)
    back = (head.template.double()[head.faces[got_t]] * got_b[..., None]).sum(1)
    dist = (back - q).norm(dim=1)
    assert float(dist.max()) <= 1e-4 + 1e-8  # never farther than the foot of the perpendicular
    assert float(((back - x).norm(dim=1) < 1e-6).float().mean()) > 0.8  # mostly that foot (else a closer fold)
    on_t, on_b = closest_points(head.template, head.faces, x)
    on = (head.template.double()[head.faces[on_t]] * on_b[..., None]).sum(1)
    assert float((on - x).norm(dim=1).max()) < 1e-7
    eps, d_max = consistency_range(head)
    per = head.expression_basis.norm(dim=-1).amax(1)
    assert eps == pytest.approx(0.1 * float(per[per > 0].min())) and d_max == pytest.approx(float(per.max()))


def test_consistency_switches_change_what_is_optimised(small, head, toy):
    ds = read_dataset(toy)
    frame, cams = frame_inputs(small, ds.tracking, [0])
    rgb_t, mask_t = targets(ds, [0])
    grads = {}
    for mode in CONSISTENCY:
        model = TrainableAvatar.from_facemodel(small, head, mode)
        names = {g["name"] for g in make_optimizer(model, TOY).param_groups}
        assert ("hat_means" in names) == (mode != "frozen") and "means" in names and "mouth_sh_dc" in names
        rgb, alpha, _ = forward(model, frame, cams, 0)
        ((rgb - rgb_t).square().mean() + (alpha - mask_t).square().mean()).backward()
        grads[mode] = {p: None if model.hat(p) is None or model.hat(p).grad is None else model.hat(p).grad
                       for p in ("means", "quats", "opacity_logits")}
        zero_w = model.weights == 0
    assert 0 < float(zero_w.float().mean()) < 1  # some (Gaussian, blendshape) pairs are masked out
    pairs = int((~zero_w).sum())

    def masked(g):  # gradient mass of a dense [K, N, ...] residual on pairs whose consistency weight is 0
        return float(g[zero_w].abs().sum())

    assert all(v is None for v in grads["frozen"].values())
    # Weighted residuals exist only where c > 0 (stored sparse); unweighted ones everywhere.
    assert grads["all"]["means"].shape == (pairs, 3) and grads["all"]["quats"].shape == (pairs, 4)
    assert float(grads["all"]["means"].abs().sum()) > 0 and float(grads["all"]["quats"].abs().sum()) > 0
    assert grads["positions"]["means"].shape == (pairs, 3) and masked(grads["positions"]["quats"]) > 0
    assert masked(grads["none"]["means"]) > 0 and masked(grads["none"]["opacity_logits"]) > 0
    # The effective delta: dG_init + c dG_hat ("all"), dG_init + dG_hat ("none").
    model = TrainableAvatar.from_facemodel(small, head, "all")
    with torch.no_grad():
        model.hat_log_scales.fill_(1.0)
    torch.testing.assert_close(model.delta("log_scales"), small.deltas.log_scales + model.weights[..., None])
    model = TrainableAvatar.from_facemodel(small, head, "none")
    with torch.no_grad():
        model.hat_log_scales.fill_(1.0)
    torch.testing.assert_close(model.delta("log_scales"), small.deltas.log_scales + 1.0)


@pytest.mark.parametrize("consistency", ["all", "positions"])
def test_sparse_blend_equals_the_dense_blend(small, head, consistency):
    model = TrainableAvatar.from_facemodel(small, head, consistency)
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if name.startswith("hat_"):
                p.copy_(0.01 * torch.randn(p.shape, generator=g))
    psi = torch.rand(2, small.num_expressions, generator=g)
    for degree in (0, 2, 3):
        with torch.no_grad():
            got, want = model.blend(psi, degree), blend(model.avatar(degree), psi)
        for key in ("means", "quats", "log_scales", "opacity_logits", "sh"):
            torch.testing.assert_close(getattr(got, key), getattr(want, key), atol=1e-6, rtol=1e-5)


def test_densify_reindex_copies_blendshape_entries(small, head):
    from render_core.train.densify import reindex

    for mode in ("all", "none"):
        model = TrainableAvatar.from_facemodel(small, head, mode)
        g = torch.Generator().manual_seed(5)
        with torch.no_grad():
            for name, p in model.named_parameters():
                if name.startswith("hat_"):
                    p.copy_(0.01 * torch.randn(p.shape, generator=g))
        opt = make_optimizer(model, TOY)
        for p in model.parameters():
            p.grad = torch.randn(p.shape, generator=g)
        opt.step()
        psi = torch.rand(1, small.num_expressions, generator=g)
        with torch.no_grad():
            before = model.blend(psi)
        old_hat = model.hat_means.detach().clone()
        old_state = {k: v.clone() for k, v in opt.state[model.hat_means].items()}
        n = model.num_gaussians
        src = torch.cat([torch.arange(0, n, 2), torch.tensor([1, 1, 7])])  # drop odd ones, three copies
        fresh = torch.zeros(len(src), dtype=torch.bool)
        fresh[-3:] = True
        reindex(model, opt, src, fresh)
        assert model.num_gaussians == len(src) and model.d.shape == (small.num_expressions, len(src))
        with torch.no_grad():
            after = model.blend(psi)
        for key in ("means", "quats", "log_scales", "opacity_logits", "sh"):
            torch.testing.assert_close(getattr(after, key), getattr(before, key)[:, src], atol=1e-6, rtol=1e-5)
        state = opt.state[model.hat_means]
        assert {g["params"][0] for g in opt.param_groups} == set(model.parameters())
        if mode == "none":  # dense rows: survivors keep their moments, children start at zero
            torch.testing.assert_close(model.hat_means.detach(), old_hat[:, src])
            torch.testing.assert_close(state["exp_avg"][:, :-3], old_state["exp_avg"][:, src[:-3]])
            assert float(state["exp_avg"][:, -3:].abs().sum()) == 0
        else:  # pairs: one per (child, parent pair); c carried along
            assert len(model.hat_n) == int((model.weights > 0).sum())
            torch.testing.assert_close(model.hat_w, model.weights[model.hat_k, model.hat_n])
        opt.step()  # the optimizer still runs on the new parameters


# ----------------------------------------------------------------------------------------------------- losses
def test_ssim_and_mouth_cylinder():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(1, 32, 32, 3, generator=g)
    assert float(ssim(a, a)) == pytest.approx(1.0, abs=1e-6)
    assert float(ssim(a, torch.rand(1, 32, 32, 3, generator=g))) < 0.2
    x = torch.rand(50, 3, generator=g) * torch.tensor([0.04, 0.015, 0.002])
    cyl = MouthCylinder.from_points(x)
    assert float(cyl.loss(x)) == 0.0
    far = x + torch.tensor([0.0, 0.1, 0.0])
    assert float(cyl.loss(far)) > 0
    assert float(cyl.sdf(torch.tensor([[float(cyl.centre[0]), float(cyl.centre[1]) + cyl.radius + 0.01,
                                         float(cyl.centre[2])]]))) == pytest.approx(0.01, abs=1e-6)


# ------------------------------------------------------------------------------------------------------- loop
def test_loss_falls_on_a_toy(trained):
    summary, out = trained
    lines = [json.loads(s) for s in (out / "work" / "log.jsonl").read_text().splitlines()]
    assert len(lines) == 50 and lines[0]["iteration"] == 1 and lines[-1]["iteration"] == 50
    assert {"iteration", "loss", "l1", "ssim", "alpha", "psnr", "seconds"} <= set(lines[0])
    first = np.mean([r["loss"] for r in lines[:5]])
    last = np.mean([r["loss"] for r in lines[-5:]])
    assert last < 0.7 * first
    assert np.mean([r["psnr"] for r in lines[-5:]]) > np.mean([r["psnr"] for r in lines[:5]]) + 1.0
    assert summary["iterations"] == 50 and summary["bundle"] and set(summary["stage_ms"]) >= {"blend", "backward"}


def test_bundle_renders_the_recorded_psnr(trained, toy):
    summary, out = trained
    avatar = read_bundle(out / "toy.bsplat")
    assert avatar.precision == "fp16" and avatar.num_gaussians == TOY.gaussians
    ds = read_dataset(toy)
    renderer = AvatarRenderer(avatar, "native")
    for index, recorded in zip(summary["final"]["frames"], summary["final"]["psnr"], strict=True):
        frame, cams = frame_inputs(avatar, ds.tracking, [index])
        rgb_t, _ = targets(ds, [index])
        got = psnr(renderer.render(frame, cams).rgb, rgb_t)
        assert got == pytest.approx(recorded, abs=0.1)


def test_bundle_records_the_dataset_the_training_and_the_held_out_figures(trained, toy, head):
    summary, out = trained
    manifest = read_manifest(out / "toy.bsplat")
    t = manifest["provenance"]["trained"]
    assert {k: t[k] for k in ("iterations", "preset", "seed", "consistency")} == {
        "iterations": 50, "preset": "tiny", "seed": 0, "consistency": "all"}
    assert t["dataset"] == {"name": "data", "frames": 6, "width": 64, "height": 64, "train": 5, "test": 1,
                            "face_model": head.name, "digest": dataset_digest(toy)}
    assert t["dataset"]["digest"].startswith("sha256:") and dataset_digest(toy) == dataset_digest(str(toy))
    e = summary["eval"]
    assert t["held_out"] == {"split": "test", "frames": 1, **{k: round(e[k], 4) for k in ("psnr_head", "psnr",
                                                                                           "ssim")}}
    assert validate_bundle(out / "toy.bsplat")["digest"] == manifest["digest"]  # rewritten whole, still valid


def test_resume_equals_an_uninterrupted_run(toy, head, tmp_path):
    # Densification at iterations 2, 4 and 6 (splits draw from the generator, children look up the grid, screen
    # radii are tracked from iteration 2 and prune from 4), a checkpoint at 3.
    cfg = TOY.with_(checkpoint_every=3, sh_every=2, densify_from=1, densify_every=2, densify_until=6,
                    densify_grad=2e-4, prune_big_after=3, max_screen_radius=8.0)
    straight = train(toy, tmp_path / "a.bsplat", workdir=tmp_path / "a", preset=cfg, iterations=6,
                     facemodel=head, seed=3)
    part = train(toy, tmp_path / "b.bsplat", workdir=tmp_path / "b", preset=cfg, iterations=6,
                 facemodel=head, seed=3, stop_after=3)
    assert part["stopped"] and part["bundle"] is None and not (tmp_path / "b.bsplat").exists()
    resumed = train(toy, tmp_path / "b.bsplat", workdir=tmp_path / "b", preset=cfg, iterations=6,
                    facemodel=head, resume=True)
    assert resumed["resumed_from"] == 3 and resumed["iterations"] == 6
    assert straight["gaussians"] > TOY.gaussians and straight["gaussians"] == resumed["gaussians"]
    assert sum(d["pruned_screen"] for d in straight["densified"]) > 0
    assert sum(d["looked_up"] for d in straight["densified"]) > 0 and straight["grid"]["bricks_built"] > 0
    a = load_checkpoint(tmp_path / "a" / "checkpoints" / "ckpt_0000006.pt")
    b = load_checkpoint(tmp_path / "b" / "checkpoints" / "ckpt_0000006.pt")
    ta, tb = a["model"]["tensors"], b["model"]["tensors"]
    assert ta.keys() == tb.keys()
    for key in ta:
        assert torch.equal(ta[key], tb[key]), key
    sa, sb = a["optimizer"]["state"], b["optimizer"]["state"]
    for i in sa:
        for key in sa[i]:
            assert torch.equal(sa[i][key], sb[i][key])
    assert torch.equal(a["rng"], b["rng"])
    log_a = [json.loads(s)["loss"] for s in (tmp_path / "a" / "log.jsonl").read_text().splitlines()]
    log_b = [json.loads(s)["loss"] for s in (tmp_path / "b" / "log.jsonl").read_text().splitlines()]
    assert log_a == log_b
    assert straight["final"]["psnr"] == resumed["final"]["psnr"]
    # A fresh run in a used workdir starts over (the old checkpoints go).
    again = train(toy, tmp_path / "b.bsplat", workdir=tmp_path / "b", preset=cfg, iterations=2,
                  facemodel=head, seed=3)
    assert again["resumed_from"] is None
    assert [p.name for p in sorted((tmp_path / "b" / "checkpoints").glob("*.pt"))] == ["ckpt_0000002.pt"]


# ---------------------------------------------------------------------------------------------------- Trainer
# Densification at iterations 2, 4 and 6 (the strategy's statistics are mid-interval at 3), the SH ramp every 2.
DENSE = TOY.with_(sh_every=2, densify_from=1, densify_every=2, densify_until=6, densify_grad=2e-4,
                  prune_big_after=3, max_screen_radius=8.0)


def trainer_state(t: Trainer) -> dict:
    """Everything a trainer carries from step to step, as plain tensors and numbers."""
    return {"iteration": t.iteration, "model": t.model.state()["tensors"], "optimizer": t.optimizer.state_dict(),
            "rng": t.generator.get_state(), "densify": t.strategy.state()}


def assert_same_state(a: dict, b: dict) -> None:
    assert a["iteration"] == b["iteration"] and a["model"].keys() == b["model"].keys()
    for key in a["model"]:
        assert torch.equal(a["model"][key], b["model"][key]), key
    sa, sb = a["optimizer"]["state"], b["optimizer"]["state"]
    assert sa.keys() == sb.keys()
    for i in sa:
        for key in sa[i]:
            assert torch.equal(torch.as_tensor(sa[i][key]), torch.as_tensor(sb[i][key])), (i, key)
    assert torch.equal(a["rng"], b["rng"])
    for key in ("grad_accum", "denom", "max_radii"):
        assert torch.equal(a["densify"][key], b["densify"][key]), key


def test_trainer_step_checkpoint_resume_equals_an_uninterrupted_run(toy, head, tmp_path):
    straight = Trainer(toy, tmp_path / "a", DENSE, iterations=6, seed=3, facemodel=head)
    assert straight.run() is Outcome.FINISHED and straight.iteration == 6
    assert straight.model.num_gaussians > TOY.gaussians  # densified
    first = Trainer(toy, tmp_path / "b", DENSE, iterations=6, seed=3, facemodel=head)
    for _ in range(3):
        first.step()
    assert first.checkpoint().name == "ckpt_0000003.pt" and float(first.strategy.denom.sum()) > 0
    # Another process: the checkpoint's seed and preset win over the arguments.
    second = Trainer(toy, tmp_path / "b", TOY, iterations=6, seed=99, facemodel=head)
    assert second.resume() and second.iteration == 3
    assert second.seed == 3 and second.preset == DENSE.with_(iterations=6)
    while second.iteration < second.total:
        second.step()
    assert_same_state(trainer_state(straight), trainer_state(second))
    losses_a = [json.loads(s)["loss"] for s in (tmp_path / "a" / "log.jsonl").read_text().splitlines()]
    losses_b = [json.loads(s)["loss"] for s in (tmp_path / "b" / "log.jsonl").read_text().splitlines()]
    assert len(losses_a) == 6 and losses_a == losses_b
    with pytest.raises(RuntimeError, match="complete"):
        second.step()
    # Without a checkpoint resume says so and the trainer starts fresh.
    assert not Trainer(toy, tmp_path / "c", DENSE, facemodel=head).resume()


def test_trainer_cancels_between_steps_with_a_checkpoint(toy, head, tmp_path):
    cancel = threading.Event()
    seen = []

    def on_progress(event: Progress) -> None:
        seen.append(event.iteration)
        if event.iteration == 2:
            cancel.set()

    t = Trainer(toy, tmp_path / "w", DENSE, iterations=6, seed=3, facemodel=head)
    assert t.run(on_progress=on_progress, should_cancel=cancel) is Outcome.CANCELLED
    assert seen == [1, 2] and t.iteration == 2  # no step after the request, none cut short
    assert last_checkpoint(tmp_path / "w").name == "ckpt_0000002.pt"
    assert [json.loads(s)["iteration"] for s in (tmp_path / "w" / "log.jsonl").read_text().splitlines()] == [1, 2]
    assert t.run(should_cancel=lambda: True) is Outcome.CANCELLED and t.iteration == 2  # a callable works too
    # The cancelled state is a consistent one: resumed elsewhere it ends where an uninterrupted run does.
    resumed = Trainer(toy, tmp_path / "w", DENSE, iterations=6, facemodel=head)
    assert resumed.resume() and resumed.run(until=4) is Outcome.STOPPED and resumed.iteration == 4
    straight = Trainer(toy, tmp_path / "s", DENSE, iterations=6, seed=3, facemodel=head)
    assert straight.run(until=4) is Outcome.STOPPED
    assert_same_state(trainer_state(straight), trainer_state(resumed))


def test_trainer_progress_events_and_previews(toy, head, tmp_path, monkeypatch):
    from render_core import raster

    calls = []
    real = raster.DIFFERENTIABLE["native"]
    monkeypatch.setitem(raster.DIFFERENTIABLE, "native", lambda *a, **k: calls.append(1) or real(*a, **k))
    t = Trainer(toy, tmp_path / "w", TOY.with_(log_every=2), iterations=4, facemodel=head)
    events: list[Progress] = []
    assert t.run(on_progress=events.append, preview_every=2) is Outcome.FINISHED
    assert len(calls) == 4 + 2  # the registry's step: four iterations and two previews
    assert [e.iteration for e in events] == [1, 2, 3, 4] and {e.total for e in events} == {4}
    for e in events:
        assert set(e.losses) == {"loss", "l1", "ssim", "alpha", "mouth"} and math.isfinite(e.losses["loss"])
        assert math.isfinite(e.psnr) and e.gaussians == TOY.gaussians and e.eta >= 0 and e.densified is None
    assert [e.elapsed for e in events] == sorted(e.elapsed for e in events) and events[-1].eta == 0
    assert [e.preview is None for e in events] == [True, False, True, False]
    ds = read_dataset(toy)
    assert t.preview_index == ds.tracking.test[0]
    img = events[-1].preview
    assert img.dtype == np.uint8 and img.shape == (ds.tracking.height, ds.tracking.width, 3) and img.max() > 0
    rng = t.generator.get_state()
    assert np.array_equal(t.preview(), img) and torch.equal(t.generator.get_state(), rng)  # on demand, no effect
    # The log: every log_every iterations, the first and the last.
    assert [json.loads(s)["iteration"] for s in (tmp_path / "w" / "log.jsonl").read_text().splitlines()] == [1, 2, 4]
    assert t.summary()["iterations_this_run"] == 4


def test_training_device_picks_the_registry_step():
    from render_core import raster

    assert raster_step("cpu") is raster.DIFFERENTIABLE["native"]
    with pytest.raises(ValueError, match="'cpu' or 'cuda'"):
        raster_step("tpu")


def test_unknown_face_model_is_an_error_naming_what_to_pass():
    from render_core.errors import DatasetError
    from render_core.train.trainer import resolve_facemodel

    with pytest.raises(DatasetError, match="facemodel=PATH"):
        resolve_facemodel("flame-2020", None)
