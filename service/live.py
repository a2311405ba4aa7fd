"""``blendsplat live``: play a driving file to an avatar over WebRTC and keep what comes back.

The driving file (docs/method.md section 11: JSON lines of ``expression``, ``joints``, ``eyelids``, ``camera``) is
read and turned into the data channel's frame messages (:func:`frame_message`: the same protobuf JSON a WebSocket
client sends), sent at ``fps`` through a :class:`~service.webrtc.client.WhepClient`; the decoded video frames are
written to an MP4 (H.264) when ``out`` is given, and the report gives the frames sent and received, pose-to-frame
latency (frames matched to their pose by RTP timestamp, :func:`~service.webrtc.client.match_indices`) and the
server's per-frame timings. A line that is not valid JSON or not an object of the driving file's keys is refused
naming the file and line (:func:`render_core.drive.parse_json_lines`); the values are the server's to validate
(its errors come back on the data channel and are counted).
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

import numpy as np


def _camera(value: Any) -> dict:
    if isinstance(value, str):
        return {"preset": value}
    if isinstance(value, dict) and {"K", "R", "t"} & set(value):
        flat = {k: np.asarray(value.get(k, []), np.float64).reshape(-1).tolist() for k in ("K", "R", "t")}
        return {"opencv": {"k": flat["K"], "r": flat["R"], "t": flat["t"], "width": value.get("width", 0),
                           "height": value.get("height", 0)}}
    if isinstance(value, dict):
        names = {"yaw": "yawDeg", "pitch": "pitchDeg", "distance": "distance"}
        return {"orbit": {names.get(k, k): v for k, v in value.items()}}
    return {"preset": value}  # the server names what is wrong


def frame_message(line: dict, index: int, client_time_us: int = 0) -> dict:
    """One driving-file line -> a ``StreamRequest`` as protobuf JSON (``{"frame": {...}}``)."""
    frame: dict[str, Any] = {"index": index, "clientTimeUs": client_time_us}
    expression = line.get("expression")
    if isinstance(expression, dict):
        frame["namedCoefficients"] = expression
    elif expression is not None:
        frame["coefficients"] = expression
    if line.get("joints") is not None:
        frame["joints"] = {name: {"values": values} for name, values in dict(line["joints"]).items()}
    if line.get("eyelids") is not None:
        frame["eyelids"] = line["eyelids"]
    if line.get("camera") is not None:
        frame["camera"] = _camera(line["camera"])
    return {"frame": frame}


def read_drive(path: str | Path) -> list[dict]:
    """The driving file's lines as objects (blank lines skipped; read as ``blendsplat render --drive`` reads them,
    without an avatar to check the values against); FrameError naming the line otherwise."""
    from render_core.drive import check_keys, parse_json_lines
    from render_core.errors import FrameError

    path = Path(path)
    with path.open("rb") as f:
        lines = parse_json_lines(enumerate(f, start=1), check_keys, source=path.name)
    if not lines:
        raise FrameError(f"{path.name}: the driving file has no frames")
    return lines


async def live(url: str, avatar: str, drive: str | Path, *, out: str | Path | None = None, size: int = 512,
               fps: float = 30.0, codec: str = "h264,vp8", api_key: str | None = None, loops: int = 1,
               verify: int = 0) -> dict:
    """Play ``drive`` (``loops`` times) to ``avatar`` over WebRTC (module docstring); the report. ``verify``: that
    many received frames (spread over the run) compared with the same poses rendered by ``POST /v1/render`` as
    PNG afterwards (``psnr_db``: mean and minimum)."""
    from .webrtc.client import WhepClient, match_indices, use_loopback_if_local

    lines = read_drive(drive)
    use_loopback_if_local(url)
    client = WhepClient(url.rstrip("/"), avatar, size=size, codecs=codec, api_key=api_key, keep=lambda n: True)
    await client.open()
    sent: dict[int, float] = {}
    poses: dict[int, dict] = {}
    try:
        start = time.perf_counter()
        for i, line in enumerate([line for _ in range(max(1, loops)) for line in lines], 1):
            await asyncio.sleep(max(0.0, start + (i - 1) / fps - time.perf_counter()))
            sent[i], message = time.perf_counter(), frame_message(line, i, int(time.time() * 1e6))
            poses[i] = message["frame"]
            client.send(message)
        await asyncio.sleep(min(2.0, 10 / fps) + 0.5)  # the last frames' way back
    finally:
        await client.close()
    indices = match_indices(client.frames, client.timings)
    latencies = [(f.at - sent[i]) * 1e3 for f, i in zip(client.frames, indices, strict=True) if i in sent]
    written = _write(client.frames, out, fps) if out else 0
    matched = [(f, i) for f, i in zip(client.frames, indices, strict=True) if i in poses and f.image is not None]
    psnrs = await _verify(url.rstrip("/"), avatar, size, api_key, matched[:: max(1, len(matched) // verify)]
                          [:verify], poses) if verify and matched else []
    codec_used = client.timings[-1]["video"]["codec"] if client.timings else None
    return {"avatar": avatar, "size": size, "codec": codec_used, "sent": len(sent), "frames": len(client.frames),
            "matched": len(latencies), "errors": len(client.errors),
            "error_messages": [e.get("message", "") for e in client.errors][:10],
            "latency_ms": {p: (round(float(np.percentile(latencies, q)), 2) if latencies else None)
                           for p, q in (("p50", 50), ("p95", 95), ("p99", 99))},
            "out": str(out) if out else None, "written": written,
            "psnr_db": {"mean": round(float(np.mean(psnrs)), 2), "min": round(float(np.min(psnrs)), 2),
                        "frames": len(psnrs)} if psnrs else None}


async def _verify(url: str, avatar: str, size: int, api_key: str | None, frames: list, poses: dict) -> list[float]:
    """PSNR of each received frame against its pose rendered by POST /v1/render as PNG."""
    import httpx

    from render_core.evaluation.metrics import psnr
    from render_core.media.codecs import decode_image

    out = []
    async with httpx.AsyncClient(timeout=60.0, headers={"Authorization": f"Bearer {api_key}"} if api_key
                                 else {}) as http:
        for frame, index in frames:
            pose = {k: v for k, v in poses[index].items() if k != "clientTimeUs"}
            r = await http.post(f"{url}/v1/render", json={"avatar_id": avatar, "width": size, "height": size,
                                                           "codec": "CODEC_PNG", "frame": pose})
            r.raise_for_status()
            reference = decode_image("png", r.content, size, size)[..., :3].astype(np.float32)
            out.append(psnr(frame.image.astype(np.float32), reference, data_range=255.0))
    return out


def _write(frames, out: str | Path, fps: float) -> int:
    """The received frames (RGB uint8) as an H.264 MP4; the count written."""
    import torch

    from render_core.media.files import VideoWriter

    images = [f.image for f in frames if f.image is not None]
    if not images:
        return 0
    h, w = images[0].shape[:2]
    with VideoWriter(out, w - w % 2, h - h % 2, fps=max(1, round(fps))) as video:
        for image in images:
            video.write(torch.from_numpy(np.ascontiguousarray(image[: h - h % 2, : w - w % 2])).float() / 255.0)
    return len(images)
