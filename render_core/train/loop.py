"""The training loop: a tracked video (portable dataset) -> a Gaussian blendshape avatar bundle.

Per iteration (docs/method.md sections 5 and 6): one random training frame (a seeded generator), blend (Eq. 1 with
the consistency parametrisation of :mod:`.model`) -> skin -> shade (SH at the view direction, degree ramped) ->
the differentiable rasterizer (native C++ forward and backward; gsplat's on CUDA) -> 0.8 L1 + 0.2 D-SSIM
+ 10 alpha MSE + 100 mouth cylinder -> backward -> Adam (eps 1e-15, per-group learning rates, xyz decay).

Reads only what a real user has: the dataset's frames, masks and tracking. Checkpoints (tensors, optimizer state,
RNG state, iteration; loaded with ``weights_only=True``) go to ``<workdir>/checkpoints``; ``resume=True``
continues from the last one and gives the same parameters as an uninterrupted run.
"""

from __future__ import annotations

import json
import logging
import math
import os
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from ..bundle import write_bundle
from ..camera import Cameras
from ..data import read_dataset
from ..data.frames import check_compatible, frame_inputs, targets
from ..deform import Frame, shade, skin
from ..errors import DatasetError
from ..facemodel import FaceModel, read_facemodel
from ..raster import ShadedSplats, native
from . import losses
from .densify import Densifier
from .grids import lookup_grid
from .initialize import init_avatar
from .model import TrainableAvatar
from .presets import Preset, get_preset

log = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "blendsplat-train-checkpoint"
CHECKPOINT_VERSION = 1
STAGES = ("data", "blend", "skin", "shade", "raster", "loss", "backward", "optimizer", "densify")


# ------------------------------------------------------------------------------------------------- helpers
def resolve_facemodel(face_model_name: str, facemodel: FaceModel | str | os.PathLike | None,
                      cache_dir: str | os.PathLike | None = None) -> FaceModel:
    """The face model the dataset was tracked with: ``facemodel`` if given (a FaceModel or a face-model file),
    else the open head when the tracking names it; otherwise a DatasetError naming what to pass."""
    if facemodel is not None:
        model = facemodel if isinstance(facemodel, FaceModel) else read_facemodel(facemodel)
    else:
        from ..facemodel.open_head import NAME, open_head

        if face_model_name != NAME:
            raise DatasetError(
                f"the dataset was tracked with face model {face_model_name!r}; only the open head ({NAME!r}) is "
                "built in: pass the face-model file it names (train(..., facemodel=PATH), e.g. one made by "
                "`blendsplat facemodel import-flame`)", field="face_model")
        model = open_head(cache_dir)
    if model.name != face_model_name:
        raise DatasetError(f"the dataset was tracked with face model {face_model_name!r}, not {model.name!r}",
                           field="face_model")
    return model


def _shaped(model: FaceModel, shape: np.ndarray) -> FaceModel:
    """The face model with the dataset's identity shape applied to its template (when it has shape blendshapes)."""
    from dataclasses import replace

    s = torch.from_numpy(np.asarray(shape, dtype=np.float32)).flatten()
    if s.numel() == 0 or model.shape_basis is None or not bool(s.abs().sum()):
        return model
    template, joints = model.shaped(s[: model.num_shape])
    return replace(model, template=template.float(), joint_positions=joints.float())


def xyz_lr(preset: Preset, step: int) -> float:
    """3DGS's exponential decay from lr_xyz to lr_xyz_final over xyz_decay_steps (then constant)."""
    t = min(max(step / max(preset.xyz_decay_steps, 1), 0.0), 1.0)
    return math.exp(math.log(preset.lr_xyz) * (1 - t) + math.log(preset.lr_xyz_final) * t)


def active_sh_degree(preset: Preset, iteration: int) -> int:
    """SH degree at a (1-based) iteration: one band more every ``sh_every`` iterations."""
    return min(preset.sh_degree, iteration // max(preset.sh_every, 1))


def make_optimizer(model: TrainableAvatar, preset: Preset) -> torch.optim.Adam:
    """Adam (eps 1e-15) with docs/method.md section 6's per-group learning rates (fused where supported)."""
    rates = {
        "means": preset.lr_xyz, "quats": preset.lr_rotation, "log_scales": preset.lr_scale,
        "opacity_logits": preset.lr_opacity, "sh_dc": preset.lr_sh_dc, "sh_rest": preset.lr_sh_rest,
        "hat_means": preset.lr_hat_xyz, "hat_quats": preset.lr_hat_rotation, "hat_log_scales": preset.lr_hat_scale,
        "hat_opacity_logits": preset.lr_hat_opacity, "hat_sh": preset.lr_hat_sh,
    }
    groups = []
    for name, p in model.named_parameters():
        key = name[len("mouth_"):] if name.startswith("mouth_") else name
        groups.append({"params": [p], "lr": rates[key], "name": name})
    device = next(model.parameters()).device
    for kwargs in ({"fused": True}, {"foreach": True}, {}):
        try:
            opt = torch.optim.Adam(groups, eps=1e-15, **kwargs)
            if kwargs.get("fused") and device.type == "cpu":
                # Some builds accept fused=True but fail at the first step: probe on a throwaway parameter.
                probe = torch.nn.Parameter(torch.zeros(2, device=device))
                probe.grad = torch.ones(2, device=device)
                torch.optim.Adam([probe], eps=1e-15, fused=True).step()
            return opt
        except (RuntimeError, TypeError, ValueError):
            continue
    raise RuntimeError("no Adam implementation available")


def optimizer_kind(opt: torch.optim.Optimizer) -> str:
    d = opt.defaults
    return "fused" if d.get("fused") else "foreach" if d.get("foreach") else "for-loop"


def check_device(device: str) -> None:
    """The trainer's devices: "cpu" (the native rasterizer's C++ backward) and "cuda" (gsplat's kernels); an error
    naming what is missing otherwise."""
    if device == "cpu":
        if not native.available():
            raise RuntimeError(f"training on the CPU needs the native backend ({native.IMPORT_ERROR})")
    elif device == "cuda":
        from ..raster import gsplat_backend

        if not gsplat_backend.available():
            raise RuntimeError(f"training with device='cuda' needs the cuda backend: "
                               f"{gsplat_backend.unavailable_reason()}")
    else:
        raise ValueError(f"device must be 'cpu' or 'cuda', got {device!r}")


def rasterize(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
              colors: torch.Tensor, cameras: Cameras, mode: str, *, device: str = "cpu",
              threads: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """The differentiable rasterization step on ``device``: rgb [B, H, W, 3], alpha [B, H, W] on black.

    "cpu": the native forward and C++ backward; "cuda": gsplat's CUDA forward and backward (CPU inputs move to the
    GPU and rgb, alpha come back to the inputs' device, all differentiably)."""
    splats = ShadedSplats(means, quats, scales, opacities, colors)
    if device == "cuda":
        from ..raster import gsplat_backend

        return gsplat_backend.rasterize_differentiable(splats, cameras, None, mode)
    return native.rasterize_differentiable(splats, cameras, None, mode, threads=threads)


def forward(model: TrainableAvatar, frame: Frame, cameras: Cameras, sh_degree: int | None = None,
            threads: int = 0, times: dict | None = None,
            capture: dict | None = None, device: str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """Render B frames of the model (differentiable): rgb [B, H, W, 3], alpha [B, H, W] on a black background.

    ``capture``: receives the posed centres ("means", [B, N + M, 3], their gradient kept) and the posed splats
    ("splats") for densification.
    ``device``: where the rasterization step runs (:func:`rasterize`)."""
    clock = time.perf_counter
    t0 = clock()
    avatar = model.avatar(sh_degree, deltas=False)
    blended = model.blend(frame.expression, sh_degree)
    t1 = clock()
    splats = skin(avatar, blended, frame)
    if capture is not None and splats.means.requires_grad:
        splats.means.retain_grad()
        capture["means"] = splats.means
        capture["splats"] = splats
    t2 = clock()
    colors = shade(splats, cameras.centres.to(splats.means))
    t3 = clock()
    rgb, alpha = rasterize(splats.means, splats.quats, splats.scales, splats.opacities, colors, cameras,
                           avatar.raster_mode, device=device, threads=threads)
    t4 = clock()
    if times is not None:
        times["blend"] += t1 - t0
        times["skin"] += t2 - t1
        times["shade"] += t3 - t2
        times["raster"] += t4 - t3
    return rgb, alpha


class _Targets:
    """Masked training targets, decoded once and kept (up to ``budget`` bytes)."""

    def __init__(self, dataset, budget: int = 2 << 30):
        self.dataset, self.budget, self.used = dataset, budget, 0
        self.cache: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}

    def __call__(self, index: int) -> tuple[torch.Tensor, torch.Tensor]:
        hit = self.cache.get(index)
        if hit is not None:
            return hit
        rgb, mask = targets(self.dataset, [index])
        size = rgb.numel() * 4 + mask.numel() * 4
        if self.used + size <= self.budget:
            self.cache[index] = (rgb, mask)
            self.used += size
        return rgb, mask


# --------------------------------------------------------------------------------------------- checkpoints
def checkpoint_dir(workdir: Path) -> Path:
    return workdir / "checkpoints"


def last_checkpoint(workdir: Path) -> Path | None:
    files = sorted(checkpoint_dir(workdir).glob("ckpt_*.pt"))
    return files[-1] if files else None


def save_checkpoint(path: Path, *, iteration: int, model: TrainableAvatar, opt: torch.optim.Optimizer,
                    gen: torch.Generator, preset: Preset, cylinder: losses.MouthCylinder, seed: int,
                    seconds: float, densifier: Densifier, keep: int = 2) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {
        "format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "iteration": iteration,
        "model": model.state(),
        "optimizer": opt.state_dict(), "rng": gen.get_state(), "preset": preset.to_dict(),
        "cylinder": cylinder.to_dict(), "seed": seed, "seconds": seconds, "densifier": densifier.state(),
    }
    tmp = path.with_suffix(".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)
    old = sorted(path.parent.glob("ckpt_*.pt"))[:-keep]
    for f in old:
        f.unlink(missing_ok=True)
    return path


def load_checkpoint(path: Path) -> dict:
    """One of our checkpoints, loaded with ``weights_only=True`` (tensors, numbers, strings, lists, dicts)."""
    state = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path} is not a blendsplat training checkpoint")
    if state.get("version") != CHECKPOINT_VERSION:
        raise ValueError(f"{path}: checkpoint version {state.get('version')} is not {CHECKPOINT_VERSION}")
    return state


# ----------------------------------------------------------------------------------------------------- train
def _report(bundle: Path, data_dir, workdir: Path, held_out: int) -> dict:
    """Held-out evaluation (report JSON and contact sheet) and the loss curves, in the workdir."""
    from ..evaluation.plot import plot_curves
    from ..evaluation.report import evaluate

    out = {"plot": str(plot_curves(workdir / "log.jsonl", workdir / "curves.png", keys=("loss", "psnr")))}
    if held_out:
        e = evaluate(bundle, data_dir, split="test", report=workdir / "report.json",
                     contact_sheet=workdir / "contact_sheet.png")
        out["eval"] = {k: e[k] for k in ("psnr", "ssim", "psnr_head", "frames", "report", "contact_sheet")}
    return out


def train(
    data_dir: str | os.PathLike,
    out_bundle: str | os.PathLike,
    workdir: str | os.PathLike | None = None,
    preset: str | Preset = "tiny",
    device: str = "cpu",
    resume: bool = False,
    seed: int = 0,
    iterations: int | None = None,
    progress: bool = True,
    *,
    facemodel: FaceModel | str | os.PathLike | None = None,
    cache_dir: str | os.PathLike | None = None,
    consistency: str | None = None,
    stop_after: int | None = None,
) -> dict:
    """Train an avatar on a portable dataset and write it to ``out_bundle`` (fp16 blendshape storage).

    Args:
        data_dir: the portable dataset (frames, masks, tracking; only the training indices are used).
        out_bundle: where the bundle goes.
        workdir: checkpoints and ``log.jsonl`` (default: ``<out_bundle stem>.train`` beside the bundle).
        preset: ``"tiny"``, ``"paper"`` or a :class:`Preset`.
        device: where the rasterization step runs: ``"cpu"`` (the native rasterizer's C++ backward) or
            ``"cuda"`` (gsplat's CUDA forward and backward; the rest of the step stays on the CPU for now).
        resume: continue from the last checkpoint in ``workdir`` (its preset and seed win).
        seed: initialisation and frame-sampling seed.
        iterations: total iterations (default: the preset's).
        progress: a tqdm bar on stderr (iteration, loss, PSNR, ETA).
        facemodel: the face model (a FaceModel or a face-model file) when the dataset's is not the open head.
        cache_dir: where the open head model is cached (default: ``$BLENDSPLAT_DATA_DIR/facemodels``).
        consistency: overrides the preset's ``"all" | "positions" | "none" | "frozen"``.
        stop_after: stop after this iteration with a checkpoint and no bundle (an interruption, for tests).

    Returns:
        A summary dict (see the report fields: iterations, seconds, stage_ms, loss/psnr first and last, final
        per-frame PSNR of the exported avatar on training frames, bundle, workdir, ...).
    """
    check_device(device)
    t_start = time.perf_counter()
    out_bundle = Path(out_bundle)
    workdir = Path(workdir) if workdir is not None else out_bundle.with_name(out_bundle.stem + ".train")
    workdir.mkdir(parents=True, exist_ok=True)
    cfg = get_preset(preset)
    if consistency is not None:
        cfg = cfg.with_(consistency=consistency)

    dataset = read_dataset(data_dir)
    tracking = dataset.tracking
    fm = _shaped(resolve_facemodel(tracking.face_model, facemodel, cache_dir), tracking.shape)

    state = None
    ckpt = last_checkpoint(workdir) if resume else None
    if resume and ckpt is None:
        log.warning("no checkpoint in %s: starting from scratch", checkpoint_dir(workdir))
    if ckpt is not None:
        state = load_checkpoint(ckpt)
        cfg = Preset(**state["preset"])
        seed = int(state["seed"])
    if iterations is not None:
        cfg = cfg.with_(iterations=int(iterations))

    if state is None:
        init = init_avatar(fm, gaussians=cfg.gaussians, mouth=cfg.mouth, sh_degree=cfg.sh_degree,
                           opacity=cfg.init_opacity, seed=seed)
        init.provenance = {**init.provenance, "generator": "blendsplat train"}
        model = TrainableAvatar.from_facemodel(init, fm, cfg.consistency)
        cylinder = losses.MouthCylinder.from_points(init.mouth.means)
        gen = torch.Generator().manual_seed(seed)
        x = init.neutral.means
        densifier = Densifier(model.num_gaussians, float((x - x.mean(0)).norm(dim=1).max()))
        start = 0
        prior_seconds = 0.0
        (workdir / "log.jsonl").write_text("")
        for old in checkpoint_dir(workdir).glob("ckpt_*.pt"):  # a fresh run: an older run's are stale
            old.unlink()
    else:
        model = TrainableAvatar.from_state(state["model"])
        cylinder = losses.MouthCylinder.from_dict(state["cylinder"])
        gen = torch.Generator()
        gen.set_state(state["rng"])
        densifier = Densifier.from_state(state["densifier"])
        start = int(state["iteration"])
        prior_seconds = float(state["seconds"])
        _truncate_log(workdir / "log.jsonl", start)
    opt = make_optimizer(model, cfg)
    grid = lookup_grid(fm, cfg.grid_resolution) if cfg.densify and cfg.grid_resolution else None
    grid_start = (grid.built, grid.build_seconds) if grid is not None else (0, 0.0)  # the grid may be shared
    if state is not None:
        opt.load_state_dict(state["optimizer"])
        del state

    view = model.avatar(detach=True, deltas=False)
    check_compatible(view, tracking)
    train_idx = np.asarray(tracking.train, dtype=np.int64)
    if len(train_idx) == 0:
        raise DatasetError("the dataset lists no training frames", field="train")
    frames_all, cams_all = frame_inputs(view, tracking, train_idx)
    target = _Targets(dataset)

    total = cfg.iterations
    end = total if stop_after is None else min(total, int(stop_after))
    times: dict[str, float] = defaultdict(float)
    history: list[dict] = []
    densified: list[dict] = []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, initial=start, file=sys.stderr, desc="train", unit="it", dynamic_ncols=True)
    clock = time.perf_counter
    run_start = clock()
    logf = open(workdir / "log.jsonl", "a")
    try:
        for it in range(start + 1, end + 1):
            t0 = clock()
            j = int(torch.randint(len(train_idx), (1,), generator=gen))
            frame = _select(frames_all, j)
            cams = _select_cams(cams_all, j)
            rgb_t, mask_t = target(int(train_idx[j]))
            degree = active_sh_degree(cfg, it)
            for g in opt.param_groups:
                if g["name"] in ("means", "mouth_means"):
                    g["lr"] = xyz_lr(cfg, it)
            times["data"] += clock() - t0
            stats = cfg.densify and it <= cfg.densify_until
            capture: dict | None = {} if stats else None
            rgb, alpha = forward(model, frame, cams, degree, cfg.threads, times, capture, device=device)
            t1 = clock()
            loss, terms = losses.total_loss(rgb, alpha, rgb_t, mask_t, model.mouth_means, cylinder)
            t2 = clock()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            t3 = clock()
            opt.step()
            t4 = clock()
            times["loss"] += t2 - t1
            times["backward"] += t3 - t2
            times["optimizer"] += t4 - t3
            if stats:
                n = model.num_gaussians
                posed = capture["means"]
                densifier.accumulate(posed[0, :n].detach(), posed.grad[0, :n], cams)
                if it > cfg.prune_big_after - cfg.densify_every:  # screen radii count from the step before
                    sp = capture["splats"]
                    densifier.observe_radii(sp.means[0, :n], sp.quats[0, :n], sp.scales[0, :n], sp.opacities[0, :n],
                                            cams)
                if cfg.densify_from < it and it % cfg.densify_every == 0:
                    counts = densifier.step(model, opt, gen, cfg.densify_grad, cfg.prune_opacity, cfg.max_gaussians,
                                            prune_big=it > cfg.prune_big_after,
                                            max_screen_radius=cfg.max_screen_radius, grid=grid)
                    log.info("iteration %d: %s", it, counts)
                    densified.append({"iteration": it, **counts})
                capture = posed = None
            times["densify"] += clock() - t4
            if it % cfg.log_every == 0 or it == end or it == 1:
                vals = {k: float(v.detach()) for k, v in terms.items()}
                rec = {"iteration": it, "loss": float(loss.detach()), **vals,
                       "psnr": losses.psnr(rgb, rgb_t), "frame": int(train_idx[j]), "sh_degree": degree,
                       "gaussians": model.num_gaussians,
                       "seconds": round(prior_seconds + clock() - run_start, 3)}
                history.append(rec)
                logf.write(json.dumps(rec) + "\n")
                logf.flush()
                if bar is not None:
                    bar.set_postfix(loss=f"{rec['loss']:.4f}", psnr=f"{rec['psnr']:.2f}", refresh=False)
            if bar is not None:
                bar.update(1)
            if it % cfg.checkpoint_every == 0 or it == end:
                save_checkpoint(checkpoint_dir(workdir) / f"ckpt_{it:07d}.pt", iteration=it, model=model, opt=opt,
                                gen=gen, preset=cfg, cylinder=cylinder, seed=seed,
                                seconds=prior_seconds + clock() - run_start, densifier=densifier)
    finally:
        logf.close()
        if bar is not None:
            bar.close()
    run_seconds = clock() - run_start
    done = end - start
    summary: dict = {
        "workdir": str(workdir), "preset": cfg.name, "consistency": model.consistency, "seed": seed,
        "iterations": end, "iterations_this_run": done, "resumed_from": start if start else None,
        "gaussians": model.num_gaussians, "mouth": int(model.mouth_means.shape[0]),
        "expressions": len(model.meta["expression_names"]), "size": [int(tracking.width), int(tracking.height)],
        "train_frames": len(train_idx), "device": device, "optimizer": optimizer_kind(opt), "eps": model.eps,
        "d_max": model.d_max,
        "seconds": round(prior_seconds + run_seconds, 3),
        "ms_per_iteration": round(1e3 * run_seconds / done, 2) if done else None,
        "stage_ms": {s: round(1e3 * times[s] / done, 2) for s in STAGES} if done else {},
        "first": history[0] if history else None, "last": history[-1] if history else None,
        "densified": densified,
        "grid": None if grid is None else {"resolution": grid.resolution, "bricks_built": grid.built - grid_start[0],
                                           "build_seconds": round(grid.build_seconds - grid_start[1], 3)},
    }
    if end < total:  # interrupted on purpose: no bundle
        summary["bundle"] = None
        summary["stopped"] = True
        return summary

    avatar = model.to_avatar(provenance={"trained": {"iterations": end, "preset": cfg.name, "seed": seed,
                                                     "consistency": model.consistency,
                                                     "dataset": str(Path(data_dir).name)}})
    out_bundle.parent.mkdir(parents=True, exist_ok=True)
    write_bundle(avatar, out_bundle, precision="fp16")
    summary["bundle"] = str(out_bundle)
    summary["final"] = final_psnr(model, frames_all, cams_all, train_idx, target, cfg, device)
    summary.update(_report(out_bundle, data_dir, workdir, len(dataset.tracking.test)))
    summary["seconds_total"] = round(time.perf_counter() - t_start, 3)
    (workdir / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def final_psnr(model: TrainableAvatar, frames_all: Frame, cams_all: Cameras, train_idx: np.ndarray, target,
               cfg: Preset, device: str = "cpu") -> dict:
    """PSNR (full frame, masked target) of the trained model on up to ``cfg.final_eval_frames`` training frames,
    rendered at the full SH degree (the exported avatar's) with the training rasterizer."""
    count = min(cfg.final_eval_frames, len(train_idx))
    picks = np.unique(np.linspace(0, len(train_idx) - 1, count).round().astype(np.int64))
    out = {"frames": [], "psnr": []}
    with torch.no_grad():
        for j in picks.tolist():
            rgb, _ = forward(model, _select(frames_all, j), _select_cams(cams_all, j), None, cfg.threads,
                             device=device)
            want, _ = target(int(train_idx[j]))
            out["frames"].append(int(train_idx[j]))
            out["psnr"].append(round(losses.psnr(rgb, want), 4))
    out["psnr_mean"] = round(float(np.mean(out["psnr"])), 4) if out["psnr"] else None
    return out


def _select(frames: Frame, j: int) -> Frame:
    return Frame(frames.expression[j:j + 1], frames.joint_rotations[j:j + 1],
                 None if frames.eyelids is None else frames.eyelids[j:j + 1])


def _select_cams(cams: Cameras, j: int) -> Cameras:
    return Cameras(cams.K[j:j + 1], cams.R[j:j + 1], cams.t[j:j + 1], cams.width, cams.height)


def _truncate_log(path: Path, iteration: int) -> None:
    """Keep the log lines up to ``iteration`` (a resumed run rewrites what came after its checkpoint)."""
    if not path.is_file():
        return
    keep = []
    for line in path.read_text().splitlines():
        try:
            if json.loads(line)["iteration"] <= iteration:
                keep.append(line)
        except (ValueError, KeyError, TypeError):
            continue
    path.write_text("".join(k + "\n" for k in keep))
