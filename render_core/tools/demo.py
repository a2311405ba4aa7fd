"""The demo animation: a synthetic avatar turns its head, talks, blinks and pulls expressions."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

from ..bundle import write_bundle
from .offline import render_bundle
from .synth import synth_avatar


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
