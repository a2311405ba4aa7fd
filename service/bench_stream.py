"""`blendsplat bench stream`: a real gRPC client that drives N concurrent streams at a fixed pose rate.

Each stream sends a pose every 1/fps seconds (``drive``, :mod:`service.bench_drive`: ``smooth``, the default,
sinusoids under 2 Hz as a person moves, or ``random``, every frame drawn afresh), acknowledges every frame it
receives, and measures pose-to-frame latency (from building the pose to receiving its encoded frame). The first
``warmup`` seconds are not counted. ``verify_frames`` (``--verify N``): afterwards N of the streamed frames are
compared with a cold render of their poses (:mod:`service.bench_verify`, ``psnr_vs_cold_db``).

The report is strict JSON: a figure with no samples (no frames arrived) is null, never NaN. The server's resident
memory (``server_rss_mb``) is read from its Prometheus endpoint (``process_resident_memory_bytes``): the
``metrics_url`` given, else ``http://<target host>:<the default HTTP port>/metrics``; when that cannot be read the
figures are null and ``server_rss_note`` says why. A server that cannot be reached raises
:class:`ServerUnreachable` (an OSError) before any stream starts.
"""

from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import dataclass, field

import grpc
import numpy as np

from blendsplat.v1 import render_pb2 as pb
from blendsplat.v1 import render_pb2_grpc as pb_grpc

from .bench_drive import Drive
from .bench_verify import VERIFIABLE, Keeper, choose, keepers, verify
from .params import CODEC_NAMES

CODECS = {name: value for value, name in CODEC_NAMES.items() if value}
log = logging.getLogger(__name__)
CONNECT_SECONDS = 5.0  # how long the channel may take to connect before the server counts as unreachable


class ServerUnreachable(ConnectionError):
    """No gRPC server answers at the target."""


@dataclass
class _Stream:
    latencies: list[float] = field(default_factory=list)
    server_ms: list[float] = field(default_factory=list)
    # queue, blend, lbs, raster, encode, batch per frame (blend, lbs and raster are the batched call's: its frames')
    stages: list[list[float]] = field(default_factory=list)
    bytes: list[int] = field(default_factory=list)
    frames: int = 0
    errors: int = 0
    dropped: int = 0
    gaussians: int = 0
    messages: list[str] = field(default_factory=list)


async def _run_stream(stub: pb_grpc.RenderServiceStub, avatar: str, size: int, codec: str, fps: float,
                      seconds: float, warmup: float, seed: int, ack: bool = True,
                      api_key: str | None = None, drive: str = "smooth", keeper: Keeper | None = None) -> _Stream:
    """One stream; ``keeper`` (``--verify``) keeps some of its counted frames with their poses."""
    result = _Stream()
    outbox: asyncio.Queue[pb.StreamRequest | None] = asyncio.Queue()
    sent_at: dict[int, float] = {}
    poses: dict[int, pb.FrameParams] = {}  # --verify: the pose of each frame on its way
    header_seen = asyncio.Event()
    header: dict = {}
    t_start = time.perf_counter()
    count_from = t_start + warmup

    async def requests():
        while (req := await outbox.get()) is not None:
            yield req

    async def tick() -> None:
        await header_seen.wait()
        poser = Drive(drive, seed, header["names"], header["joints"], fps)
        period, index, t_next = 1.0 / fps, 0, time.perf_counter()
        end = time.perf_counter() + warmup + seconds
        while t_next < end:
            await asyncio.sleep(max(0.0, t_next - time.perf_counter()))
            index += 1
            msg = poser.pose(index)
            sent_at[index] = time.perf_counter()
            if keeper is not None:
                poses[index] = msg
            outbox.put_nowait(pb.StreamRequest(frame=msg))
            t_next += period
        await asyncio.sleep(0.5)  # let the last frames arrive before half-closing
        outbox.put_nowait(None)

    outbox.put_nowait(pb.StreamRequest(open=pb.SessionConfig(
        avatar_id=avatar, width=size, height=size, codec=CODECS[codec], fps_hint=fps)))
    ticker = asyncio.create_task(tick())
    try:
        metadata = (("authorization", f"Bearer {api_key}"),) if api_key else None
        async for reply in stub.RenderStream(requests(), metadata=metadata):
            kind = reply.WhichOneof("msg")
            now = time.perf_counter()
            if kind == "header":
                header.update(names=list(reply.header.expression_names), joints=list(reply.header.joint_names))
                result.gaussians = reply.header.gaussians
                header_seen.set()
            elif kind == "frame":
                f = reply.frame
                if ack:
                    outbox.put_nowait(pb.StreamRequest(ack=pb.Ack(index=f.index)))
                if sent_at.get(f.index, 0.0) >= count_from or not ack:
                    result.frames += 1
                    result.latencies.append((now - sent_at[f.index]) * 1e3)
                    result.server_ms.append(f.timings.total_ms)
                    t = f.timings
                    result.stages.append([t.queue_ms, t.blend_ms, t.lbs_ms, t.raster_ms, t.encode_ms, t.batch])
                    result.bytes.append(len(f.data))
                    if keeper is not None:
                        keeper.offer(f.index, poses.get(f.index), f.data)
                sent_at.pop(f.index, None)
                poses.pop(f.index, None)
            elif kind == "error":
                result.errors += 1
                result.messages.append(reply.error.message)
            elif kind == "status":
                result.dropped = reply.status.dropped
                if reply.status.code != pb.OK:
                    result.errors += 1
                    result.messages.append(reply.status.message)
    except grpc.aio.AioRpcError as e:
        result.errors += 1
        result.messages.append(f"{e.code().name}: {e.details()}")
    finally:
        ticker.cancel()
    return result


def _pct(values: list[float], q: float) -> float | None:
    """The ``q``-th percentile, or None (JSON null) without samples."""
    return round(float(np.percentile(values, q)), 2) if values else None


def default_metrics_url(target: str) -> str:
    """The /metrics URL of the server at the gRPC ``target`` (HOST:PORT) when its HTTP port is the default one."""
    from .settings import Settings

    host = target.rsplit(":", 1)[0] if ":" in target else target
    return f"http://{host or '127.0.0.1'}:{Settings.model_fields['http_port'].default}/metrics"


def _server_rss(metrics_url: str) -> tuple[float | None, str | None]:
    """The server's resident memory (MB) from its Prometheus endpoint: (MB, None), or (None, why not)."""
    import urllib.request

    try:
        with urllib.request.urlopen(metrics_url, timeout=10) as r:
            for line in r.read().decode(errors="replace").splitlines():
                if line.startswith("process_resident_memory_bytes "):
                    return round(float(line.split()[1]) / 1e6, 1), None
    except (OSError, ValueError) as e:  # URLError, HTTPError, timeouts are OSErrors
        return None, f"{metrics_url} could not be read ({type(e).__name__}: {str(e)[:200]}); --metrics-url names it"
    return None, f"{metrics_url} has no process_resident_memory_bytes"


async def _connect(channel: grpc.aio.Channel, target: str, seconds: float) -> None:
    """Wait until the channel connects: :class:`ServerUnreachable` as soon as a connection attempt fails (refused,
    no route) or after ``seconds``."""
    hint = "is it running (`blendsplat serve` or `blendsplat up`)? --target HOST:PORT names another"
    deadline = time.monotonic() + seconds
    state = channel.get_state(try_to_connect=True)
    while state != grpc.ChannelConnectivity.READY:
        if state in (grpc.ChannelConnectivity.TRANSIENT_FAILURE, grpc.ChannelConnectivity.SHUTDOWN):
            raise ServerUnreachable(f"cannot connect to a gRPC server at {target}; {hint}")
        try:
            await asyncio.wait_for(channel.wait_for_state_change(state), max(0.0, deadline - time.monotonic()))
        except TimeoutError:
            raise ServerUnreachable(f"no gRPC server answers at {target} (not connected within {seconds:g} s); "
                                    f"{hint}") from None
        state = channel.get_state(try_to_connect=True)


async def bench_stream(target: str, avatar: str, streams: int = 1, seconds: float = 10.0, fps: float = 30.0,
                       size: int = 512, codec: str = "jpeg", warmup: float = 1.0, seed: int = 0,
                       ack: bool = True, metrics_url: str | None = None, api_key: str | None = None,
                       connect_seconds: float = CONNECT_SECONDS, drive: str = "smooth", verify_frames: int = 0) -> dict:
    """``ack=False``: readers that never acknowledge (flow control must keep the server's memory flat: the server's
    resident memory before and at the end is reported, from ``metrics_url``, by default the target host's
    /metrics on the default HTTP port). ``drive``: the poses (:mod:`service.bench_drive`, smooth or random).
    ``verify_frames``: after the timed run, that many streamed frames compared with a cold render of their poses
    (:mod:`service.bench_verify`; ``psnr_vs_cold_db``). Raises :class:`ServerUnreachable` when no server answers at
    ``target`` within ``connect_seconds``; ValueError for a codec that cannot be verified."""
    if verify_frames and codec not in VERIFIABLE:
        raise ValueError(f"--verify compares frames one by one: codec {codec!r} cannot be verified (use one of "
                         f"{', '.join(VERIFIABLE)})")
    keep = keepers(streams, verify_frames) if verify_frames > 0 else None
    metadata = (("authorization", f"Bearer {api_key}"),) if api_key else None
    async with grpc.aio.insecure_channel(target, options=[("grpc.max_receive_message_length", 64 << 20)]) as ch:
        await _connect(ch, target, connect_seconds)
        metrics_url = metrics_url or default_metrics_url(target)
        rss_before, rss_note = await asyncio.to_thread(_server_rss, metrics_url)
        log.info("streaming %d stream(s) of %r from %s for %g s after a %g s warm-up (%s drive)", streams, avatar,
                 target, seconds, warmup, drive)
        stub = pb_grpc.RenderServiceStub(ch)
        results = await asyncio.gather(*(
            _run_stream(stub, avatar, size, codec, fps, seconds, warmup, seed + i, ack, api_key, drive,
                        keep[i] if keep else None)
            for i in range(streams)))
        rss_during, note = await asyncio.to_thread(_server_rss, metrics_url)
        rss_note = rss_note or note
        checked = await verify(stub, avatar, size, codec, choose(keep, verify_frames), metadata) if keep else None
    latencies = [x for r in results for x in r.latencies]
    server = [x for r in results for x in r.server_ms]
    sizes = [x for r in results for x in r.bytes]
    per_stream = [r.frames / seconds for r in results]
    return {
        "target": target, "avatar": avatar, "streams": streams, "gaussians": max(r.gaussians for r in results),
        "size": size, "codec": codec, "fps_target": fps, "seconds": seconds, "warmup_seconds": warmup,
        "fps_per_stream": round(float(np.mean(per_stream)), 2), "fps_per_stream_min": round(min(per_stream), 2),
        "fps_aggregate": round(sum(per_stream), 2), "frames": len(latencies),
        "latency_ms": {"p50": _pct(latencies, 50), "p95": _pct(latencies, 95), "p99": _pct(latencies, 99),
                       "max": round(max(latencies), 2) if latencies else None},
        "server_ms": {"p50": _pct(server, 50), "p99": _pct(server, 99),
                      **{f"{stage}_p50": _pct([s[i] for r in results for s in r.stages], 50)
                         for i, stage in enumerate(("queue", "blend", "lbs", "raster", "encode"))},
                      "batch_mean": round(float(np.mean([s[5] for r in results for s in r.stages])), 2)
                      if latencies else None},
        "bytes_per_frame": round(float(np.mean(sizes)), 1) if sizes else 0.0,
        "dropped": sum(r.dropped for r in results), "errors": sum(r.errors for r in results),
        "error_messages": sorted({m for r in results for m in r.messages})[:10],
        "drive": drive, "acks": ack, "server_rss_mb": {"before": rss_before, "end": rss_during},
        "metrics_url": metrics_url,
        **({"server_rss_note": rss_note} if rss_note else {}),
        **({"psnr_vs_cold_db": checked.get("psnr_db_min"), "verify": checked} if checked is not None else {}),
    }
