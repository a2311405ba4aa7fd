"""Offline rendering: a bundle and a driving file in, one image per line (PNG or EXR) or one H.264 video out."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import torch

from ..avatar import Avatar
from ..bundle import read_bundle
from ..drive import read_drive_file
from ..errors import OptionError
from ..media.files import FORMATS, VideoWriter, write_image
from ..renderer import AvatarRenderer


def render_drive(
    avatar: Avatar,
    drive_path: str | Path,
    out_dir: str | Path,
    *,
    size: int = 512,
    fmt: str = "png",
    backend: str | None = None,
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
    fps: int = 30,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Render every line of ``drive_path`` for ``avatar`` into ``out_dir``; returns a summary (files, frames).

    The whole driving file is validated before the first frame renders, so a bad line costs nothing.
    ``progress(done, total)`` is called after each frame (the command line draws its bar with it).
    """
    if fmt not in FORMATS:
        raise OptionError(f"unknown format {fmt!r}; use one of {', '.join(FORMATS)}", field="format")
    frames = read_drive_file(drive_path, avatar, size, size)
    renderer = AvatarRenderer(avatar, backend)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    bg = torch.tensor(background, dtype=torch.float32)
    files: list[str] = []
    video = VideoWriter(out / "render.mp4", size, size, fps=fps) if fmt == "mp4" else None
    try:
        for i, df in enumerate(frames):
            result = renderer.render(df.frame, df.camera, background=bg)
            if video is not None:
                video.write(result.rgb[0])
            else:
                path = out / f"frame_{i:05d}.{fmt}"
                rgb, alpha = result.rgb[0], result.alpha[0]  # PNG: the colour over the background; EXR: RGBA
                write_image(path, torch.cat([rgb, alpha[..., None]], -1) if fmt == "exr" else rgb)
                files.append(str(path))
            if progress is not None:
                progress(i + 1, len(frames))
    finally:
        if video is not None:
            video.close()
            files.append(str(out / "render.mp4"))
    return {"frames": len(frames), "out": str(out), "format": fmt, "size": size, "backend": renderer.backend,
            "files": files}


def render_bundle(bundle_path: str | Path, drive_path: str | Path, out_dir: str | Path, **kwargs) -> dict:
    """:func:`render_drive` for a bundle file (validated on load)."""
    avatar = read_bundle(bundle_path)
    return {"bundle": str(bundle_path), **render_drive(avatar, drive_path, out_dir, **kwargs)}
