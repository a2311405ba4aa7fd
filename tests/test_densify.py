"""Densification details (render_core.train.densify): screen-radius pruning and lookup-grid values for children."""

from __future__ import annotations

import math

import pytest
import torch

from render_core.camera import Cameras
from render_core.deform import Splats
from render_core.rotation import axis_angle_to_matrix, matrix_to_quat
from render_core.train import TrainableAvatar, get_preset
from render_core.train.densify import DensifyStrategy, screen_radii
from render_core.train.grids import LookupGrid
from render_core.train.initialize import init_avatar
from render_core.train.trainer import make_optimizer
from tests.test_grids import blob_model

CFG = get_preset("tiny")


def camera(f: float = 100.0) -> Cameras:
    """64 x 64 pixels, focal ``f``, at the origin looking down +z."""
    K = torch.tensor([[[f, 0, 32.0], [0, f, 32.0], [0, 0, 1]]])
    return Cameras(K, torch.eye(3)[None], torch.zeros(1, 3), 64, 64)


def hand_built() -> tuple[torch.Tensor, ...]:
    """Four Gaussians in front of :func:`camera`: sigma 5 cm at 1 m (5 px), at 0.5 m (10 px), a 10 x 1 cm cigar
    turned to lie along y at 1 m (10 px along y, 1 px along x), and one behind the camera."""
    means = torch.tensor([[0.0, 0, 1], [0.02, 0, 0.5], [0, 0.01, 1], [0, 0, -1]])
    turn = matrix_to_quat(axis_angle_to_matrix(torch.tensor([0, 0, math.pi / 2])))
    quats = torch.tensor([[1.0, 0, 0, 0]] * 4)
    quats[2] = turn
    scales = torch.tensor([[0.05] * 3, [0.05] * 3, [0.1, 0.01, 0.01], [0.05] * 3])
    return means, quats, scales, torch.full((4,), 0.9)


def test_screen_radius_is_three_sigma_of_the_largest_eigenvalue():
    means, quats, scales, opac = hand_built()
    r = screen_radii(means, quats, scales, opac, camera())
    # Isotropic: 2D variance (f s / z)^2 + 0.3 (the blur); the cigar: the larger eigenvalue is along y.
    want = [math.ceil(3 * math.sqrt(5.0**2 + 0.3)), None, math.ceil(3 * math.sqrt(10.0**2 + 0.3)), 0]
    assert r[0] == want[0] == 16 and r[2] == want[2] == 31 and r[3] == 0
    # Off-axis (x/z = 0.04): the exact EWA covariance of that Gaussian, its larger eigenvalue.
    x, z, f, s = 0.02, 0.5, 100.0, 0.05
    J = torch.tensor([[f / z, 0, -f * x / z**2], [0, f / z, 0]], dtype=torch.float64)
    cov = J @ (s * s * torch.eye(3, dtype=torch.float64)) @ J.T + 0.3 * torch.eye(2, dtype=torch.float64)
    assert r[1] == math.ceil(3 * math.sqrt(float(torch.linalg.eigvalsh(cov).max())))


@pytest.fixture(scope="module")
def blob():
    return blob_model()


def trainable(blob, n: int = 4) -> TrainableAvatar:
    av = init_avatar(blob, gaussians=n, mouth=2, seed=0)
    return TrainableAvatar.from_facemodel(av, blob, "all")


@pytest.mark.parametrize("prune_big", [False, True])
def test_gaussians_bigger_than_20_px_on_screen_are_pruned_after_3k(blob, prune_big):
    model = trainable(blob)
    opt = make_optimizer(model, CFG)
    keep_means = model.means.detach().clone()
    dens = DensifyStrategy(4, extent=100.0, grad_threshold=math.inf, prune_opacity=0.0,
                           max_gaussians=100)  # no world-size pruning
    dens.observe_radii(*hand_built(), camera())
    assert dens.max_radii.tolist() == [16, 31, 31, 0]
    # A later frame sees the first one closer (radius 2 x 16): the largest radius counts.
    means, quats, scales, opac = hand_built()
    dens.observe_radii(means * torch.tensor([1, 1, 0.5]), quats, scales, opac, camera())
    assert dens.max_radii[0] > 20
    counts = dens.refine(model, opt, torch.Generator(), prune_big=prune_big)
    if prune_big:  # iteration > prune_big_after: only the one never bigger than 20 px stays
        assert counts["pruned"] == counts["pruned_screen"] == 3 and model.num_gaussians == 1
        torch.testing.assert_close(model.means.detach(), keep_means[3:])
    else:
        assert counts["pruned"] == 0 and model.num_gaussians == 4
    assert dens.max_radii.tolist() == [0.0] * model.num_gaussians  # a new interval starts


def test_children_and_moved_gaussians_take_the_grid_values(blob):
    n = 40
    model = trainable(blob, n)
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        model.hat_means.copy_(0.01 * torch.randn(model.hat_means.shape, generator=g))
        model.means[5] += torch.tensor([0.01, 0, 0])  # moved by more than a grid cell
        model.means[6] += torch.tensor([1e-5, 0, 0])  # not
    opt = make_optimizer(model, CFG)
    for p in model.parameters():
        p.grad = torch.ones_like(p)
    opt.step()  # Adam moments everywhere
    before = {k: getattr(model, k).detach().clone() for k in ("lbs_weights", "d", "hat_k", "hat_n", "hat_means")}
    grid = LookupGrid(blob, 32)
    dens = DensifyStrategy(n, extent=0.05, grad_threshold=0.5, prune_opacity=0.0, max_gaussians=1000, grid=grid)
    dens.grad_accum[:3], dens.denom[:] = 1.0, 1.0  # Gaussians 0-2 densify
    with torch.no_grad():
        model.log_scales[0] = math.log(1e-5)  # small: cloned; 1 and 2 are split
    counts = dens.refine(model, opt, torch.Generator().manual_seed(1))
    assert counts["cloned"] == 1 and counts["split"] == 2 and model.num_gaussians == n + 3
    # New order: survivors 0, 3..n-1, the clone of 0, then two children each of 1 and 2.
    children = torch.arange(n - 2, n + 3)
    looked = torch.cat([torch.tensor([3]), children])  # old Gaussian j >= 3 is now at j - 2
    lbs, d = grid.lookup(model.means.detach()[looked])
    torch.testing.assert_close(model.lbs_weights[looked], lbs)
    torch.testing.assert_close(model.d[:, looked], d)
    torch.testing.assert_close(model.lookup_at[looked], model.means.detach()[looked])
    assert counts["looked_up"] == len(looked)
    # The others keep their values; c and the weighted pairs follow d.
    old = torch.cat([torch.tensor([0]), torch.arange(3, n)])
    same = torch.cat([torch.tensor([0]), torch.arange(1, n - 2)])  # their new indices (old 5 -> 3 moved)
    same, old = same[same != 3], old[old != 5]
    torch.testing.assert_close(model.lbs_weights[same], before["lbs_weights"][old])
    torch.testing.assert_close(model.d[:, same], before["d"][:, old])
    assert torch.equal(model.weights, ((model.d - model.eps) / (model.d_max - model.eps)).clamp_min(0))
    assert len(model.hat_k) == int((model.weights > 0).sum())
    torch.testing.assert_close(model.hat_w, model.weights[model.hat_k, model.hat_n])
    # Residuals of pairs that stay are carried (survivors keep theirs, children have their parent's copy); a pair
    # whose c became positive starts at zero; children's Adam moments are zero.
    carried = 0
    for k in range(blob.num_expressions):
        for new, prev in ((4, 6), (0, 0), (n - 2, 0), (n - 1, 1), (n + 2, 2)):
            a = ((model.hat_k == k) & (model.hat_n == new)).nonzero().flatten()
            b = ((before["hat_k"] == k) & (before["hat_n"] == prev)).nonzero().flatten()
            if len(a) and len(b):
                torch.testing.assert_close(model.hat_means.detach()[a], before["hat_means"][b])
                carried += 1
            elif len(a):
                assert float(model.hat_means.detach()[a].abs().sum()) == 0
    assert carried >= 5
    moments = opt.state[model.hat_means]["exp_avg"]
    assert float(moments[torch.isin(model.hat_n, children)].abs().sum()) == 0
    assert {p for grp in opt.param_groups for p in grp["params"]} == set(model.parameters())
    for p in model.parameters():
        p.grad = torch.ones_like(p)
    opt.step()


def test_without_a_grid_children_copy_their_parent(blob):
    model = trainable(blob, 10)
    opt = make_optimizer(model, CFG)
    dens = DensifyStrategy(10, extent=0.05, grad_threshold=0.5, prune_opacity=0.0, max_gaussians=100)
    dens.grad_accum[2], dens.denom[:] = 1.0, 1.0
    with torch.no_grad():
        model.log_scales[2] = math.log(1e-5)
    lbs2, d2 = model.lbs_weights[2].clone(), model.d[:, 2].clone()
    counts = dens.refine(model, opt, torch.Generator())
    assert counts["cloned"] == 1 and counts["looked_up"] == 0
    assert torch.equal(model.lbs_weights[-1], lbs2) and torch.equal(model.d[:, -1], d2)


def test_the_strategy_owns_its_schedule(blob):
    """Statistics up to refine_until, screen radii from the interval that ends after prune_big_after, a refinement
    every refine_every iterations after refine_from, world- and screen-size pruning only after prune_big_after."""
    model = trainable(blob)
    opt = make_optimizer(model, CFG)
    with torch.no_grad():
        model.log_scales[:2] = math.log(0.001)
        model.log_scales[2:] = math.log(0.05)  # > 0.1 x extent: pruned once prune_big applies
    dens = DensifyStrategy(4, extent=0.1, refine_from=2, refine_until=8, refine_every=3, prune_big_after=5,
                           grad_threshold=math.inf, prune_opacity=0.0, max_screen_radius=1e9)
    means, quats, scales, opac = (torch.cat([t, t[:2]])[None] for t in hand_built())  # 4 face + 2 mouth
    refined, denom, radii = {}, {}, {}
    for it in range(1, 10):
        posed = Splats(means.clone().requires_grad_(True) * 1.0, quats, scales, opac,
                       torch.zeros(1, 6, 1, 3), None, 0)
        dens.step_pre_backward(it, posed)
        posed.means[..., :2].sum().backward()
        counts = dens.step_post_backward(it, model, opt, torch.Generator(), camera())
        if counts is not None:
            refined[it] = counts["pruned"]
        denom[it], radii[it] = float(dens.denom.sum()), float(dens.max_radii.sum())
    assert refined == {3: 0, 6: 2}  # the big two: not at 3 (the first after refine_from), at 6
    assert denom[2] == 8 and radii[2] == 0  # two iterations' statistics; no radii before 5 - 3
    assert denom[3] == 0 and denom[4] == 4 and radii[4] > 0  # a new interval after each refinement
    assert denom[8] == 2 * 2 and not dens.collects(9) and denom[9] == denom[8]  # none collected after 8
