"""Stream frames from a running service over gRPC, as a client outside its container would (deploy/smoke).

    python deploy/stream_check.py --target 127.0.0.1:50051 --avatar demo --seconds 3

One stream at --fps, every frame acknowledged (service/bench_stream.py's client), with the API key of
BLENDSPLAT_API_KEY as ``authorization: Bearer`` metadata when it is set. Prints one JSON line (frames, fps,
latency p50, errors); exit 0 when frames arrived and nothing failed.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys

import grpc

from blendsplat.v1 import render_pb2_grpc as pb_grpc
from service.bench_stream import _pct, _run_stream


class BearerKey(grpc.aio.StreamStreamClientInterceptor):
    def __init__(self, key: str):
        self.key = key

    async def intercept_stream_stream(self, continuation, details, request_iterator):
        metadata = grpc.aio.Metadata(*(details.metadata or ()), ("authorization", f"Bearer {self.key}"))
        details = grpc.aio.ClientCallDetails(details.method, details.timeout, metadata, details.credentials,
                                             details.wait_for_ready)
        return await continuation(details, request_iterator)


async def check(target: str, avatar: str, seconds: float, fps: float, size: int) -> dict:
    key = os.environ.get("BLENDSPLAT_API_KEY", "").strip()
    interceptors = [BearerKey(key)] if key else None
    async with grpc.aio.insecure_channel(target, interceptors=interceptors) as channel:
        r = await _run_stream(pb_grpc.RenderServiceStub(channel), avatar, size, "jpeg", fps, seconds, 0.5, 0)
    return {"target": target, "avatar": avatar, "frames": r.frames, "fps": round(r.frames / seconds, 2),
            "latency_p50_ms": _pct(r.latencies, 50), "gaussians": r.gaussians, "errors": r.errors,
            "messages": r.messages[:5], "api_key": bool(key)}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--target", required=True)
    p.add_argument("--avatar", required=True)
    p.add_argument("--seconds", type=float, default=3.0)
    p.add_argument("--fps", type=float, default=15.0)
    p.add_argument("--size", type=int, default=256)
    a = p.parse_args()
    result = asyncio.run(check(a.target, a.avatar, a.seconds, a.fps, a.size))
    print(json.dumps(result))
    return 0 if result["frames"] > 0 and not result["errors"] else 1


if __name__ == "__main__":
    sys.exit(main())
