"""``blendsplat bench bundles``: the render speed of trained avatars side by side, on a dataset's own frames.

What pruning (or any change to an avatar) buys is a ratio: the same frames rendered by two or more bundles of one
dataset (a pruned one against the unpruned, say). ``bench render`` times one avatar on random expressions; this
renders the dataset's ``split`` frames (their expressions, poses and cameras; the camera scaled to ``size`` pixels
wide) with each bundle in turn, ``block`` frames at a time, for ``rounds`` rounds, so that the bundles share the
machine's state (a shared, noisy machine slows them alike) and the ratio carries. Each call renders ``streams``
consecutive frames batched, to 8-bit RGBA (the stream path) on the native backend by default. Times are the median
over the rounds of a block's mean milliseconds a call; ``speedup`` is the first bundle's time over each one's.
"""

from __future__ import annotations

import logging
import statistics
import time
from pathlib import Path

import torch

from ..avatar import Avatar
from ..camera import Cameras
from ..deform import Frame
from ..errors import DatasetError, OptionError
from .bench import machine

log = logging.getLogger(__name__)

STAGES = ("blend", "lbs", "raster", "bin")


def _scaled(cams: Cameras, size: int) -> Cameras:
    """The cameras with their intrinsics scaled to ``size`` pixels wide (the height in proportion)."""
    s = size / cams.width
    K = cams.K.clone()
    K[:, :2] *= s
    return Cameras(K, cams.R, cams.t, size, max(1, round(cams.height * s)))


def bench_bundles(bundles: list[str | Path | Avatar], data_dir: str | Path, *, size: int = 512, streams: int = 1,
                  rounds: int = 12, block: int = 20, warmup: int = 5, split: str = "test",
                  backend: str | None = None, threads: int = 0) -> dict:
    """Time each of ``bundles`` (paths or avatars; at least one, the first the reference) on the frames of
    ``split`` of the dataset at ``data_dir``; returns the JSON report. Raises OptionError for a bad count,
    DatasetError when a bundle does not animate the dataset (other expressions or joints) or the split has fewer
    frames than ``streams``."""
    from ..bundle import read_bundle
    from ..data.frames import check_compatible, frame_inputs
    from ..data.portable import read_dataset
    from ..evaluation.report import split_indices
    from ..renderer import AvatarRenderer

    if not bundles:
        raise OptionError("give at least one bundle", field="bundles")
    for name, value, least in (("size", size, 1), ("streams", streams, 1), ("rounds", rounds, 1),
                               ("block", block, 1), ("warmup", warmup, 0), ("threads", threads, 0)):
        if value < least:
            raise OptionError(f"must be at least {least}, got {value}", field=name)
    ds = read_dataset(data_dir)
    indices = split_indices(ds, split)
    if len(indices) < streams:
        raise DatasetError(f"the dataset {data_dir} has {len(indices)} {split} frames; {streams} stream(s) need as "
                           f"many", field=split)
    entries = []
    for i, b in enumerate(bundles):
        avatar = b if isinstance(b, Avatar) else read_bundle(b)
        try:
            check_compatible(avatar, ds.tracking)
        except DatasetError as e:
            what = f"avatar {i + 1}" if isinstance(b, Avatar) else str(b)
            raise DatasetError(f"{what} cannot render {data_dir}: {e.detail}", field=e.field) from None
        frames, cams = frame_inputs(avatar, ds.tracking, indices)
        entries.append({"name": None if isinstance(b, Avatar) else str(b), "avatar": avatar,
                        "renderer": AvatarRenderer(avatar, backend, threads=threads), "frames": frames,
                        "cams": _scaled(cams, size), "ms": [], "stages": []})
    starts = len(indices) - streams + 1  # where a call's run of consecutive frames may start

    def call(e: dict, j: int) -> float:
        j %= starts
        f = e["frames"]
        frame = Frame(f.expression[j:j + streams], f.joint_rotations[j:j + streams],
                      None if f.eyelids is None else f.eyelids[j:j + streams])
        cams = e["cams"].index(slice(j, j + streams))
        t0 = time.perf_counter()
        _, timings = e["renderer"].render_rgba8(frame, cams)
        ms = (time.perf_counter() - t0) * 1e3
        e["stages"].append(timings or {})
        return ms

    log.info("%d bundle(s), %d %s frames at %d px, %d stream(s) a call: %d round(s) of %d call(s) each",
             len(entries), len(indices), split, size, streams, rounds, block)
    for e in entries:
        for j in range(warmup):
            call(e, j)
        e["stages"].clear()
    for r in range(rounds):
        for e in entries:
            e["ms"].append(statistics.mean(call(e, r * block + j) for j in range(block)))
    reference = statistics.median(entries[0]["ms"])
    out = []
    for e in entries:
        ms = statistics.median(e["ms"])
        stages = {k: round(statistics.median(float(t[k]) for t in e["stages"]), 3)
                  for k in STAGES if all(k in t for t in e["stages"])}
        out.append({"bundle": e["name"], "gaussians": e["avatar"].num_gaussians, "mouth": e["avatar"].num_mouth,
                    "ms": round(ms, 3), "ms_per_frame": round(ms / streams, 3), "stages_ms": stages,
                    "speedup": round(reference / ms, 3), "rounds_ms": [round(x, 3) for x in e["ms"]],
                    "backend": e["renderer"].backend})
    return {"benchmark": "bundles", "data": str(data_dir), "split": split, "frames": int(len(indices)),
            "size": size, "height": entries[0]["cams"].height, "streams": streams, "rounds": rounds,
            "block": block, "warmup": warmup, "output": "rgba8", "bundles": out,
            "threads": threads or torch.get_num_threads(),
            "machine": machine()}
