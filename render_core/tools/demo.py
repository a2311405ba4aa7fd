"""The demo: the animation (a synthetic avatar turns its head, talks, blinks and pulls expressions) and the builder
of the trained demo avatar the package ships (:func:`build_demo_avatar`)."""

from __future__ import annotations

import json
import logging
import math
import os
import tempfile
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

from ..bundle import read_bundle_and_manifest, read_manifest, write_bundle
from ..errors import BlendsplatError, OptionError
from .offline import render_bundle
from .synth import synth_avatar

log = logging.getLogger(__name__)


def demo_drive_lines(frames: int, expression_names: list[str]) -> list[dict]:
    """A looping performance: the camera sways, the jaw talks, eyes blink and expressions cycle."""
    lines = []
    for i in range(frames):
        t = i / max(frames, 1)
        k = len(expression_names)
        expression = {}
        if k:
            a, b = (i // 15) % k, (i // 15 + 1) % k
            w = (i % 15) / 15
            expression = {expression_names[a]: round(1.0 - w, 4), expression_names[b]: round(w, 4)}
        blink = 1.0 if (i % 40) in (20, 21, 22) else 0.0
        lines.append({
            "expression": expression,
            "joints": {
                "jaw": [round(0.12 * max(0.0, math.sin(2 * math.pi * 3 * t)), 4), 0.0, 0.0],
                "neck": [round(0.08 * math.sin(2 * math.pi * t), 4), round(0.25 * math.sin(2 * math.pi * t), 4),
                         0.0],
            },
            "eyelids": [blink, blink],
            "camera": {"yaw": round(20 * math.sin(2 * math.pi * t), 3), "pitch": 5.0},
        })
    return lines


def run_demo(out_dir: str | Path, *, size: int = 256, frames: int = 60, gaussians: int = 10_000,
             progress: Callable[[int, int], None] | None = None) -> dict:
    """Write a synthetic bundle, a driving file and the rendered H.264 video into ``out_dir``; ``progress(done,
    total)`` after each rendered frame."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    avatar = synth_avatar(gaussians, 8, seed=7)
    bundle = out / "demo.bundle"
    write_bundle(avatar, bundle)
    drive = out / "demo.jsonl"
    drive.write_text("".join(json.dumps(line) + "\n" for line in demo_drive_lines(frames,
                                                                                  avatar.expression_names)))
    summary = render_bundle(bundle, drive, out, size=size, fmt="mp4", background=(0.08, 0.09, 0.12),
                            progress=progress)
    return {"video": summary["files"][0], "bundle": str(bundle), "drive": str(drive), "frames": frames,
            "size": size}


# The shipped demo avatar's recipe (render_core/facemodel/demo-avatar.bsplat): `blendsplat bundle build-demo`'s
# defaults. The same as `blendsplat data synth --frames 300 --size 256 --seed 7` then `blendsplat train DS --preset
# tiny --iterations 3000 --gaussians 12000 --seed 0`: 12k initial face Gaussians (densified up to 18k) keep the
# fp16 schema-2 file under MAX_DEMO_BYTES (the tiny preset's 20k, densified to 30k, would be about 23 MB).
DEMO_RECIPE = {"frames": 300, "size": 256, "data_seed": 7, "preset": "tiny", "iterations": 3000, "gaussians": 12_000,
               "seed": 0, "threads": 2}
MAX_DEMO_BYTES = 16 << 20
MIN_DEMO_PSNR_HEAD = 30.0


def build_demo_avatar(out: str | os.PathLike, *, frames: int = 300, size: int = 256, data_seed: int = 7,
                      preset: str = "tiny", iterations: int = 3000, gaussians: int = 12_000, seed: int = 0,
                      threads: int = 2, workdir: str | os.PathLike | None = None,
                      max_bytes: int = MAX_DEMO_BYTES, min_psnr_head: float = MIN_DEMO_PSNR_HEAD,
                      progress: Callable[[int, int], None] | None = None) -> dict:
    """Build the demo avatar with our own pipeline and write it to ``out``: the open head's synthetic video
    (:func:`render_core.data.generate.synth_dataset`: ``frames`` frames of ``size`` x ``size``, ``data_seed``), a
    training run on it (``preset`` scaled to ``gaussians`` initial face Gaussians, ``iterations``, ``seed``), the
    result as a schema-2 fp16 bundle whose provenance records the dataset, the training and its held-out
    figures, and this recipe.

    Reproducible as far as a CPU allows: every seed is fixed and torch runs with ``threads`` intra-op threads (the
    native rasterizer with as many; its backward sums per-pair slots in a fixed order, so its result does not
    depend on the thread schedule). The same machine and thread count give the same bundle; another CPU (its
    SIMD kernels, BLAS) or thread count may change the last bits of the values, never the recipe.
    Rebuilding does not churn the file: when the new content equals the file already at ``out`` (its creation
    time aside), the file is left as it is (``unchanged``). Refused (nothing written): a held-out psnr_head below
    ``min_psnr_head`` or a file over ``max_bytes``. ``workdir`` keeps the dataset and the training's work folder
    (default: a temporary folder, removed). ``progress(done, total)`` after each training iteration.

    Returns a summary: path, bytes, gaussians, mouth, expressions, precision, schema_version, psnr_head, psnr,
    ssim, iterations, training_seconds, seconds, digest, unchanged."""
    import torch

    from ..data.generate import synth_dataset
    from ..train import Trainer, get_preset

    out = Path(out)
    if threads < 1:
        raise OptionError(f"must be at least 1, got {threads}", field="threads")
    recipe = {"command": "blendsplat bundle build-demo", "frames": frames, "size": size, "data_seed": data_seed,
              "preset": preset, "iterations": iterations, "gaussians": gaussians, "seed": seed, "threads": threads}
    cfg = get_preset(preset).with_gaussians(gaussians).with_(threads=threads)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="blendsplat-demo-") as tmp:
        work = Path(workdir) if workdir is not None else Path(tmp)
        data = work / f"synthetic-open-head-{frames}x{size}-seed{data_seed}"
        saved = torch.get_num_threads()
        torch.set_num_threads(threads)
        torch.manual_seed(seed)
        try:
            log.info("demo avatar: the synthetic video (%d frames of %dx%d, seed %d) -> %s", frames, size, size,
                     data_seed, data)
            synth = synth_dataset(data, frames=frames, size=size, seed=data_seed)
            trainer = Trainer(data, work / "train", cfg, seed=seed, iterations=iterations)
            log.info("demo avatar: training (%s, %d iterations, %d initial face Gaussians, %d threads)", preset,
                     iterations, gaussians, threads)
            trainer.run(on_progress=None if progress is None else lambda e: progress(e.iteration, e.total))
            summary = trainer.finish(work / "trained.bundle")
        finally:
            torch.set_num_threads(saved)
        avatar, manifest = read_bundle_and_manifest(work / "trained.bundle")
        trained = manifest["provenance"]["trained"]
        held_out = trained.get("held_out") or {}
        psnr_head = held_out.get("psnr_head")
        if psnr_head is None or psnr_head < min_psnr_head:
            raise BlendsplatError(f"the trained avatar's held-out psnr_head is {psnr_head} dB, below {min_psnr_head}: "
                                  "not written (more --iterations or --gaussians)", field="psnr_head")
        trained["dataset"]["synthetic"] = {"generator": "blendsplat data synth", "frames": frames, "size": size,
                                           "seed": data_seed, "face_model": synth["face_model"]}
        provenance = {**manifest["provenance"], "trained": trained, "recipe": recipe}
        written, unchanged = _publish(avatar, provenance, out, max_bytes)
    return {"path": str(out), "bytes": out.stat().st_size, "gaussians": written["counts"]["gaussians"],
            "mouth": written["counts"]["mouth"], "expressions": written["counts"]["blendshapes"],
            "precision": written["precision"], "schema_version": written["schema_version"],
            "psnr_head": psnr_head, "psnr": held_out.get("psnr"), "ssim": held_out.get("ssim"),
            "held_out_frames": held_out.get("frames"), "iterations": trained["iterations"],
            "training_seconds": summary["seconds"], "seconds": round(time.perf_counter() - t0, 1),
            "digest": written["digest"], "unchanged": unchanged}


def _publish(avatar, provenance: dict, out: Path, max_bytes: int) -> tuple[dict, bool]:
    """Write ``avatar`` with ``provenance`` to ``out`` (schema 2, fp16) unless the file there already holds the
    same content: its creation time is reused for the comparison, so an identical rebuild leaves the file alone.
    The manifest written (or kept) and whether the file was left unchanged."""
    old = None
    if out.is_file():
        try:
            old = read_manifest(out)
        except (BlendsplatError, OSError):
            old = None
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".demo-", dir=out.parent) as tmp:
        candidate = Path(tmp) / out.name
        created = (old or {}).get("provenance", {}).get("created_at")
        avatar.provenance = {**provenance, "created_at": created or datetime.now(UTC).isoformat(timespec="seconds")}
        manifest = write_bundle(avatar, candidate, precision="fp16", schema_version=2)
        if old is not None and manifest["digest"] == old.get("digest"):
            return old, True
        if created:  # new content: a new creation time
            avatar.provenance["created_at"] = datetime.now(UTC).isoformat(timespec="seconds")
            manifest = write_bundle(avatar, candidate, precision="fp16", schema_version=2)
        size = candidate.stat().st_size
        if size > max_bytes:
            raise OptionError(f"the demo avatar would be {size} bytes, over {max_bytes}: fewer --gaussians",
                              field="gaussians")
        os.replace(candidate, out)
    return manifest, False
