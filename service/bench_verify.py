"""`blendsplat bench stream --verify N`: are the streamed frames the frames a cold render gives?

While the streams run, each keeps a few of its counted frames (:class:`Keeper`: the frame's index, the pose sent
for it and the encoded bytes received, evenly spread over the run, at most twice what it needs). After the timed
run, N of them (spread over the streams and over time) are rendered again, one at a time, by the server's Render
RPC: a single frame outside any stream, so nothing a stream carries from frame to frame (a previous frame's
depth order, tile lists) is used, with every CPU-cost mechanism off (``RenderRequest.reference``: the native
renderer's baseline schedule), as PNG (lossless). The figure is the PSNR of
each streamed frame against that cold render, **compared in the stream's codec**: for JPEG, the cold render is
encoded with the same encoder and quality the server uses (libjpeg-turbo through simplejpeg, quality 90, 4:2:0,
fast DCT) and both are decoded. A frame whose pixels are the cold render's then compares as identical
(``PSNR_CAP``, 100 dB), whatever JPEG itself loses (about 40 dB, ``psnr_vs_lossless_db``), and what a mechanism
changes shows as it survives the encoder (a rounding flip in a DCT coefficient included), so the figure measures
the mechanisms, not JPEG. PNG and raw RGBA streams are compared as they are (RGBA). H.264 has no per-frame
reference (its frames depend on the frames before) and cannot be verified.

``psnr_vs_cold_db`` is the minimum over the frames; ``verify`` gives the mean, how many frames were identical, and
the worst frame's stream and index.
"""

from __future__ import annotations

from dataclasses import dataclass

import grpc
import numpy as np

from blendsplat.v1 import render_pb2 as pb
from blendsplat.v1 import render_pb2_grpc as pb_grpc

VERIFIABLE = ("jpeg", "png", "raw_rgba")


@dataclass
class Sample:
    stream: int
    index: int
    pose: pb.FrameParams
    data: bytes  # the frame as streamed (encoded)


class Keeper:
    """About ``want`` to ``2 * want`` of one stream's frames, evenly spread over however many arrive: every
    ``stride``-th frame offered is kept, and when ``2 * want`` are kept every other one goes and the stride
    doubles."""

    def __init__(self, stream: int, want: int):
        self.stream, self.want = stream, max(1, want)
        self.stride, self.seen = 1, 0
        self.kept: list[Sample] = []

    def offer(self, index: int, pose: pb.FrameParams | None, data: bytes) -> None:
        if pose is not None and self.seen % self.stride == 0:
            self.kept.append(Sample(self.stream, index, pose, data))
            if len(self.kept) >= 2 * self.want:
                self.kept, self.stride = self.kept[::2], self.stride * 2
        self.seen += 1

    def pick(self, n: int) -> list[Sample]:
        """``n`` of the kept frames (all of them if fewer), evenly spaced."""
        if n >= len(self.kept):
            return list(self.kept)
        return [self.kept[int(i)] for i in np.linspace(0, len(self.kept) - 1, n).round()] if n > 0 else []


def keepers(streams: int, n: int) -> list[Keeper]:
    """One :class:`Keeper` per stream, together keeping at least ``n`` frames when that many arrive."""
    return [Keeper(i, -(-n // streams)) for i in range(streams)]


def choose(keep: list[Keeper], n: int) -> list[Sample]:
    """``n`` frames over the streams: as many from each as it allows (``n // streams``, the rest to the first),
    more from the others where a stream has fewer."""
    quota = [n // len(keep) + (i < n % len(keep)) for i in range(len(keep))]
    spare = sum(max(0, q - len(k.kept)) for q, k in zip(quota, keep, strict=True))
    for i, k in enumerate(keep):  # a short stream's share goes to the others
        extra = min(spare, max(0, len(k.kept) - quota[i]))
        quota[i] += extra
        spare -= extra
    return [s for q, k in zip(quota, keep, strict=True) for s in k.pick(q)]


def _compare(codec: str, streamed: bytes, cold_rgba: np.ndarray, size: int) -> tuple[float, float | None]:
    """(PSNR of the streamed frame against the cold render in the stream's codec, PSNR against the cold render
    itself (JPEG: what the codec loses; else None))."""
    from render_core.evaluation.metrics import psnr
    from render_core.media.codecs import decode_image, make_encoder

    got = decode_image(codec, streamed, size, size)
    if codec != "jpeg":
        return psnr(got, cold_rgba, data_range=255.0), None
    with make_encoder("jpeg", size, size) as encoder:  # the server's encoder, default quality (the bench's)
        cold = decode_image("jpeg", encoder.encode(cold_rgba), size, size)
    return psnr(got, cold, data_range=255.0), psnr(got, cold_rgba[..., :3], data_range=255.0)


async def verify(stub: pb_grpc.RenderServiceStub, avatar: str, size: int, codec: str, samples: list[Sample],
                 metadata) -> dict:
    """Render ``samples`` again cold (Render RPC, PNG, ``reference``: every speed mechanism off) and compare
    (module docstring): the ``verify`` report."""
    from render_core.media.codecs import decode_image

    figures, lossless, errors = [], [], []
    for s in samples:
        pose = pb.FrameParams()
        pose.CopyFrom(s.pose)
        try:
            reply = await stub.Render(pb.RenderRequest(avatar_id=avatar, width=size, height=size, codec=pb.CODEC_PNG,
                                                       frame=pose, reference=True), metadata=metadata)
        except grpc.aio.AioRpcError as e:
            errors.append(f"{e.code().name}: {e.details()}")
            continue
        cold = decode_image("png", reply.frame.data, size, size)
        value, loss = _compare(codec, s.data, cold, size)
        figures.append((value, s))
        if loss is not None:
            lossless.append(loss)
    if not figures:
        return {"frames": 0, "note": "; ".join(sorted(set(errors))[:3]) or "no frame was kept to verify"}
    worst, at = min(figures, key=lambda f: f[0])
    values = [f[0] for f in figures]
    return {
        "frames": len(figures), "reference": "Render RPC, reference: every speed mechanism off, no stream state; PNG",
        "compared_in": f"{codec}, the cold render encoded as the server encodes" if codec == "jpeg" else codec,
        "psnr_db_min": round(worst, 2), "psnr_db_mean": round(float(np.mean(values)), 2),
        "identical": sum(v >= _cap() for v in values), "worst": {"stream": at.stream, "index": at.index},
        "psnr_vs_lossless_db": round(min(lossless), 2) if lossless else None, "errors": len(errors),
        **({"error_messages": sorted(set(errors))[:3]} if errors else {}),
    }


def _cap() -> float:
    from render_core.evaluation.metrics import PSNR_CAP

    return PSNR_CAP
