"""Stream a driving file through the service and save the frames as an MP4.

    pip install './clients/python[media]'
    BLENDSPLAT_URL=http://127.0.0.1:8080 BLENDSPLAT_GRPC_TARGET=127.0.0.1:50051 \
        BLENDSPLAT_API_KEY=$(cat data/admin.key) python clients/python/examples/stream_to_mp4.py [DRIVING.jsonl]

Each line of the driving file (docs/method.md section 11) is one pose, sent as it is (``stream.send(**pose)``);
``stream.render`` keeps one pose in flight so that none is dropped. Prints ``{"frames": N, "out": "stream.mp4"}``.
"""

import json
import os
import statistics
import sys
from pathlib import Path

from blendsplat_client import Client
from blendsplat_client.media import Mp4Writer

DATA = Path(__file__).resolve().parent / "data"


def main() -> None:
    driving = Path(sys.argv[1]) if len(sys.argv) > 1 else DATA / "drive.jsonl"
    poses = [json.loads(line) for line in driving.read_text().splitlines() if line.strip()]
    avatar = os.environ.get("BLENDSPLAT_AVATAR", "demo")
    out = "stream.mp4"
    latencies = []
    with Client() as client, Mp4Writer(out, fps=30) as video:
        with client.stream(avatar, size=256, codec="jpeg") as stream:
            for frame in stream.render(poses):
                video.write(frame.image)
                latencies.append(frame.latency_ms)
    print(f"{video.frames} frames of {avatar!r}, latency p50 {statistics.median(latencies):.1f} ms", file=sys.stderr)
    print(json.dumps({"frames": video.frames, "out": out, "latency_p50_ms": round(statistics.median(latencies), 1)}))


if __name__ == "__main__":
    main()
