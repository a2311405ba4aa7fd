"""Several render streams at once with asyncio: each plays the driving file on the demo avatar.

    BLENDSPLAT_URL=http://127.0.0.1:8080 BLENDSPLAT_GRPC_TARGET=127.0.0.1:50051 \
        BLENDSPLAT_API_KEY=$(cat data/admin.key) python clients/python/examples/async_streams.py [STREAMS]

Prints ``{"frames": N, "streams": S, "latency_p50_ms": ...}`` (frames over all streams).
"""

import asyncio
import json
import os
import statistics
import sys
from pathlib import Path

from blendsplat_client import AsyncClient

DATA = Path(__file__).resolve().parent / "data"


async def play(client: AsyncClient, avatar: str, poses: list[dict], number: int) -> list[float]:
    latencies = []
    async with client.stream(avatar, size=128, codec="jpeg", camera={"yaw": 10.0 * number}) as stream:
        async for frame in stream.render(poses):
            latencies.append(frame.latency_ms)
    return latencies


async def main() -> None:
    streams = int(sys.argv[1]) if len(sys.argv) > 1 else 3
    poses = [json.loads(line) for line in (DATA / "drive.jsonl").read_text().splitlines() if line.strip()]
    avatar = os.environ.get("BLENDSPLAT_AVATAR", "demo")
    async with AsyncClient() as client:
        results = await asyncio.gather(*(play(client, avatar, poses, n) for n in range(streams)))
    latencies = [ms for result in results for ms in result]
    print(json.dumps({"frames": len(latencies), "streams": streams,
                      "latency_p50_ms": round(statistics.median(latencies), 1)}))


if __name__ == "__main__":
    asyncio.run(main())
