"""Densification and pruning (docs/method.md section 6) with blendshape entries copied to children.

Statistics: after each backward, the view-space positional gradient of every face Gaussian, in gsplat's /
3DGS's normalised units (the pixel-space gradient of the projected centre times (W/2, H/2)), recovered from the
gradient of the posed world-space centre through the pinhole model (dL/du = dL/dx_cam * z / f; the small part of
the gradient that flows through the covariance's dependence on the centre is not separated out). The norm is
accumulated for every Gaussian with a non-zero gradient (the visible ones). When screen-size pruning can apply,
also the largest screen radius of every visible Gaussian since the last refinement (:func:`screen_radii`: 3 sigma of the
larger eigenvalue of the blurred 2D covariance, as 3DGS; the rasterizer does not return radii).

:class:`DensifyStrategy` owns the schedule (hooks before and after each backward, as gsplat's strategies) and
refines every ``densify_every`` iterations in (densify_from, densify_until]:
- Gaussians with a mean accumulated gradient >= ``densify_grad``: cloned (an exact copy) if their largest scale is
  <= ``percent_dense`` x the scene extent, else split into two children sampled from the parent's Gaussian with
  scales / 1.6 (the parent is removed);
- pruned: neutral opacity < ``prune_opacity``, and after ``prune_big_after`` iterations (3DGS: 3000) also a largest
  scale > 0.1 x extent or a screen radius > ``max_screen_radius`` (20 px) in some frame since the last one;
- capped at ``max_gaussians`` (the largest gradients first).
Children copy their parent's blendshape entries (dG_init pairs, dG_hat pairs or rows, pose correctives, eyelid
offsets); their Adam moments start at zero, survivors keep theirs. With a lookup grid (:mod:`.grids`, the
paper's), children and the Gaussians that moved more than a grid cell since their values were set get their LBS
weights and displacement magnitudes d (hence c = max(f(d), 0) and the set of weighted pairs) from the grid
(:func:`assign_surface`); without one they copy their parent's. The mouth interior is not densified. The scene
extent is the largest distance of the initial face Gaussians from their centroid.
"""

from __future__ import annotations

import logging

import torch
from torch import Tensor, nn

from ..camera import Cameras
from ..deform import Splats
from ..raster.reference import project
from ..rotation import quat_to_matrix
from .geometry import consistency_weights
from .grids import LookupGrid
from .model import PROPS, TrainableAvatar
from .presets import Preset

log = logging.getLogger(__name__)

PERCENT_DENSE = 0.01
SPLIT_SCALE = 1.6
MAX_SCREEN_RADIUS = 20.0  # pixels (3DGS's max_screen_size)


def screen_radii(
    means: Tensor,  # [N, 3] posed world-space centres
    quats: Tensor,  # [N, 4] wxyz
    scales: Tensor,  # [N, 3] standard deviations
    opacities: Tensor,  # [N]
    cameras: Cameras,  # one camera
) -> Tensor:
    """Screen radius [N] in pixels of each Gaussian seen by ``cameras[0]``: ceil(3 sqrt(lambda_max)) of its blurred
    2D covariance (the projection of docs/method.md section 9: clamped Jacobian, + 0.3 on the diagonal), as 3DGS's
    rasterizer reports it; 0 for Gaussians that are culled (behind the near plane, too transparent, off screen)."""
    with torch.no_grad():
        cams = Cameras(cameras.K[:1], cameras.R[:1], cameras.t[:1], cameras.width, cameras.height)
        proj = project(means[None].detach(), quats[None].detach(), scales[None].detach(),
                       opacities[None].detach(), cams.to(means.dtype))
        a, b, c = proj.conics[0].unbind(-1)  # inverse of the blurred covariance [[s00, s01], [s01, s11]]
        det = 1.0 / (a * c - b * b).clamp_min(1e-30)
        s00, s11 = c * det, a * det
        mid = 0.5 * (s00 + s11)
        lam = mid + (mid * mid - det).clamp_min(0.0).sqrt()
        return torch.where(proj.visible[0], torch.ceil(3.0 * lam.clamp_min(0.0).sqrt()), 0.0)


class DensifyStrategy:
    """Densification and pruning as a strategy that owns its schedule and its statistics.

    The trainer calls two hooks every iteration: :meth:`step_pre_backward` with the posed splats (before the loss's
    backward: their centres must keep a gradient) and :meth:`step_post_backward` after it (and after the optimizer
    step), which accumulates the statistics and, on schedule, refines (:meth:`refine`). The schedule, as a
    preset states it (:meth:`from_preset`): statistics at iterations <= ``refine_until``; screen radii from the
    interval that ends after ``prune_big_after``; a refinement every ``refine_every`` iterations after
    ``refine_from`` (up to ``refine_until``), with world- and screen-size pruning after ``prune_big_after``.
    :meth:`state` / :meth:`from_state` carry the statistics through a checkpoint (the schedule comes from the
    preset, the grid from the face model)."""

    def __init__(self, n: int, extent: float, *, refine_from: int = 500, refine_until: int = 15_000,
                 refine_every: int = 100, grad_threshold: float = 1e-3, prune_opacity: float = 0.005,
                 max_gaussians: int = 200_000, prune_big_after: int = 3000,
                 max_screen_radius: float = MAX_SCREEN_RADIUS, grid: LookupGrid | None = None,
                 device: torch.device | str = "cpu"):
        self.extent = float(extent)
        self.refine_from, self.refine_until, self.refine_every = refine_from, refine_until, max(refine_every, 1)
        self.grad_threshold, self.prune_opacity, self.max_gaussians = grad_threshold, prune_opacity, max_gaussians
        self.prune_big_after, self.max_screen_radius = prune_big_after, max_screen_radius
        self.grid = grid  # where children and moved Gaussians get their LBS weights and d (None: their parent's)
        self.device = torch.device(device)  # the model's: the statistics live beside it
        self._reset(n)
        self._posed: Splats | None = None  # this iteration's posed splats, between the two hooks

    def _reset(self, n: int) -> None:
        """A new interval of statistics for ``n`` Gaussians."""
        self.grad_accum = torch.zeros(n, device=self.device)
        self.denom = torch.zeros(n, device=self.device)
        self.max_radii = torch.zeros(n, device=self.device)  # the largest screen radius (px) since the last refine

    @classmethod
    def from_preset(cls, preset: Preset, n: int, extent: float, grid: LookupGrid | None = None,
                    device: torch.device | str = "cpu") -> DensifyStrategy:
        """The preset's schedule and thresholds (``densify=False``: a strategy that never collects nor refines);
        ``device``: the model's."""
        return cls(n, extent, refine_from=preset.densify_from,
                   refine_until=preset.densify_until if preset.densify else 0, refine_every=preset.densify_every,
                   grad_threshold=preset.densify_grad, prune_opacity=preset.prune_opacity,
                   max_gaussians=preset.max_gaussians, prune_big_after=preset.prune_big_after,
                   max_screen_radius=preset.max_screen_radius, grid=grid, device=device)

    def state(self) -> dict:
        return {"extent": self.extent, "grad_accum": self.grad_accum.clone(), "denom": self.denom.clone(),
                "max_radii": self.max_radii.clone()}

    def load_state(self, state: dict) -> None:
        """The statistics of :meth:`state` (a checkpoint's, saved on any device)."""
        self.extent = float(state["extent"])
        dev = self.device
        self.grad_accum, self.denom = state["grad_accum"].to(dev, copy=True), state["denom"].to(dev, copy=True)
        self.max_radii = (state["max_radii"].to(dev, copy=True) if "max_radii" in state
                          else torch.zeros_like(self.denom))

    def select(self, index: Tensor) -> None:
        """Keep the statistics of the face Gaussians ``index`` only, in that order (after a removal that kept
        them, e.g. :mod:`.prune`'s)."""
        self.grad_accum, self.denom, self.max_radii = (t[index] for t in (self.grad_accum, self.denom,
                                                                          self.max_radii))

    # ------------------------------------------------------------------------------------------- the schedule
    def collects(self, iteration: int) -> bool:
        """Whether gradient statistics are gathered at this (1-based) iteration."""
        return iteration <= self.refine_until

    def step_pre_backward(self, iteration: int, posed: Splats) -> None:
        """Before the backward: keep the gradient of the posed centres when this iteration collects."""
        if self.collects(iteration) and posed.means.requires_grad:
            posed.means.retain_grad()
            self._posed = posed

    def step_post_backward(self, iteration: int, model: TrainableAvatar, opt: torch.optim.Optimizer,
                           gen: torch.Generator, cameras: Cameras) -> dict | None:
        """After the backward and the optimizer step: accumulate this iteration's statistics (the face Gaussians
        of the splats :meth:`step_pre_backward` saw, from ``cameras``) and refine on schedule; returns the counts
        of :meth:`refine` when it refined, else None."""
        posed, self._posed = self._posed, None
        if posed is None:
            return None
        n = model.num_gaussians
        self.accumulate(posed.means[0, :n].detach(), posed.means.grad[0, :n], cameras)
        if iteration > self.prune_big_after - self.refine_every:  # screen radii count from the interval before
            self.observe_radii(posed.means[0, :n], posed.quats[0, :n], posed.scales[0, :n], posed.opacities[0, :n],
                               cameras)
        if self.refine_from < iteration and iteration % self.refine_every == 0:
            counts = self.refine(model, opt, gen, prune_big=iteration > self.prune_big_after)
            log.info("iteration %d: %s", iteration, counts)
            return counts
        return None

    # ----------------------------------------------------------------------------------------- the mechanics
    def observe_radii(self, means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                      cameras: Cameras) -> None:
        """Keep the largest screen radius of every face Gaussian (posed [N, ...] tensors, :func:`screen_radii`)."""
        r = screen_radii(means, quats, scales, opacities, cameras).to(self.max_radii)
        self.max_radii = torch.maximum(self.max_radii, r)

    def accumulate(self, posed_means: Tensor, grad: Tensor, cameras: Cameras) -> None:
        """Add one frame's view-space gradient norms (``posed_means``/``grad``: [N, 3] world-space face Gaussians)."""
        R, t, K = cameras.R[0].to(grad), cameras.t[0].to(grad), cameras.K[0].to(grad)
        z = (posed_means.detach() @ R[2]) + t[2]
        g_cam = grad @ R.T
        gu = g_cam[:, 0] * z / K[0, 0] * (cameras.width / 2)
        gv = g_cam[:, 1] * z / K[1, 1] * (cameras.height / 2)
        norm = torch.sqrt(gu * gu + gv * gv)
        visible = grad.abs().sum(1) > 0
        self.grad_accum += torch.where(visible, norm, 0.0)
        self.denom += visible.to(self.denom.dtype)

    def refine(self, model: TrainableAvatar, opt: torch.optim.Optimizer, gen: torch.Generator,
               prune_big: bool = False) -> dict:
        """Densify and prune now; returns counts (cloned, split, pruned, pruned_screen, looked_up, gaussians) and
        starts a new interval of statistics.

        ``prune_big``: also prune Gaussians larger than 0.1 x extent in the world or ``max_screen_radius`` pixels
        on screen (the largest radius :meth:`observe_radii` saw since the last refinement). Splits draw their
        children from ``gen``."""
        n = model.num_gaussians
        avg = self.grad_accum / self.denom.clamp_min(1)
        with torch.no_grad():
            scale = model.log_scales.detach().exp().amax(1)
            prune = torch.sigmoid(model.opacity_logits.detach()) < self.prune_opacity
            screen = torch.zeros(n, dtype=torch.bool, device=self.device)
            if prune_big:
                prune |= scale > 0.1 * self.extent
                if len(self.max_radii) == n:
                    screen = (self.max_radii > self.max_screen_radius) & ~prune
                    prune |= screen
            chosen = (avg >= self.grad_threshold) & ~prune
            room = max(self.max_gaussians - int((~prune).sum()), 0)
            big = scale > PERCENT_DENSE * self.extent
            # Each clone adds one Gaussian, each split one net (two children replace the parent).
            if int(chosen.sum()) > room:
                order = torch.argsort(torch.where(chosen, avg, -1.0), descending=True, stable=True)
                keep_chosen = torch.zeros(n, dtype=torch.bool, device=self.device)
                keep_chosen[order[:room]] = True
                chosen &= keep_chosen
            clone = chosen & ~big
            split = chosen & big
            keep = ~prune & ~split
            keep_idx, clone_idx, split_idx = (m.nonzero().flatten() for m in (keep, clone, split))
            src = torch.cat([keep_idx, clone_idx, split_idx, split_idx])
            fresh = torch.cat([torch.zeros(len(keep_idx), dtype=torch.bool, device=self.device),
                               torch.ones(len(clone_idx) + 2 * len(split_idx), dtype=torch.bool, device=self.device)])
            updates = {}
            if len(split_idx):
                s = model.log_scales.detach()[split_idx].exp()
                rot = quat_to_matrix(torch.nn.functional.normalize(model.quats.detach()[split_idx], dim=-1))
                samples = torch.randn(2, len(split_idx), 3, generator=gen).to(s) * s  # drawn on the CPU
                offsets = (rot @ samples.unsqueeze(-1)).squeeze(-1)  # [2, S, 3]
                means = model.means.detach()
                children = means[split_idx].unsqueeze(0) + offsets
                start = len(keep_idx) + len(clone_idx)
                new_means = means[src].clone()
                new_means[start:] = children.reshape(-1, 3)
                new_scales = model.log_scales.detach()[src].clone()
                new_scales[start:] = torch.log(s / SPLIT_SCALE).repeat(2, 1)
                updates = {"means": new_means, "log_scales": new_scales}
            reindex(model, opt, src, fresh, updates)
            looked_up = 0
            grid = self.grid
            if grid is not None:
                moved = (model.means.detach() - model.lookup_at).norm(dim=1) > grid.cell
                idx = (fresh | moved).nonzero().flatten()
                if len(idx):
                    lbs, d = grid.lookup(model.means.detach()[idx])
                    assign_surface(model, opt, idx, lbs, d)
                looked_up = len(idx)
        self._reset(model.num_gaussians)
        return {"cloned": len(clone_idx), "split": len(split_idx), "pruned": int(prune.sum()),
                "pruned_screen": int(screen.sum()), "looked_up": looked_up, "gaussians": model.num_gaussians}


def _expand_pairs(pair_n: Tensor, src: Tensor, n_old: int) -> tuple[Tensor, Tensor]:
    """Pairs of the old Gaussians -> pairs of the new ones: (index of the old pair [P'], new Gaussian [P'])."""
    order = torch.argsort(src, stable=True)  # new Gaussians grouped by parent
    count = torch.bincount(src, minlength=n_old)
    start = torch.cumsum(count, 0) - count
    rep = count[pair_n]
    old_pair = torch.repeat_interleave(torch.arange(len(pair_n), device=pair_n.device), rep)
    offset = (torch.arange(len(old_pair), device=pair_n.device)
              - torch.repeat_interleave(torch.cumsum(rep, 0) - rep, rep))
    child = order[start[pair_n[old_pair]] + offset]
    return old_pair, child


def reindex(model: TrainableAvatar, opt: torch.optim.Optimizer, src: Tensor, fresh: Tensor,
            updates: dict[str, Tensor] | None = None) -> None:
    """Replace the face Gaussians by ``src`` (new Gaussian j is a copy of old Gaussian src[j]), carrying every
    per-Gaussian tensor, the (Gaussian, blendshape) pairs and the Adam moments (zero where ``fresh``)."""
    updates = updates or {}
    n_old = model.num_gaussians
    init_pair, init_child = _expand_pairs(model.init_n, src, n_old)
    hat_pair, hat_child = _expand_pairs(model.hat_n, src, n_old)
    hat_fresh = fresh[hat_child]

    # How each tensor is re-indexed: ("rows", dim) for per-Gaussian tensors, "init"/"hat" for pair tensors.
    plan: dict[str, tuple] = {}
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
        plan[name] = ("rows", 0)
    for name in ("d", "weights"):
        plan[name] = ("rows", 1)
    plan["lbs_weights"] = ("rows", 0)
    plan["lookup_at"] = ("rows", 0)
    for prop in PROPS:
        plan["init_" + prop] = ("init",)
        hat = model.hat(prop)
        if hat is not None:
            plan["hat_" + prop] = ("hat",) if model.weighted(prop) else ("rows", 1)
    plan["init_k"] = ("init",)
    plan["hat_k"] = ("hat",)
    plan["hat_w"] = ("hat",)

    def apply(name: str, t: Tensor, moment: bool = False) -> Tensor:
        how = plan[name]
        if how[0] == "rows":
            out = t.index_select(how[1], src)
            if moment:
                shape = [1] * out.dim()
                shape[how[1]] = -1
                out = out * (~fresh).reshape(shape).to(out.dtype)
            return out
        if how[0] == "init":
            return t[init_pair]
        out = t[hat_pair]
        if moment:
            out = out * (~hat_fresh).reshape(-1, *([1] * (out.dim() - 1))).to(out.dtype)
        return out

    params = dict(model.named_parameters())
    for name in plan:
        if name in params:
            value = updates[name] if name in updates else apply(name, params[name].detach())
            swap_parameter(model, opt, name, value, lambda v, name=name: apply(name, v, moment=True))
        else:
            model.register_buffer(name, apply(name, getattr(model, name)))
    model.register_buffer("init_n", init_child)
    model.register_buffer("hat_n", hat_child)
    if model.pose_correctives is not None:
        model.pose_correctives = model.pose_correctives.index_select(1, src)
    if model.eyelid_offsets is not None:
        model.eyelid_offsets = model.eyelid_offsets.index_select(1, src)


def swap_parameter(model: TrainableAvatar, opt: torch.optim.Optimizer, name: str, value: Tensor,
                   moments) -> None:
    """Replace parameter ``name`` by ``value`` in the model and the optimizer; Adam's moments go through
    ``moments`` (old moment -> new moment), other state (the step) is kept."""
    old = getattr(model, name)
    new = nn.Parameter(value)
    for group in opt.param_groups:
        if group["params"][0] is old:
            state = opt.state.pop(old, None)
            if state:
                opt.state[new] = {k: (moments(v) if k in ("exp_avg", "exp_avg_sq") else v) for k, v in state.items()}
            group["params"][0] = new
            break
    setattr(model, name, new)


def assign_surface(model: TrainableAvatar, opt: torch.optim.Optimizer, index: Tensor, lbs: Tensor,
                   d: Tensor) -> None:
    """Give face Gaussians ``index`` [P] new LBS weights [P, J] and displacement magnitudes d [K, P] (looked up at
    their current positions, which become ``lookup_at``). The consistency weights c = max(f(d), 0) follow, and
    with them the weighted pairs: a pair that stays keeps its residual dG_hat and Adam moments, a new pair (c
    became > 0) starts at zero, a pair whose c became 0 is dropped. dG_init is not touched."""
    with torch.no_grad():
        model.lbs_weights[index] = lbs.to(model.lbs_weights)
        model.d[:, index] = d.to(model.d)
        model.lookup_at[index] = model.means.detach()[index]
        model.weights = consistency_weights(model.d, model.eps, model.d_max)
        n = model.num_gaussians
        new_k, new_n = (model.weights > 0).nonzero(as_tuple=True)
        old_key, order = torch.sort(model.hat_k * n + model.hat_n)
        new_key = new_k * n + new_n
        if len(old_key):
            pos = torch.searchsorted(old_key, new_key).clamp(max=len(old_key) - 1)
            found = old_key[pos] == new_key
            src = order[pos]
        else:
            found = torch.zeros(len(new_key), dtype=torch.bool, device=new_key.device)
            src = torch.zeros(len(new_key), dtype=torch.long, device=new_key.device)

        def carry(t: Tensor) -> Tensor:
            out = t.new_zeros(len(new_key), *t.shape[1:])
            out[found] = t[src[found]]
            return out

        for prop in PROPS:
            hat = model.hat(prop)
            if hat is not None and model.weighted(prop):
                swap_parameter(model, opt, "hat_" + prop, carry(hat.detach()), carry)
        model.hat_k, model.hat_n = new_k, new_n
        model.hat_w = model.weights[new_k, new_n].clone()
