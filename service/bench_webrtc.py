"""`blendsplat bench webrtc`: N WebRTC sessions driven at a fixed pose rate, then the same poses as PNG and JPEG.

Each stream (a :class:`~service.webrtc.client.WhepClient`) sends smooth poses (a few expressions and the head's
joints on slow sines, as a speaking face moves) on its data channel every 1/fps seconds and receives the video
track. A video frame is matched to the pose it shows by its RTP timestamp (:func:`~service.webrtc.client.
match_indices`); pose-to-frame latency runs from sending the pose to the frame received (its last packet; both on
this client's clock), as the gRPC bench's runs to the message received. Like that bench, this client decodes nothing
during the run (a receiver's decoder is the receiving machine's, not the server's: here it would share the server's
cores): each frame's bitstream is kept and decoded after the run. The first ``warmup`` seconds are not counted.

After the timed run (never during it), the first stream's video is decoded and its recorded poses are rendered once
more by the service:
as PNG (the reference) for the frames whose decoded pixels were kept (``psnr_db``: the decoded video against them,
matched by index, mean over the kept frames), and as JPEG at the service's default quality for a sample of the
poses (``jpeg_bytes_per_second``: their mean size times the video's frame rate: the JPEG stream's bytes for the same
frames). Those renders go through ``POST /v1/render`` on the same URL, or the gRPC ``Render`` call when a gRPC
target is given; both are the engine's single-frame path.

The JSON report: fps (per stream, mean; fps_min the slowest), latency_ms {p50, p95, p99, max}, errors (data
channel errors, refused or failed sessions, missing frames are not errors), psnr_db, bytes_per_second (the video
bitstream's bytes per second per stream), jpeg_bytes_per_second, and the server's per-frame timings, p50 unless
named (``server_ms``): render_p50 (blend + lbs + raster: one batched render call), render_per_frame_p50 (that
divided by the frames in its batch; batch_mean), the video encoder's encode_p50 and encode_p99 (wall time of its
call for one frame: the codec and RTP packetisation of a 4:2:0 frame) and encode_cpu_p50 (that call's CPU time: the
encode cost per frame and stream), send_p50 (handed to the encoder to its RTP packets sent) and total_p50 (pose
received to its packets sent).
"""

from __future__ import annotations

import asyncio
import functools
import json
import math
import os
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .webrtc.client import WhepClient

KEEP_FRAMES = 40  # decoded frames kept for the PSNR (evenly over the run)
JPEG_SAMPLES = 120  # poses rendered as JPEG for the byte rate


@functools.lru_cache(maxsize=64)
def _waves(count: int, seed: int) -> tuple[list[int], list[float], list[float]]:
    """The six active expressions of ``seed`` and every expression's frequency and phase (drawn once: a pose is
    then a few sines, so the client's 30 poses a second per stream cost it little CPU beside the server's)."""
    rng = np.random.default_rng(seed)
    active = rng.choice(count, size=min(6, count), replace=False)
    return [int(k) for k in active], rng.uniform(0.2, 0.7, count).tolist(), rng.uniform(0, 2 * math.pi, count).tolist()


def smooth_pose(index: int, fps: float, names: list[str], joints: list[str], seed: int = 0) -> dict:
    """FrameParams JSON of frame ``index``: six expressions and the non-root joints on slow sines."""
    t = index / fps
    active, freq, phase = _waves(len(names), seed)
    coeffs = [0.0] * len(names)
    for k in active:
        coeffs[k] = round(0.3 + 0.3 * math.sin(2 * math.pi * freq[k] * t + phase[k]), 4)
    rotations = {name: {"values": [round(0.08 * math.sin(2 * math.pi * 0.15 * t + i), 4),
                                   round(0.12 * math.sin(2 * math.pi * 0.1 * t + 1 + i), 4), 0.0]}
                 for i, name in enumerate(joints) if name != "root"}
    return {"index": index, "clientTimeUs": time.time_ns() // 1000, "coefficients": coeffs, "joints": rotations}


@dataclass
class _Run:
    client: WhepClient
    sent: dict[int, float] = field(default_factory=dict)  # index -> perf_counter when sent
    poses: dict[int, dict] = field(default_factory=dict)
    window: tuple[float, float] = (0.0, 0.0)
    bytes_window: int = 0
    error: str | None = None


async def _drive(run: _Run, fps: float, seconds: float, warmup: float, seed: int) -> None:
    c = run.client
    names, joints = c.header.get("expressionNames", []), c.header.get("jointNames", [])
    period, index = 1.0 / fps, 0
    t0 = time.perf_counter()
    t_next, count_from, end = t0, t0 + warmup, t0 + warmup + seconds
    bytes_start = None
    while t_next < end:
        await asyncio.sleep(max(0.0, t_next - time.perf_counter()))
        if bytes_start is None and time.perf_counter() >= count_from:
            bytes_start = c.video_bytes()
        index += 1
        pose = smooth_pose(index, fps, names, joints, seed)
        run.sent[index], run.poses[index] = time.perf_counter(), pose
        c.send({"frame": pose})
        t_next += period
    await asyncio.sleep(0.5)  # the last frames arrive
    run.window = (count_from, end)
    run.bytes_window = c.video_bytes() - (bytes_start or 0)


async def _render(http, url: str, grpc_target: str | None, avatar: str, size: int, codec: str, pose: dict
                  ) -> bytes:
    """One pose rendered by the service's single-frame path (PNG or JPEG at its default quality)."""
    if grpc_target:
        import grpc
        from google.protobuf import json_format

        from blendsplat.v1 import render_pb2 as pb
        from blendsplat.v1 import render_pb2_grpc as pb_grpc

        request = json_format.ParseDict({"avatarId": avatar, "width": size, "height": size,
                                         "codec": f"CODEC_{codec.upper()}", "frame": pose}, pb.RenderRequest())
        key = http.headers.get("authorization")
        async with grpc.aio.insecure_channel(grpc_target) as ch:
            reply = await pb_grpc.RenderServiceStub(ch).Render(
                request, metadata=(("authorization", key),) if key else None)
        return reply.frame.data
    r = await http.post(f"{url}/v1/render", json={"avatar_id": avatar, "width": size, "height": size,
                                                  "codec": f"CODEC_{codec.upper()}", "frame": pose})
    r.raise_for_status()
    return r.content


async def _quality(run: _Run, indices: list[int | None], url: str, grpc_target: str | None, avatar: str,
                   size: int, api_key: str | None) -> tuple[float | None, float | None, float | None]:
    """(mean PSNR of the kept decoded frames against PNG renders, its minimum, mean JPEG bytes per frame)."""
    import httpx

    from render_core.evaluation.metrics import psnr
    from render_core.media.codecs import decode_image

    kept = [(f, i) for f, i in zip(run.client.frames, indices, strict=True) if f.image is not None and i]
    shown = sorted({i for i in indices if i})
    sample = shown[:: max(1, len(shown) // JPEG_SAMPLES)]
    headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
    psnrs, jpeg = [], []
    async with httpx.AsyncClient(timeout=60.0, headers=headers) as http:
        for frame, index in kept:
            png = await _render(http, url, grpc_target, avatar, size, "png", run.poses[index])
            reference = decode_image("png", png, size, size)[..., :3]
            psnrs.append(psnr(frame.image.astype(np.float32), reference.astype(np.float32), data_range=255.0))
        for index in sample:
            jpeg.append(len(await _render(http, url, grpc_target, avatar, size, "jpeg", run.poses[index])))
    return (round(float(np.mean(psnrs)), 2) if psnrs else None, round(float(np.min(psnrs)), 2) if psnrs else None,
            float(np.mean(jpeg)) if jpeg else None)


def _pct(values: list[float], q: float) -> float | None:
    return round(float(np.percentile(values, q)), 2) if values else None


def _server_ms(timings: list[dict]) -> dict:
    """The server's per-frame figures (p50 unless named): the render call (blend + lbs + raster, for the whole
    batch) and its share per frame (divided by the batch), the video encode per frame (wall and CPU: the encode
    cost), the hand-off to the RTP packets sent, and the pose's receipt to its packets sent."""
    stage = [t["frame"].get("timings", {}) for t in timings]
    video = [t.get("video", {}) for t in timings]
    render = [s.get("blendMs", 0) + s.get("lbsMs", 0) + s.get("rasterMs", 0) for s in stage]
    return {"render_p50": _pct(render, 50),
            "render_per_frame_p50": _pct([r / max(1, int(s.get("batch", 1))) for r, s in zip(render, stage,
                                                                                            strict=True)], 50),
            "batch_mean": round(float(np.mean([int(s.get("batch", 1)) for s in stage])), 2) if stage else None,
            "encode_p50": _pct([s.get("encodeMs", 0) for s in stage], 50),
            "encode_p99": _pct([s.get("encodeMs", 0) for s in stage], 99),
            "encode_cpu_p50": _pct([v["encodeCpuMs"] for v in video if "encodeCpuMs" in v], 50),
            "send_p50": _pct([v["sendMs"] for v in video if "sendMs" in v], 50),
            "total_p50": _pct([s.get("totalMs", 0) for s in stage], 50)}


async def bench_webrtc(url: str, avatar: str, *, seconds: float = 20.0, fps: float = 30.0, size: int = 512,
                       codec: str = "h264", streams: int = 1, warmup: float = 2.0, seed: int = 0,
                       api_key: str | None = None, grpc_target: str | None = None) -> dict:
    from .webrtc.client import WhepClient, match_indices, use_loopback_if_local

    url = url.rstrip("/")
    use_loopback_if_local(url)
    expected = (warmup + seconds) * fps
    step = max(1, int(expected // KEEP_FRAMES))
    runs = [_Run(WhepClient(url, avatar, size=size, codecs=codec, api_key=api_key, decode=False,
                            keep=lambda n, step=step: n % step == step // 2 and n >= warmup * fps))
            for _ in range(streams)]
    opened = await asyncio.gather(*(r.client.open() for r in runs), return_exceptions=True)
    for run, result in zip(runs, opened, strict=True):
        if isinstance(result, BaseException):
            run.error = f"{type(result).__name__}: {result}"
    live = [r for r in runs if r.error is None]
    await asyncio.gather(*(_drive(r, fps, seconds, warmup, seed + i) for i, r in enumerate(live)))
    for r in live:
        await r.client.close()
    latencies, fps_each, bps, timings = [], [], [], []
    matched_all: list[list[int | None]] = []
    for r in live:
        indices = match_indices(r.client.frames, r.client.timings)
        matched_all.append(indices)
        start, end = r.window
        counted = [(f, i) for f, i in zip(r.client.frames, indices, strict=True) if i and r.sent[i] >= start]
        latencies += [(f.at - r.sent[i]) * 1e3 for f, i in counted]
        fps_each.append(sum(1 for f in r.client.frames if start <= f.at <= end + 0.5) / seconds)
        bps.append(r.bytes_window / seconds)
        timings += [t for t in r.client.timings if int(t["frame"]["index"]) in r.sent
                    and r.sent[int(t["frame"]["index"])] >= start]
    psnr_mean = psnr_min = jpeg_frame = None
    if live:
        live[0].client.decode_recorded()
        psnr_mean, psnr_min, jpeg_frame = await _quality(live[0], matched_all[0], url, grpc_target, avatar, size,
                                                         api_key)
    fps_mean = float(np.mean(fps_each)) if fps_each else 0.0
    return {
        "url": url, "avatar": avatar, "codec": live[0].client.timings[-1]["video"]["codec"]
        if live and live[0].client.timings else codec, "size": size, "streams": streams, "fps_target": fps,
        "seconds": seconds, "warmup_seconds": warmup, "fps": round(fps_mean, 2),
        "fps_min": round(min(fps_each), 2) if fps_each else 0.0, "frames": len(latencies),
        "latency_ms": {"p50": _pct(latencies, 50), "p95": _pct(latencies, 95), "p99": _pct(latencies, 99),
                       "max": round(max(latencies), 2) if latencies else None},
        "errors": sum(len(r.client.errors) for r in runs) + sum(1 for r in runs if r.error),
        "error_messages": ([r.error for r in runs if r.error] + [e.get("message", "") for r in runs
                                                                 for e in r.client.errors])[:10],
        "psnr_db": psnr_mean, "psnr_db_min": psnr_min, "psnr_frames": sum(
            1 for f in (live[0].client.frames if live else []) if f.image is not None),
        "bytes_per_second": round(float(np.mean(bps)), 1) if bps else None,
        "jpeg_bytes_per_second": round(jpeg_frame * fps_mean, 1) if jpeg_frame else None,
        "jpeg_bytes_per_frame": round(jpeg_frame, 1) if jpeg_frame else None,
        "server_ms": _server_ms(timings),
        "replay": "grpc" if grpc_target else "http",
    }


def run(args) -> int:
    """The command: the report as JSON on stdout; exit 1 when no stream opened or no frame arrived."""
    import logging

    from render_core.tools import cli as core_cli

    from .webrtc.client import ClientError

    for name in ("aioice", "aiortc", "httpx"):  # their per-connection INFO lines are not the bench's progress
        logging.getLogger(name).setLevel(logging.WARNING)
    try:
        result = asyncio.run(bench_webrtc(args.url, args.avatar, seconds=args.seconds, fps=args.fps, size=args.size,
                                          codec=args.codec, streams=args.streams, warmup=args.warmup,
                                          seed=args.seed, api_key=args.api_key, grpc_target=args.grpc_target))
    except (ClientError, OSError) as e:
        raise SystemExit(f"blendsplat: error: bench webrtc: {e}") from None  # exit status 1, the text on stderr
    core_cli.emit(result, indent=None if args.json else 2)
    if not result["frames"]:
        raise SystemExit(f"blendsplat: error: bench webrtc: no frames: {json.dumps(result['error_messages'])}")
    return 0


def add_parser(bench_commands) -> None:
    b = bench_commands.add_parser("webrtc", help="drive a running service over WebRTC: fps, pose-to-frame latency, "
                                                 "decoded quality and bytes against the JPEG stream")
    b.add_argument("--url", required=True, help="the service's HTTP URL, e.g. http://127.0.0.1:8080")
    b.add_argument("--avatar", required=True, help="avatar id")
    b.add_argument("--seconds", type=float, default=20.0, help="measured time (after the warm-up)")
    b.add_argument("--warmup", type=float, default=2.0, help="seconds streamed first and not counted")
    b.add_argument("--fps", type=float, default=30.0, help="poses sent per second per stream")
    b.add_argument("--size", type=int, default=512)
    b.add_argument("--codec", choices=("h264", "vp8"), default="h264")
    b.add_argument("--streams", type=int, default=1)
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--grpc-target", default=None, help="HOST:PORT: replay the poses over gRPC (default: POST "
                                                       "/v1/render on --url)")
    b.add_argument("--json", action="store_true", help="one JSON line")
    b.add_argument("--api-key", default=os.environ.get("BLENDSPLAT_API_KEY"),
                   help="API key with the render scope (default: the environment variable BLENDSPLAT_API_KEY)")
    b.set_defaults(fn=run)
