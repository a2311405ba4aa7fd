"""Training as an object a command or a job worker drives: :class:`Trainer` (and :func:`train`, the whole run).

Per iteration (docs/method.md sections 5 and 6): one random training frame (a seeded generator), blend (Eq. 1 with
the consistency parametrisation of :mod:`.model`) -> skin -> shade (SH at the view direction, degree ramped) ->
the differentiable rasterizer (the backend registry's step for the device: the native C++ forward and backward on
the CPU, gsplat's on CUDA) -> 0.8 L1 + 0.2 D-SSIM + 10 alpha MSE + 100 mouth cylinder -> backward -> Adam (eps
1e-15, per-group learning rates, xyz decay) -> densification (:class:`.densify.DensifyStrategy`, on its schedule)
-> pruning by contribution (:class:`.prune.ContributionPruner`, at the preset's ``prune_at`` iterations).

The trainer's state is the model, the optimizer, the frame-sampling generator, the densification strategy's
statistics, the pruning record and the iteration; the schedule (SH ramp, xyz decay, densification, pruning, log
and checkpoint intervals) is the preset's. :meth:`Trainer.checkpoint` saves all of it and :meth:`Trainer.resume`
restores it, so a resumed training gives the same parameters as an uninterrupted one. Reads only what a real user
has: the dataset's frames, masks and tracking.

The work folder: ``checkpoints/ckpt_<iteration>.pt`` (the last two; local files of tensors, numbers and strings,
loaded with ``weights_only=True``), ``log.jsonl`` (a record every ``log_every`` iterations, the first, the last
and every checkpointed one) and, after :meth:`Trainer.finish`, ``summary.json``, the loss curves and the held-out
evaluation. Every file is written beside under a temporary name and renamed into place (:mod:`render_core.atomic`;
a failed write removes its temporary file); those a killed run left (a torn checkpoint) are removed when the work
folder is next trained in (:func:`remove_torn`: at :meth:`Trainer.resume` and before a run's first write).
"""

from __future__ import annotations

import json
import logging
import math
import os
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, replace
from enum import StrEnum
from pathlib import Path

import numpy as np
import torch

from .. import raster
from ..atomic import atomic_path, remove_stale
from ..bundle import write_bundle
from ..camera import Cameras
from ..data import read_dataset
from ..data.frames import check_compatible, frame_inputs, targets
from ..deform import Frame, Splats, shade, skin
from ..errors import DatasetError, OptionError
from ..evaluation.align import moved_splats
from ..evaluation.metrics import psnr
from ..facemodel import FaceModel, read_facemodel
from . import losses
from .densify import DensifyStrategy
from .grids import lookup_grid
from .initialize import init_avatar
from .model import TrainableAvatar
from .poses import FramePoses
from .presets import Preset, get_preset
from .prune import ContributionPruner

log = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "blendsplat-train-checkpoint"
CHECKPOINT_VERSION = 1
CHECKPOINTS_KEPT = 2
STAGES = ("data", "blend", "skin", "shade", "raster", "loss", "backward", "optimizer", "densify", "prune")
DEVICES = {"cpu": "native", "cuda": "cuda"}  # training device -> the raster backend whose differentiable step runs


# ------------------------------------------------------------------------------------------------- the events
@dataclass(frozen=True)
class Progress:
    """One trained iteration, as :meth:`Trainer.step` returns it and the progress callback receives it."""

    iteration: int  # the iteration just trained (1-based)
    total: int  # the training's last iteration
    losses: dict[str, float]  # "loss" (the total) and its terms: "l1", "ssim" (the SSIM), "alpha", "mouth"
    psnr: float  # of this iteration's render against its (masked) target, dB
    gaussians: int  # face Gaussians after this iteration (densification changes the count)
    elapsed: float  # training seconds so far, those of the runs before a resume included
    eta: float | None  # seconds left to ``total`` at this run's mean seconds per iteration
    frame: int  # the dataset index of the frame trained on
    sh_degree: int
    densified: dict | None = None  # the densification counts when this iteration refined
    pruned: dict | None = None  # the contribution-pruning counts when this iteration pruned
    preview: np.ndarray | None = None  # [H, W, 3] uint8 (:meth:`Trainer.preview`) when the run was asked for one


class Outcome(StrEnum):
    """How :meth:`Trainer.run` ended (it checkpoints in every case)."""

    FINISHED = "finished"  # the last iteration is trained
    STOPPED = "stopped"  # the run reached its ``until``
    CANCELLED = "cancelled"  # ``should_cancel`` said so between two steps


CancelCheck = Callable[[], bool] | threading.Event


# ------------------------------------------------------------------------------------------------- helpers
def resolve_facemodel(face_model_name: str, facemodel: FaceModel | str | os.PathLike | None) -> FaceModel:
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
        model = open_head()
    if model.name != face_model_name:
        raise DatasetError(f"the dataset was tracked with face model {face_model_name!r}, not {model.name!r}",
                           field="face_model")
    return model


def _shaped(model: FaceModel, shape: np.ndarray) -> FaceModel:
    """The face model with the dataset's identity shape applied to its template (when it has shape blendshapes)."""
    s = torch.from_numpy(np.asarray(shape, dtype=np.float32)).flatten()
    if s.numel() == 0 or model.shape_basis is None or not bool(s.abs().sum()):
        return model
    template, joints = model.shaped(s[: model.num_shape])
    return replace(model, template=template.float(), joint_positions=joints.float())


def xyz_lr(preset: Preset, step: int) -> float:
    """3DGS's exponential decay from lr_xyz to lr_xyz_final over xyz_decay_steps (then constant)."""
    t = min(max(step / max(preset.xyz_decay_steps, 1), 0.0), 1.0)
    return math.exp(math.log(preset.lr_xyz) * (1 - t) + math.log(preset.lr_xyz_final) * t)


def refine_lr(preset: Preset, iteration: int, total: int) -> float:
    """The per-frame corrections' learning rate at an iteration, as a fraction of their first: an exponential
    decay from ``refine_poses_from`` to ``refine_lr_final`` at the last iteration."""
    t = min(max((iteration - preset.refine_poses_from) / max(total - preset.refine_poses_from, 1), 0.0), 1.0)
    return preset.refine_lr_final ** t


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


def raster_step(device: str) -> raster.Differentiable:
    """The differentiable rasterization step for training on ``device`` ("cpu": the native backend's C++
    backward; "cuda": gsplat's kernels), from the backend registry; an error naming what is missing otherwise."""
    if device not in DEVICES:
        raise OptionError(f"must be 'cpu' or 'cuda', got {device!r}", field="device")
    backend = DEVICES[device]
    try:
        return raster.differentiable(backend)
    except OptionError:
        raise OptionError(f"training with device={device!r} needs the {backend} backend: "
                          f"{raster.unavailable_reason(backend)}", field="device") from None


def torch_device(device: str) -> torch.device:
    """Where training's tensors live for ``device``: the CPU, or the cuda backend's GPU (model, frames, targets,
    loss, Adam and the densification statistics all stay there; only the frame-sampling generator is the CPU's)."""
    if device == "cuda":
        from ..raster import gsplat_backend

        return gsplat_backend.device()
    return torch.device("cpu")


def stage_clock(device: torch.device) -> Callable[[], float]:
    """``time.perf_counter`` that first waits for the device's queued work (on a GPU, a stage's time is the
    kernels it launched, not the launches)."""
    if device.type == "cuda":
        return lambda: (torch.cuda.synchronize(device), time.perf_counter())[1]
    return time.perf_counter


def forward(model: TrainableAvatar, frame: Frame, cameras: Cameras, sh_degree: int | None = None, *,
            rasterize: raster.Differentiable | None = None, threads: int = 0,
            times: dict | None = None, clock: Callable[[], float] = time.perf_counter,
            motion: tuple[torch.Tensor, torch.Tensor] | None = None,
            ) -> tuple[torch.Tensor, torch.Tensor, Splats]:
    """Render B frames of the model (differentiable): rgb [B, H, W, 3], alpha [B, H, W] on a black background,
    and the posed splats (face Gaussians first; densification reads them).

    ``rasterize``: the rasterization step (:func:`raster_step`; default the CPU's). ``times``: stage seconds
    (read with ``clock``, :func:`stage_clock`) are added to it. ``motion``: (w [B, 3], u [B, 3]), a rigid
    correction of each frame's head (:class:`.poses.FramePoses`), or None."""
    rasterize = rasterize or raster_step("cpu")
    t0 = clock()
    avatar = model.avatar(sh_degree, deltas=False)
    blended = model.blend(frame.expression, sh_degree)
    t1 = clock()
    splats = skin(avatar, blended, frame)
    t2 = clock()
    if motion is None:
        colors = shade(splats, cameras.centres.to(splats.means))
        shaded = raster.ShadedSplats(splats.means, splats.quats, splats.scales, splats.opacities, colors)
    else:
        shaded = moved_splats(splats, cameras, *motion)
    t3 = clock()
    rgb, alpha = rasterize(shaded, cameras, None, avatar.raster_mode, threads=threads)
    t4 = clock()
    if times is not None:
        times["blend"] += t1 - t0
        times["skin"] += t2 - t1
        times["shade"] += t3 - t2
        times["raster"] += t4 - t3
    return rgb, alpha, splats


class _Targets:
    """Masked training targets, decoded once and kept on ``device`` (up to ``budget`` bytes)."""

    def __init__(self, dataset, budget: int = 2 << 30, device: torch.device | str = "cpu"):
        self.dataset, self.budget, self.used, self.device = dataset, budget, 0, torch.device(device)
        self.cache: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}

    def __call__(self, index: int) -> tuple[torch.Tensor, torch.Tensor]:
        hit = self.cache.get(index)
        if hit is not None:
            return hit
        rgb, mask = (t.to(self.device) for t in targets(self.dataset, [index]))
        size = rgb.numel() * 4 + mask.numel() * 4
        if self.used + size <= self.budget:
            self.cache[index] = (rgb, mask)
            self.used += size
        return rgb, mask


def _select(frames: Frame, j: int) -> Frame:
    return Frame(frames.expression[j:j + 1], frames.joint_rotations[j:j + 1],
                 None if frames.eyelids is None else frames.eyelids[j:j + 1])


def _cancel_check(should_cancel: CancelCheck | None) -> Callable[[], bool]:
    if should_cancel is None:
        return lambda: False
    if isinstance(should_cancel, threading.Event):
        return should_cancel.is_set
    return should_cancel


# --------------------------------------------------------------------------------------------- checkpoints
def checkpoint_dir(workdir: Path) -> Path:
    return workdir / "checkpoints"


def _checkpoints(workdir: Path) -> list[Path]:
    """The work folder's checkpoints, oldest first (the names sort by iteration)."""
    return sorted(checkpoint_dir(workdir).glob("ckpt_*.pt"))


def remove_torn(workdir: Path) -> list[str]:
    """Remove the temporary files a killed run left in the work folder and its checkpoints (a checkpoint torn
    mid-write never became ``ckpt_*.pt``); the names removed."""
    removed = remove_stale(checkpoint_dir(workdir)) + remove_stale(workdir)
    if removed:
        log.info("removed %d temporary file(s) an interrupted run left: %s", len(removed), ", ".join(removed[:5]))
    return removed


def last_checkpoint(workdir: Path) -> Path | None:
    files = _checkpoints(workdir)
    return files[-1] if files else None


def load_checkpoint(path: Path) -> dict:
    """One of our checkpoints, loaded with ``weights_only=True`` (tensors, numbers, strings, lists, dicts)."""
    state = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise OptionError(f"{path} is not a blendsplat training checkpoint", field="checkpoint")
    if state.get("version") != CHECKPOINT_VERSION:
        raise OptionError(f"{path}: version {state.get('version')} is not {CHECKPOINT_VERSION}", field="checkpoint")
    return state


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


# ------------------------------------------------------------------------------------------------- the trainer
class Trainer:
    """Trains an avatar on a portable dataset, one :meth:`step` at a time.

    Args:
        data_dir: the portable dataset (frames, masks, tracking; only the training indices are trained on).
        workdir: the work folder (checkpoints, ``log.jsonl``, the report).
        preset: ``"tiny"``, ``"paper"`` or a :class:`Preset` (its schedule is the trainer's).
        device: where training runs: ``"cpu"`` (the native rasterizer's C++ forward and backward) or ``"cuda"``
            (the whole step on the GPU: the model, frames, targets, blend, skinning, shading, gsplat's CUDA
            forward and backward, the loss, Adam and densification; checkpoints are device-neutral, so a run
            resumes on either).
        seed: initialisation and frame-sampling seed.
        iterations: total iterations (default: the preset's; also overrides a resumed checkpoint's).
        facemodel: the face model (a FaceModel or a face-model file) when the dataset's is not the open head.
        consistency: overrides the preset's ``"all" | "positions" | "none" | "frozen"`` (a fresh start only).

    The model is initialised on first use, unless :meth:`resume` loads a checkpoint first. Nothing is written to
    the work folder before the first :meth:`step` or :meth:`checkpoint`; then a fresh start removes an earlier
    training's log and checkpoints there, and a resumed one the log lines and checkpoints after its iteration.
    Not thread-safe: call :meth:`preview`, :meth:`checkpoint` and the rest between steps (a progress callback
    may)."""

    def __init__(self, data_dir: str | os.PathLike, workdir: str | os.PathLike, preset: str | Preset = "tiny", *,
                 device: str = "cpu", seed: int = 0, iterations: int | None = None,
                 facemodel: FaceModel | str | os.PathLike | None = None, consistency: str | None = None):
        self.rasterize = raster_step(device)
        self.device = device
        self.torch_device = torch_device(device)
        self._clock = stage_clock(self.torch_device)
        self.data_dir, self.workdir = Path(data_dir), Path(workdir)
        cfg = get_preset(preset)
        if consistency is not None:
            cfg = cfg.with_(consistency=consistency)
        self._iterations = None if iterations is None else int(iterations)
        self.preset = cfg if self._iterations is None else cfg.with_(iterations=self._iterations)
        self.seed = int(seed)
        self.dataset = read_dataset(data_dir)
        tracking = self.dataset.tracking
        self.facemodel = _shaped(resolve_facemodel(tracking.face_model, facemodel), tracking.shape)
        self.train_idx = np.asarray(tracking.train, dtype=np.int64)
        if len(self.train_idx) == 0:
            raise DatasetError("the dataset lists no training frames", field="train")
        test = list(tracking.test)
        self.preview_index = int(test[0] if test else self.train_idx[0])  # the frame :meth:`preview` renders
        self._targets = _Targets(self.dataset, device=self.torch_device)
        self._created = time.perf_counter()
        self.iteration = 0  # the last trained iteration
        self._model: TrainableAvatar | None = None

    # --------------------------------------------------------------------------------------------- the state
    def _setup(self, state: dict | None) -> None:
        """The training state: a fresh start (``state`` None) or a checkpoint's."""
        cfg, fm = self.preset, self.facemodel
        if state is None:
            init = init_avatar(fm, gaussians=cfg.gaussians, mouth=cfg.mouth, sh_degree=cfg.sh_degree,
                               opacity=cfg.init_opacity, seed=self.seed)
            init.provenance = {**init.provenance, "generator": "blendsplat train"}
            model = TrainableAvatar.from_facemodel(init, fm, cfg.consistency)
            self.cylinder = losses.MouthCylinder.from_points(init.mouth.means)
            gen = torch.Generator().manual_seed(self.seed)
            x = init.neutral.means
            extent = float((x - x.mean(0)).norm(dim=1).max())
            start, prior = 0, 0.0
        else:
            model = TrainableAvatar.from_state(state["model"])
            self.cylinder = losses.MouthCylinder.from_dict(state["cylinder"])
            gen = torch.Generator()
            gen.set_state(state["rng"])
            extent = float(state["densifier"]["extent"])
            start, prior = int(state["iteration"]), float(state["seconds"])
        dev = self.torch_device
        model = model.to(dev)
        self.cylinder = replace(self.cylinder, centre=self.cylinder.centre.to(dev))
        opt = make_optimizer(model, cfg)
        grid = lookup_grid(fm, cfg.grid_resolution) if cfg.densify and cfg.grid_resolution else None
        strategy = DensifyStrategy.from_preset(cfg, model.num_gaussians, extent, grid, device=dev)
        if state is not None:
            opt.load_state_dict(state["optimizer"])
            strategy.load_state(state["densifier"])
        view = model.avatar(detach=True, deltas=False)
        tracking = self.dataset.tracking
        check_compatible(view, tracking)
        frames, cams = frame_inputs(view, tracking, self.train_idx)
        self._frames, self._cams = frames.to(device=dev), cams.to(device=dev)
        frames, cams = frame_inputs(view, tracking, [self.preview_index])
        self._preview_inputs = frames.to(device=dev), cams.to(device=dev)
        self._model, self._optimizer, self._generator, self._strategy = model, opt, gen, strategy
        self.iteration = self._start = self._saved = start
        self._resumed = state is not None
        self._prior_seconds, self._seconds, self._steps = prior, 0.0, 0
        self._times: dict[str, float] = defaultdict(float)
        self._history: list[dict] = []  # the log records written since this state began
        self._densified: list[dict] = []
        self._pruner = ContributionPruner.from_preset(cfg)
        self._poses = (FramePoses(len(self.train_idx), device=dev,
                                  expressions=self._frames.expression.shape[1] if cfg.refine_expressions else 0)
                       if cfg.refine_poses or cfg.refine_expressions else None)
        if self._poses is not None and state is not None and "poses" in state:
            self._poses.load_state(state["poses"])
        self._pruned: list[dict] = [dict(p) for p in state.get("pruned", [])] if state is not None else []
        self._pending: dict | None = None  # the last step's record when the log has not had it
        self._disk_ready = False
        self._grid_start = (grid.built, grid.build_seconds) if grid is not None else (0, 0.0)  # grids are shared

    def _ensure(self) -> None:
        if self._model is None:
            self._setup(None)

    def _prepare_disk(self) -> None:
        """Before the first write: a fresh start clears the work folder's log and checkpoints, a resumed one
        drops what came after its iteration."""
        if self._disk_ready:
            return
        checkpoint_dir(self.workdir).mkdir(parents=True, exist_ok=True)
        remove_torn(self.workdir)
        logfile = self.workdir / "log.jsonl"
        if self._resumed:
            _truncate_log(logfile, self._start)
        else:
            logfile.write_text("")
        for old in _checkpoints(self.workdir):  # an earlier training's, or later than the resumed one
            if not self._resumed or int(old.stem.split("_")[1]) > self._start:
                old.unlink()
        self._disk_ready = True

    @property
    def model(self) -> TrainableAvatar:
        self._ensure()
        return self._model

    @property
    def optimizer(self) -> torch.optim.Optimizer:
        self._ensure()
        return self._optimizer

    @property
    def generator(self) -> torch.Generator:
        """The frame-sampling generator (densification's splits draw from it too)."""
        self._ensure()
        return self._generator

    @property
    def strategy(self) -> DensifyStrategy:
        self._ensure()
        return self._strategy

    @property
    def total(self) -> int:
        """The last iteration."""
        return self.preset.iterations

    @property
    def elapsed(self) -> float:
        """Training seconds so far (steps and checkpoints; the runs before a resume included)."""
        return self._prior_seconds + self._seconds

    def resume(self, checkpoint: str | os.PathLike | None = None) -> bool:
        """Continue from ``checkpoint`` (default: the work folder's last one): its model, optimizer, generator,
        densification statistics, iteration, preset and seed (``iterations``, when given, still overrides the
        total). False, with a warning, when there is none (the trainer then starts fresh)."""
        path = Path(checkpoint) if checkpoint is not None else last_checkpoint(self.workdir)
        if path is None:
            log.warning("no checkpoint in %s: starting from scratch", checkpoint_dir(self.workdir))
            return False
        remove_torn(self.workdir)  # a checkpoint torn when the previous run was killed
        state = load_checkpoint(path)
        cfg = Preset(**state["preset"])
        self.preset = cfg if self._iterations is None else cfg.with_(iterations=self._iterations)
        self.seed = int(state["seed"])
        self._setup(state)
        log.info("resumed from %s (iteration %d)", path, self.iteration)
        return True

    def checkpoint(self) -> Path:
        """Save the whole state as ``<workdir>/checkpoints/ckpt_<iteration>.pt`` (atomically; the last
        ``CHECKPOINTS_KEPT`` are kept) and log the last step's record if the log has not had it."""
        self._ensure()
        self._prepare_disk()
        self._write_log()
        t0 = time.perf_counter()
        path = checkpoint_dir(self.workdir) / f"ckpt_{self.iteration:07d}.pt"
        state = {
            "format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "iteration": self.iteration,
            "model": self._model.state(), "optimizer": self._optimizer.state_dict(),
            "rng": self._generator.get_state(), "preset": self.preset.to_dict(), "cylinder": self.cylinder.to_dict(),
            "seed": self.seed, "seconds": self.elapsed, "densifier": self._strategy.state(),
            "pruned": [dict(p) for p in self._pruned],
        }
        if self._poses is not None:
            state["poses"] = self._poses.state()
        with atomic_path(path) as tmp:
            torch.save(state, tmp)
        for old in _checkpoints(self.workdir)[:-CHECKPOINTS_KEPT]:
            old.unlink(missing_ok=True)
        self._saved = self.iteration
        self._seconds += time.perf_counter() - t0
        return path

    # ------------------------------------------------------------------------------------------------ training
    def step(self) -> Progress:
        """Train one iteration and return its :class:`Progress` (without a preview); its log record is written on
        the log schedule or by the next :meth:`checkpoint`. Checkpoints are :meth:`run`'s (or the caller's) to
        take. RuntimeError when the last iteration is trained."""
        self._ensure()
        if self.iteration >= self.total:
            raise RuntimeError(f"the training is complete ({self.total} iterations)")
        self._prepare_disk()
        cfg, model, opt, gen, times = self.preset, self._model, self._optimizer, self._generator, self._times
        clock = self._clock
        t0 = clock()
        it = self.iteration + 1
        j = int(torch.randint(len(self.train_idx), (1,), generator=gen))
        frame, cams = _select(self._frames, j), self._cams.index(j)
        index = int(self.train_idx[j])
        rgb_t, mask_t = self._targets(index)
        degree = active_sh_degree(cfg, it)
        for g in opt.param_groups:
            if g["name"] in ("means", "mouth_means"):
                g["lr"] = xyz_lr(cfg, it)
        times["data"] += clock() - t0
        poses = self._poses if self._poses is not None and it > cfg.refine_poses_from else None
        motion = poses.motion(j) if poses is not None else None
        if poses is not None and poses.expressions:
            frame = Frame(poses.expression(frame.expression), frame.joint_rotations, frame.eyelids)
        rgb, alpha, posed = forward(model, frame, cams, degree, rasterize=self.rasterize, threads=cfg.threads,
                                    times=times, clock=clock, motion=motion)
        self._strategy.step_pre_backward(it, posed)
        t1 = clock()
        loss, terms = losses.total_loss(rgb, alpha, rgb_t, mask_t, model.mouth_means, self.cylinder)
        if poses is not None:
            loss = loss + poses.prior()
        t2 = clock()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        t3 = clock()
        opt.step()
        if poses is not None:
            poses.step(refine_lr(cfg, it, self.total))
        t4 = clock()
        times["loss"] += t2 - t1
        times["backward"] += t3 - t2
        times["optimizer"] += t4 - t3
        densified = self._strategy.step_post_backward(it, model, opt, gen, cams)
        if densified is not None:
            self._densified.append({"iteration": it, **densified})
        t5 = clock()
        times["densify"] += t5 - t4
        pruned = None
        if self._pruner.due(it):
            motions = None if poses is None else poses.wu  # the frames as training sees them
            pruned = {"iteration": it, **self._pruner.prune(model, opt, self._strategy, self._frames, self._cams,
                                                            self.rasterize, motions=motions, threads=cfg.threads)}
            self._pruned.append(pruned)
            log.info("iteration %d: pruned by contribution %s", it, pruned)
            times["prune"] += clock() - t5
        self.iteration = it
        self._steps += 1
        scalars = torch.stack([loss.detach().float(), *(v.detach().float() for v in terms.values())]).tolist()
        values = dict(zip(("loss", *terms), scalars, strict=True))  # one read from the device for the five
        step_psnr = psnr(rgb, rgb_t)
        self._seconds += clock() - t0
        self._pending = {"iteration": it, **values, "psnr": step_psnr, "frame": index, "sh_degree": degree,
                         "gaussians": model.num_gaussians, "seconds": round(self.elapsed, 3)}
        if pruned is not None:
            self._pending["pruned"] = {k: v for k, v in pruned.items() if k != "iteration"}
        if it % cfg.log_every == 0 or it == 1 or it == self.total or pruned is not None:
            self._write_log()
        return Progress(iteration=it, total=self.total, losses=values, psnr=step_psnr, gaussians=model.num_gaussians,
                        elapsed=self.elapsed, eta=(self.total - it) * self._seconds / self._steps, frame=index,
                        sh_degree=degree, densified=densified, pruned=pruned)

    def _write_log(self) -> None:
        if self._pending is None:
            return
        with open(self.workdir / "log.jsonl", "a") as f:
            f.write(json.dumps(self._pending) + "\n")
        self._history.append(self._pending)
        self._pending = None

    def run(self, until: int | None = None, on_progress: Callable[[Progress], None] | None = None,
            should_cancel: CancelCheck | None = None, preview_every: int = 0) -> Outcome:
        """Step to ``until`` (default: the last iteration), checking ``should_cancel`` (a callable or a
        threading.Event) before each step; checkpoint every ``checkpoint_every`` iterations and when the run
        ends, whatever ends it (a failing step leaves the last checkpoint). ``on_progress`` receives every
        step's :class:`Progress`, with a :meth:`preview` every ``preview_every`` iterations (0: never)."""
        self._ensure()
        end = self.total if until is None else min(self.total, int(until))
        cancelled = _cancel_check(should_cancel)
        outcome = None
        while self.iteration < end:
            if cancelled():
                outcome = Outcome.CANCELLED
                log.info("cancelled after iteration %d", self.iteration)
                break
            event = self.step()
            if preview_every and event.iteration % preview_every == 0:
                event = replace(event, preview=self.preview())
            if event.iteration % self.preset.checkpoint_every == 0:
                self.checkpoint()
            if on_progress is not None:
                on_progress(event)
        if self.iteration != self._saved:
            self.checkpoint()
        if outcome is None:
            outcome = Outcome.FINISHED if self.iteration >= self.total else Outcome.STOPPED
        return outcome

    def preview(self) -> np.ndarray:
        """The model now, rendered at dataset frame ``preview_index`` (the first held-out frame, else the first
        training frame; full SH degree, no gradient, the state untouched): [H, W, 3] uint8."""
        from ..media.pixels import to_uint8

        self._ensure()
        frame, cams = self._preview_inputs
        with torch.no_grad():
            rgb, _, _ = forward(self._model, frame, cams, None, rasterize=self.rasterize, threads=self.preset.threads)
        return to_uint8(rgb[0])

    def preview_truth(self) -> np.ndarray:
        """The dataset's own image of the frame :meth:`preview` renders, the background masked to black as the
        losses see it: [H, W, 3] uint8 (what a viewer shows beside the preview)."""
        from ..media.pixels import to_uint8

        rgb, _ = targets(self.dataset, [self.preview_index])
        return to_uint8(rgb[0])

    # ---------------------------------------------------------------------------------------------- the result
    def summary(self) -> dict:
        """What this trainer did since it started or resumed (JSON-ready)."""
        self._ensure()
        model, done, tracking = self._model, self._steps, self.dataset.tracking
        grid = self._strategy.grid
        return {
            "workdir": str(self.workdir), "preset": self.preset.name, "consistency": model.consistency,
            "seed": self.seed, "iterations": self.iteration, "iterations_this_run": done,
            "refine": {"poses": self.preset.refine_poses or self.preset.refine_expressions,
                       "expressions": self.preset.refine_expressions},
            "resumed_from": self._start if self._start else None, "gaussians": model.num_gaussians,
            "mouth": int(model.mouth_means.shape[0]), "expressions": len(model.meta["expression_names"]),
            "size": [int(tracking.width), int(tracking.height)], "train_frames": len(self.train_idx),
            "device": self.device, "optimizer": optimizer_kind(self._optimizer), "eps": model.eps,
            "d_max": model.d_max, "seconds": round(self.elapsed, 3),
            "ms_per_iteration": round(1e3 * self._seconds / done, 2) if done else None,
            "stage_ms": {s: round(1e3 * self._times[s] / done, 2) for s in STAGES} if done else {},
            "first": self._history[0] if self._history else None,
            "last": self._history[-1] if self._history else None,
            "densified": list(self._densified),
            "pruned": list(self._pruned),
            "poses": None if self._poses is None else self._poses.summary(),
            "grid": None if grid is None else {"resolution": grid.resolution,
                                               "bricks_built": grid.built - self._grid_start[0],
                                               "build_seconds": round(grid.build_seconds - self._grid_start[1], 3)},
        }

    def dataset_provenance(self) -> dict:
        """What a trained bundle records of its dataset: the folder's name, frames, size, split, face model and a
        digest of its files (:func:`dataset_digest`)."""
        tr = self.dataset.tracking
        return {"name": self.data_dir.name, "frames": int(tr.frames), "width": int(tr.width),
                "height": int(tr.height), "train": len(self.train_idx), "test": len(tr.test),
                "face_model": tr.face_model, "digest": dataset_digest(self.data_dir)}

    def final_psnr(self) -> dict:
        """PSNR (full frame, masked target) of the model on up to ``final_eval_frames`` training frames, rendered
        at the full SH degree (the exported avatar's) with the training rasterizer, with the frames' pose and
        expression corrections when training learnt them."""
        self._ensure()
        count = min(self.preset.final_eval_frames, len(self.train_idx))
        picks = np.unique(np.linspace(0, len(self.train_idx) - 1, count).round().astype(np.int64))
        out = {"frames": [], "psnr": []}
        with torch.no_grad():
            for j in picks.tolist():
                frame, motion = _select(self._frames, j), None
                if self._poses is not None:  # as training sees the frame
                    frame, motion = self._poses.applied(j, frame)
                rgb, _, _ = forward(self._model, frame, self._cams.index(j), None, rasterize=self.rasterize,
                                    threads=self.preset.threads, motion=motion)
                want, _ = self._targets(int(self.train_idx[j]))
                out["frames"].append(int(self.train_idx[j]))
                out["psnr"].append(round(psnr(rgb, want), 4))
        out["psnr_mean"] = round(float(np.mean(out["psnr"])), 4) if out["psnr"] else None
        return out

    def finish(self, out_bundle: str | os.PathLike) -> dict:
        """Export the avatar to ``out_bundle`` (fp16 blendshape storage), evaluate it (``final``: PSNR on training
        frames; the held-out report and contact sheet when the dataset has test frames; the loss curves) and
        write ``summary.json``; returns the summary."""
        from ..evaluation.report import relative_paths

        out_bundle = Path(out_bundle)
        self._prepare_disk()
        summary = self.summary()
        cfg, model = self.preset, self._model
        trained = {"iterations": self.iteration, "preset": cfg.name, "seed": self.seed,
                   "consistency": model.consistency, "dataset": self.dataset_provenance()}
        avatar = model.to_avatar(provenance={"trained": trained})
        out_bundle.parent.mkdir(parents=True, exist_ok=True)
        manifest = write_bundle(avatar, out_bundle, precision="fp16")
        summary["bundle"] = str(out_bundle)
        summary["final"] = self.final_psnr()
        summary.update(_report(out_bundle, self.data_dir, self.workdir, len(self.dataset.tracking.test)))
        if "eval" in summary:  # the held-out figures join the bundle's provenance (same tensors, same created_at)
            e = summary["eval"]
            held_out = {"split": "test", "frames": e["frames"],
                        **{k: None if e[k] is None else round(float(e[k]), 4) for k in ("psnr_head", "psnr", "ssim")}}
            avatar.provenance = {**manifest["provenance"], "trained": {**trained, "held_out": held_out}}
            write_bundle(avatar, out_bundle, precision="fp16")
        summary["seconds_total"] = round(time.perf_counter() - self._created, 3)
        # the file names files relative to the workdir (or by name): it is served to API clients (a job's summary)
        with atomic_path(self.workdir / "summary.json") as tmp:
            tmp.write_text(json.dumps(relative_paths(summary, self.workdir), indent=2))
        return summary


def dataset_digest(root: str | os.PathLike) -> str:
    """``"sha256:<hex>"`` over a dataset folder's regular files in sorted relative-path order (each: the UTF-8 path,
    its byte length and its bytes), so the same files give the same digest wherever the folder is."""
    import hashlib

    root = Path(root)
    h = hashlib.sha256(b"blendsplat-dataset-digest-v1\n")
    for path in sorted((p for p in root.rglob("*") if p.is_file() and not p.is_symlink()),
                       key=lambda p: p.relative_to(root).as_posix()):
        rel = path.relative_to(root).as_posix().encode()
        h.update(len(rel).to_bytes(8, "little") + rel + path.stat().st_size.to_bytes(8, "little"))
        with open(path, "rb") as f:
            while chunk := f.read(1 << 20):
                h.update(chunk)
    return f"sha256:{h.hexdigest()}"


def _report(bundle: Path, data_dir: Path, workdir: Path, held_out: int) -> dict:
    """Held-out evaluation (report JSON and contact sheet) and the loss curves, in the workdir."""
    from ..evaluation.plot import training_plots
    from ..evaluation.report import evaluate

    out = {"plots": training_plots(workdir / "log.jsonl", workdir / "curves.png", keys=("loss", "psnr"))}
    if held_out:
        e = evaluate(bundle, data_dir, split="test", report=workdir / "report.json",
                     contact_sheet=workdir / "contact_sheet.png")
        out["eval"] = {k: e[k] for k in ("psnr", "ssim", "psnr_head", "frames", "report", "contact_sheet")}
    return out


# ------------------------------------------------------------------------------------------------- the command
def train(
    data_dir: str | os.PathLike,
    out_bundle: str | os.PathLike,
    workdir: str | os.PathLike | None = None,
    preset: str | Preset = "tiny",
    device: str = "cpu",
    resume: bool = False,
    seed: int = 0,
    iterations: int | None = None,
    *,
    facemodel: FaceModel | str | os.PathLike | None = None,
    consistency: str | None = None,
    stop_after: int | None = None,
    on_progress: Callable[[Progress], None] | None = None,
    should_cancel: CancelCheck | None = None,
) -> dict:
    """Train an avatar on a portable dataset and write it to ``out_bundle``: a :class:`Trainer` run to the end,
    then :meth:`Trainer.finish`.

    ``workdir`` defaults to ``<out_bundle stem>.train`` beside the bundle; ``resume`` continues from its last
    checkpoint (whose preset and seed win); ``stop_after`` stops after that iteration with a checkpoint and no
    bundle (an interruption, for tests), as a cancel through ``should_cancel`` does; ``on_progress`` receives
    every step's :class:`Progress`. The other arguments are the :class:`Trainer`'s.

    Returns:
        The summary (:meth:`Trainer.finish`: iterations, seconds, stage_ms, the first and last log records, the
        final per-frame PSNR on training frames, bundle, workdir, ...); for a run that stopped early
        :meth:`Trainer.summary` with ``bundle`` None, ``stopped`` and ``cancelled``.
    """
    out_bundle = Path(out_bundle)
    workdir = Path(workdir) if workdir is not None else out_bundle.with_name(out_bundle.stem + ".train")
    trainer = Trainer(data_dir, workdir, preset, device=device, seed=seed, iterations=iterations,
                      facemodel=facemodel, consistency=consistency)
    if resume:
        trainer.resume()
    outcome = trainer.run(until=stop_after, on_progress=on_progress, should_cancel=should_cancel)
    if outcome is not Outcome.FINISHED:
        return {**trainer.summary(), "bundle": None, "stopped": True, "cancelled": outcome is Outcome.CANCELLED}
    return trainer.finish(out_bundle)
