"""The `blendsplat` command: render_core's commands plus `serve`, `worker`, `up`, `migrate`, `settings` and
`bench stream`."""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
from pathlib import Path

from render_core.tools import cli as core_cli

from .access import keys_cli


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
    from .jobs.worker import main as worker_main

    return worker_main(args)


def _add_worker(commands) -> None:
    """`blendsplat worker`: its options are service/jobs/worker.py's own (``add_arguments``), added when the command
    is parsed, so no other command imports the worker (or needs it to exist)."""
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
                from .jobs.worker import add_arguments
            except ImportError as e:
                w.error(f"the worker is unavailable: {e}")
            add_arguments(w)
            added.append(True)
        return parse(args, namespace)

    w.parse_known_args = parse_known_args


def cmd_bench_stream(args: argparse.Namespace) -> int:
    """The report as strict JSON on stdout; exit 1, with why on stderr, when no frame arrived (a server that cannot be
    reached is an error before any stream: ServerUnreachable, printed by the command's main)."""
    from .bench_stream import bench_stream

    result = asyncio.run(bench_stream(args.target, args.avatar, streams=args.streams, seconds=args.seconds,
                                      fps=args.fps, size=args.size, codec=args.codec, warmup=args.warmup,
                                      seed=args.seed, ack=not args.no_ack, metrics_url=args.metrics_url,
                                      api_key=args.api_key, drive=args.drive, verify_frames=args.verify))
    core_cli.emit(result, indent=None if args.json else 2)
    if result.get("server_rss_note"):
        print(f"blendsplat: note: server_rss_mb is null: {result['server_rss_note']}", file=sys.stderr)
    if not result["frames"]:
        reasons = "; ".join(result["error_messages"]) or "the server sent none"
        print(f"blendsplat: error: bench stream: no frames from {args.target} (avatar {args.avatar!r}): {reasons}",
              file=sys.stderr)
        return 1
    return 0


def cmd_bench_load(args: argparse.Namespace) -> int:
    from .bench_load import bench_load

    result = bench_load(args.bundle, size=args.size, backend=args.backend, threads=args.threads, vs_v1=args.vs_v1)
    core_cli.emit(result, indent=None if args.json else 2)
    return 0


def cmd_migrate(args: argparse.Namespace) -> int:
    """Upgrade the job database to the newest schema (Alembic), then exit: for a Kubernetes Job or init container
    that runs before new replicas start (serve and worker also migrate at start; concurrent runs are safe)."""
    from pydantic import ValidationError
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import SQLAlchemyError

    from .db import head, migrate, warn_if_sqlite_on_network_filesystem
    from .settings import Settings

    overrides = {k: v for k, v in (("data_dir", args.data_dir), ("jobs_url", args.jobs_url)) if v is not None}
    try:
        url = Settings(**overrides).jobs_database_url
    except ValidationError as e:
        print(f"blendsplat: error: invalid settings (environment BLENDSPLAT_* or options):\n{e}", file=sys.stderr)
        return 2
    shown = make_url(url).render_as_string(hide_password=True)
    warn_if_sqlite_on_network_filesystem(url)
    try:
        migrate(url)
    except SQLAlchemyError as e:
        print(f"blendsplat: error: migrating {shown}: {type(e).__name__}: {str(e)[:500]}", file=sys.stderr)
        return 1
    core_cli.emit({"database": shown, "revision": head()}, indent=None)
    return 0


SETTINGS_BEGIN = "<!-- settings-reference: begin (generated by `blendsplat settings --markdown`; do not edit) -->"
SETTINGS_END = "<!-- settings-reference: end -->"


def settings_reference() -> list[dict[str, str]]:
    """One row per field of :class:`service.settings.Settings`: its environment variable, type, default and
    description (what ``blendsplat settings`` prints)."""
    import typing

    from .settings import Settings

    def type_text(annotation) -> str:
        if typing.get_origin(annotation) is typing.Literal:
            return " | ".join(str(a) for a in typing.get_args(annotation))
        text = getattr(annotation, "__name__", None) if typing.get_origin(annotation) is None else None
        return {"Path": "path"}.get(text, text) if text else str(annotation).replace("pathlib.", "").replace(
            "Path", "path")

    rows = []
    for name, field in Settings.model_fields.items():
        default = field.get_default(call_default_factory=True)
        rows.append({"variable": f"{Settings.model_config.get('env_prefix', '')}{name}".upper(),
                     "type": type_text(field.annotation),
                     "default": "(unset)" if default is None else json.dumps(
                         str(default) if isinstance(default, Path) else default),
                     "description": field.description or ""})
    return rows


def settings_markdown() -> str:
    """The settings reference as a Markdown table between the README's markers."""
    def cell(text: str) -> str:
        return text.replace("|", "\\|").replace("\n", " ")

    lines = [SETTINGS_BEGIN, "| Variable | Type | Default | Description |", "| --- | --- | --- | --- |"]
    lines += [f"| `{r['variable']}` | {cell(r['type'])} | `{cell(r['default'])}` | {cell(r['description'])} |"
              for r in settings_reference()]
    return "\n".join([*lines, SETTINGS_END]) + "\n"


def cmd_settings(args: argparse.Namespace) -> int:
    if args.update is not None:
        text = args.update.read_text()
        if SETTINGS_BEGIN not in text or SETTINGS_END not in text:
            print(f"blendsplat: error: {args.update} has no settings reference markers", file=sys.stderr)
            return 2
        head_, rest = text.split(SETTINGS_BEGIN, 1)
        args.update.write_text(head_ + settings_markdown().rstrip("\n") + rest.split(SETTINGS_END, 1)[1])
        return 0
    print(settings_markdown() if args.markdown else core_cli.dumps(settings_reference()), end="")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from .bench_drive import DRIVES
    from .bench_stream import CODECS
    from .settings import Settings

    p = core_cli.build_parser()
    keys_cli.add_parser(p.commands)
    s = p.commands.add_parser("serve", help="run the streaming render service (gRPC + HTTP) until SIGTERM",
                              description="Settings come from BLENDSPLAT_* environment variables "
                                          "(see service/settings.py); these options override them.")
    s.add_argument("--grpc-port", type=int, default=None, help="default 50051 (0: any free port)")
    s.add_argument("--http-port", type=int, default=None, help="default 8080 (0: any free port)")
    s.add_argument("--data-dir", type=Path, default=None, help="bundle store root (default ./data)")
    s.add_argument("--host", default=None, help="interface to listen on (default: BLENDSPLAT_HOST, else 127.0.0.1, "
                                                "this machine only; 0.0.0.0: every interface)")
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
    u.add_argument("--host", default=None, help="interface to listen on (default: BLENDSPLAT_HOST, else 127.0.0.1, "
                                                "this machine only; 0.0.0.0: every interface)")
    u.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="the worker's training device")
    u.add_argument("--worker-metrics-port", type=int, default=0,
                   help="serve the worker's Prometheus metrics on this port (default: none)")
    u.set_defaults(fn=cmd_up)

    _add_worker(p.commands)

    m = p.commands.add_parser("migrate", help="upgrade the job database to the newest schema and exit",
                              description="Runs the job database's Alembic migrations (BLENDSPLAT_JOBS_URL, default "
                                          "the SQLite file <data-dir>/jobs.db) to head: for a Kubernetes Job or init "
                                          "container before a rollout. Idempotent; safe to run concurrently.")
    m.add_argument("--data-dir", type=Path, default=None, help="default: BLENDSPLAT_DATA_DIR or ./data")
    m.add_argument("--jobs-url", default=None, help="job database URL (default: BLENDSPLAT_JOBS_URL or the SQLite "
                                                   "file <data-dir>/jobs.db)")
    m.set_defaults(fn=cmd_migrate)

    c = p.commands.add_parser("settings", help="the settings reference: every BLENDSPLAT_* variable, its type, "
                                               "default and meaning")
    c.add_argument("--markdown", action="store_true", help="as the Markdown table of the README (default: JSON)")
    c.add_argument("--update", type=Path, default=None, metavar="FILE",
                   help="rewrite the table between the settings-reference markers of FILE (e.g. README.md)")
    c.set_defaults(fn=cmd_settings)
    from .jobs.cli import add_commands as add_jobs_commands

    add_jobs_commands(p.commands)  # `blendsplat jobs ...`: the training jobs' REST client

    b = p.bench_commands.add_parser("stream", help="drive a running service over gRPC: fps and pose-to-frame "
                                                   "latency per stream")
    b.add_argument("--target", default=f"127.0.0.1:{Settings.model_fields['grpc_port'].default}",
                   help="HOST:PORT of the gRPC server (default: the server's default, %(default)s)")
    b.add_argument("--avatar", required=True, help="avatar id")
    b.add_argument("--streams", type=int, default=1)
    b.add_argument("--seconds", type=float, default=10.0, help="measured time (after the warm-up)")
    b.add_argument("--warmup", type=float, default=1.0, help="seconds streamed first and not counted")
    b.add_argument("--fps", type=float, default=30.0, help="poses sent per second per stream")
    b.add_argument("--size", type=int, default=512)
    b.add_argument("--codec", choices=sorted(CODECS), default="jpeg")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--drive", choices=DRIVES, default="smooth",
                   help="the poses: smooth (default), each coefficient and joint angle a sinusoid under 2 Hz with "
                        "its own phase per stream, as a person moves; random, every frame drawn afresh")
    b.add_argument("--verify", type=int, default=0, metavar="N",
                   help="afterwards, render N of the streamed poses again cold (the Render RPC: one frame, no "
                        "stream state, every CPU-cost mechanism off, lossless PNG) and report psnr_vs_cold_db, the "
                        "lowest PSNR of a streamed frame against it; JPEG frames are compared with the cold render "
                        "JPEG-encoded as the server encodes it, so identical pixels give 100 dB and the figure "
                        "shows what the mechanisms change, not what JPEG loses (that is verify.psnr_vs_lossless_db)"
                        "; not for h264")
    b.add_argument("--no-ack", action="store_true", help="readers that never acknowledge a frame (flow control)")
    b.add_argument("--metrics-url", default=None,
                   help="the server's /metrics URL, read for its resident memory before and at the end "
                        "(server_rss_mb; default: http://<target host>:"
                        f"{Settings.model_fields['http_port'].default}/metrics, the default HTTP port)")
    b.add_argument("--json", action="store_true", help="one JSON line")
    b.add_argument("--api-key", default=os.environ.get("BLENDSPLAT_API_KEY"),
                   help="API key with the render scope (default: the environment variable BLENDSPLAT_API_KEY)")
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
    from .bench_webrtc import add_parser as add_bench_webrtc

    add_bench_webrtc(p.bench_commands)  # `blendsplat bench webrtc` (service/bench_webrtc.py)
    _add_live_command(p.commands)
    return p


def cmd_live(args: argparse.Namespace) -> int:
    """`blendsplat live`: a driving file played over WebRTC (service/live.py); the report as JSON."""
    import logging

    from render_core.errors import FrameError

    from .live import live
    from .webrtc.client import ClientError

    for name in ("aioice", "aiortc", "httpx"):  # their per-connection lines are not this command's output
        logging.getLogger(name).setLevel(logging.WARNING)
    try:
        report = asyncio.run(live(args.url, args.avatar, args.drive, out=args.out, size=args.size, fps=args.fps,
                                  codec=args.codec, api_key=args.api_key, loops=args.loops, verify=args.verify))
    except (ClientError, FrameError, OSError) as e:
        raise SystemExit(f"blendsplat: error: live: {e}") from None
    core_cli.emit(report, indent=None if args.json else 2)
    return 0 if report["frames"] else 1


def _add_live_command(commands) -> None:
    c = commands.add_parser("live", help="play a driving file to an avatar over WebRTC; write what comes back as "
                                         "an MP4 and report pose-to-frame latency")
    c.add_argument("--url", required=True, help="the service's HTTP URL, e.g. http://127.0.0.1:8080")
    c.add_argument("--avatar", required=True, help="avatar id")
    c.add_argument("--drive", required=True, type=Path, help="driving file (JSON lines, docs/method.md section 11)")
    c.add_argument("--out", type=Path, default=None, help="write the received video here (MP4, H.264)")
    c.add_argument("--size", type=int, default=512)
    c.add_argument("--fps", type=float, default=30.0, help="poses sent per second")
    c.add_argument("--codec", choices=("h264,vp8", "h264", "vp8"), default="h264,vp8")
    c.add_argument("--loops", type=int, default=1, help="play the file this many times")
    c.add_argument("--verify", type=int, default=0, help="afterwards, compare this many received frames with the "
                                                          "same poses rendered as PNG (psnr_db)")
    c.add_argument("--json", action="store_true", help="one JSON line")
    c.add_argument("--api-key", default=os.environ.get("BLENDSPLAT_API_KEY"),
                   help="API key with the render scope (default: the environment variable BLENDSPLAT_API_KEY)")
    c.set_defaults(fn=cmd_live)


def main(argv: list[str] | None = None) -> int:
    return core_cli.main(argv, build_parser())


if __name__ == "__main__":
    sys.exit(main())
