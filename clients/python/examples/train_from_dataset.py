"""Upload a tracked-video dataset, train an avatar on it, follow the job live, and stream one frame of the result.

    BLENDSPLAT_URL=http://127.0.0.1:8080 BLENDSPLAT_API_KEY=$(cat data/admin.key) \
        python clients/python/examples/train_from_dataset.py [DATASET.tar.gz | VIDEO.mp4]

``BLENDSPLAT_EXAMPLE_ITERATIONS`` iterations (default 20) of the tiny preset. Progress goes to stderr; the last
line is ``{"job": ID, "state": "succeeded", "avatar": ...}``.
"""

import json
import os
import secrets
import sys
from pathlib import Path

from blendsplat_client import Client

DATA = Path(__file__).resolve().parent / "data"


def main() -> None:
    source = Path(sys.argv[1]) if len(sys.argv) > 1 else DATA / "dataset.tar.gz"
    iterations = int(os.environ.get("BLENDSPLAT_EXAMPLE_ITERATIONS", "20"))
    avatar = f"example-{secrets.token_hex(4)}"

    def uploaded(sent: int, total: int) -> None:
        print(f"\ruploading {sent}/{total} bytes", end="\n" if sent == total else "", file=sys.stderr)

    def progress(event) -> None:
        if event.event == "progress" and event.data.get("iteration"):
            d = event.data
            print(f"iteration {d['iteration']}/{d.get('total_iterations')} loss {d.get('loss')}", file=sys.stderr)
        elif event.event == "state":
            print(f"state: {event.data.get('state')}", file=sys.stderr)

    with Client(timeout=60) as client:
        upload = client.upload(source, progress=uploaded)
        print(f"upload {upload['upload_id']}: {upload['kind']}, {upload['frames']} frames", file=sys.stderr)
        job = client.submit_job(upload["upload_id"], preset="tiny", iterations=iterations, avatar_id=avatar)
        job = client.wait(job["id"], on_event=progress, timeout=1800)
        report = json.loads(client.artefact(job["id"], "report"))
        print(f"held-out report: {sorted(report)[:6]}", file=sys.stderr)
        frame = client.render(avatar, 128, "png", expression={})  # the new avatar renders at once
        print(f"rendered a {frame.width}x{frame.height} frame of {avatar}", file=sys.stderr)
    print(json.dumps({"job": job["id"], "state": job["state"], "avatar": avatar}))


if __name__ == "__main__":
    main()
