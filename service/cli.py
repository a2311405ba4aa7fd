"""The `blendsplat` command: render_core's commands plus `serve`, `worker`, `up` and `bench stream`."""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
from pathlib import Path

from render_core.tools import cli as core_cli


def _settings(args: argparse.Namespace):
    """Settings from the environment with the command's options over them; None (after saying why) if invalid."""
    from pydantic import ValidationError

    from .settings import Settings

    overrides = {k: v for k, v in (("grpc_port", args.grpc_port), ("http_port", args.http_port),
                                   ("data_dir", args.data_dir), ("host", args.host)) if v is not None}
    try:
        return Settings(**overrides)
    except ValidationError as e:
        print(f"blendsplat: error: invalid settings (environment BLENDSPLAT_* or options):\n{e}", file=sys.stderr)
        return None


def cmd_serve(args: argparse.Namespace) -> int:
    from .server import serve

    settings = _settings(args)
    if settings is None:
        return 2
    asyncio.run(serve(settings))
    return 0


def cmd_up(args: argparse.Namespace) -> int:
    from .server import up

    settings = _settings(args)
    if settings is None:
        return 2
    asyncio.run(up(settings, worker_metrics_port=args.worker_metrics_port, device=args.device))
    return 0


def cmd_worker(args: argparse.Namespace) -> int:
    from .worker import main as worker_main

    return worker_main(args)


def _add_worker(commands) -> None:
    """`blendsplat worker`: its options are service/worker.py's own (``add_arguments``), added when the command is
    parsed, so no other command imports the worker (or needs it to exist)."""
    w = commands.add_parser("worker", help="train queued jobs from the job database until SIGTERM",
                            description="Claims jobs from the job database (BLENDSPLAT_JOBS_URL, default the SQLite "
                                        "file <data-dir>/jobs.db) and trains them one at a time; SIGTERM "
                                        "checkpoints the job in training and hands it back.")
    w.set_defaults(fn=cmd_worker)
    parse = w.parse_known_args
    added = []

    def parse_known_args(args=None, namespace=None):
        if not added:
            try:
                from .worker import add_arguments
            except ImportError as e:
                w.error(f"the worker is unavailable: {e}")
            add_arguments(w)
            added.append(True)
        return parse(args, namespace)

    w.parse_known_args = parse_known_args


def cmd_bench_stream(args: argparse.Namespace) -> int:
    from .bench_stream import bench_stream

    result = asyncio.run(bench_stream(args.target, args.avatar, streams=args.streams, seconds=args.seconds,
                                      fps=args.fps, size=args.size, codec=args.codec, warmup=args.warmup,
                                      seed=args.seed, ack=not args.no_ack, metrics_url=args.metrics_url))
    if args.json:
        print(json.dumps(result))
    else:
        print(json.dumps(result, indent=2))
    return 0 if result["frames"] else 1


def cmd_bench_load(args: argparse.Namespace) -> int:
    from .bench_load import bench_load

    result = bench_load(args.bundle, size=args.size, backend=args.backend, threads=args.threads, vs_v1=args.vs_v1)
    print(json.dumps(result) if args.json else json.dumps(result, indent=2))
    return 0


def build_parser() -> argparse.ArgumentParser:
    from .bench_stream import CODECS

    p = core_cli.build_parser()
    s = p.commands.add_parser("serve", help="run the streaming render service (gRPC + HTTP) until SIGTERM",
                              description="Settings come from BLENDSPLAT_* environment variables "
                                          "(see service/settings.py); these options override them.")
    s.add_argument("--grpc-port", type=int, default=None, help="default 50051 (0: any free port)")
    s.add_argument("--http-port", type=int, default=None, help="default 8080 (0: any free port)")
    s.add_argument("--data-dir", type=Path, default=None, help="bundle store root (default ./data)")
    s.add_argument("--host", default=None, help="interface to listen on (default 0.0.0.0)")
    s.set_defaults(fn=cmd_serve)

    u = p.commands.add_parser("up", help="the whole product on one machine: `serve` plus one training worker",
                              description="Runs the render service (gRPC + HTTP, with the training jobs' REST API) "
                                          "in this process and one `blendsplat worker` child process (nice +10, "
                                          "restarted if it dies) on the same data dir and job database (default: "
                                          "a SQLite file in the data dir). SIGTERM or Ctrl-C stops both: streams "
                                          "drain, the job in training is checkpointed and handed back.")
    u.add_argument("--grpc-port", type=int, default=None, help="default 50051 (0: any free port)")
    u.add_argument("--http-port", type=int, default=None, help="default 8080 (0: any free port)")
    u.add_argument("--data-dir", type=Path, default=None, help="bundles, uploads, work folders, jobs.db "
                                                               "(default ./data)")
    u.add_argument("--host", default=None, help="interface to listen on (default 0.0.0.0)")
    u.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="the worker's training device")
    u.add_argument("--worker-metrics-port", type=int, default=0,
                   help="serve the worker's Prometheus metrics on this port (default: none)")
    u.set_defaults(fn=cmd_up)

    _add_worker(p.commands)
    from .jobs_client import add_commands as add_jobs_commands

    add_jobs_commands(p.commands)  # `blendsplat jobs ...`: the training jobs' REST client

    b = p.bench_commands.add_parser("stream", help="drive a running service over gRPC: fps and pose-to-frame "
                                                   "latency per stream")
    b.add_argument("--target", required=True, help="HOST:PORT of the gRPC server")
    b.add_argument("--avatar", required=True, help="avatar id")
    b.add_argument("--streams", type=int, default=1)
    b.add_argument("--seconds", type=float, default=10.0, help="measured time (after the warm-up)")
    b.add_argument("--warmup", type=float, default=1.0, help="seconds streamed first and not counted")
    b.add_argument("--fps", type=float, default=30.0, help="poses sent per second per stream")
    b.add_argument("--size", type=int, default=512)
    b.add_argument("--codec", choices=sorted(CODECS), default="jpeg")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--no-ack", action="store_true", help="readers that never acknowledge a frame (flow control)")
    b.add_argument("--metrics-url", default=None,
                   help="the server's /metrics URL: report its resident memory before and at the end")
    b.add_argument("--json", action="store_true", help="one JSON line")
    b.set_defaults(fn=cmd_bench_stream)

    b = p.bench_commands.add_parser("load", help="cold and warm load of a bundle from a store to its first frame: "
                                                 "milliseconds per stage, resident memory, full verification")
    b.add_argument("--bundle", required=True, type=Path)
    b.add_argument("--size", type=int, default=512, help="the first frame's width and height")
    b.add_argument("--backend", default=None, help="renderer backend (default: the service's default)")
    b.add_argument("--threads", type=int, default=0, help="native threads (0: all)")
    b.add_argument("--vs-v1", action="store_true", help="also the same avatar as a schema-1 (dense) bundle")
    b.add_argument("--json", action="store_true", help="one JSON line")
    b.set_defaults(fn=cmd_bench_load)
    return p


def main(argv: list[str] | None = None) -> int:
    return core_cli.main(argv, build_parser())


if __name__ == "__main__":
    sys.exit(main())
