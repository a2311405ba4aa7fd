"""`blendsplat jobs submit | list | show | cancel | wait | delete`: a command-line client of the training jobs' REST
API (service/jobs/api.py) over the Python client package, ``blendsplat_client`` (clients/python: the HTTP calls,
retries of idempotent ones, the event stream with its polling fallback, typed errors); here are the commands'
side: arguments, checking and packing a dataset folder, progress bars, the printed results, exit codes.

Conventions (docs/architecture.md): results go to stdout (the job's JSON with ``--json``, else a short summary);
progress bars (tqdm, only when stderr is a terminal), state changes and errors go to stderr. Exit codes: 0
success (``submit --wait`` / ``wait``: the job succeeded), 1 the job failed or was cancelled, 2 a usage,
connection, HTTP or timeout error, 130 waiting interrupted by Ctrl-C (the job goes on). The API key is sent as
``Authorization: Bearer KEY`` and never printed nor put in a URL.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
import tarfile
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from blendsplat_client import BlendsplatError, Client, RetryPolicy, errors

from .display import TERMINAL, UploadBar, Watch, error_text, job_table, summary

DEFAULT_SERVER = "http://127.0.0.1:8080"
SERVER_ENV, KEY_ENV = "BLENDSPLAT_SERVER", "BLENDSPLAT_API_KEY"
STATES = ("queued", "running", "succeeded", "failed", "cancelled")
ARCHIVE_SUFFIXES = (".tar.gz", ".tgz", ".tar", ".zip")
VIDEO_SUFFIXES = (".mp4", ".m4v", ".mov", ".webm", ".mkv")  # a video the server tracks (it sniffs the content)
RETRY = RetryPolicy(attempts=3)  # idempotent calls (reads, the keyed create): two more tries, under 2 s
EXIT_OK, EXIT_JOB, EXIT_ERROR, EXIT_INTERRUPTED = 0, 1, 2, 130


class CliError(Exception):
    """What stops a command before the server has a say (a wrong argument, not a dataset): exit 2."""


def _client(args: argparse.Namespace) -> Client:
    server = args.server or os.environ.get(SERVER_ENV) or DEFAULT_SERVER
    key = args.api_key if args.api_key is not None else os.environ.get(KEY_ENV, "")
    try:
        return Client(server, api_key=key, retry=RETRY)
    except ValueError as exc:  # the URL or the key
        raise CliError(str(exc).replace("the server URL", "--server")) from None


def check_dataset(folder: Path) -> None:
    """Check a tracked-video dataset folder (docs/tracked-video-format.md) before it is packed: the manifest and
    tracking fully, the frame and mask files for existence (the server decodes every one); CliError naming the
    problem."""
    from render_core.data.portable import read_dataset
    from render_core.errors import DatasetError

    if not (folder / "dataset.json").is_file():
        raise CliError(f"{folder} is not a tracked-video dataset: it has no dataset.json "
                       "(docs/tracked-video-format.md; `blendsplat data convert` makes one)")
    try:
        read_dataset(folder)
    except DatasetError as exc:
        raise CliError(f"{folder} is not a valid tracked-video dataset: {exc}") from None


def pack_dataset(folder: Path, out: Path) -> None:
    """Pack a tracked-video dataset folder into a .tar.gz on disk, the dataset in one top-level folder; checked
    first (:func:`check_dataset`)."""
    check_dataset(folder)
    with tarfile.open(out, "w:gz", compresslevel=3, dereference=True) as tar:  # frames are PNG: little to gain
        tar.add(folder, arcname=folder.resolve().name or "dataset",
                filter=lambda m: m if (m.isfile() or m.isdir()) else None)


def _print_json(obj: Any) -> None:
    from render_core.tools.cli import emit

    emit(obj)  # strict JSON, as every command's


def _show(client: Client, job: dict[str, Any], as_json: bool) -> None:
    if as_json:
        _print_json(job)
    else:
        sys.stdout.write(summary(client.settings.url, job) + "\n")
        sys.stdout.flush()


def _resume_hint(args: argparse.Namespace, job_id: str) -> str:
    extra = f" --server {args.server}" if args.server else ""
    return f"blendsplat jobs wait {job_id}{extra}"


def _ended(job: dict[str, Any], want: str = "succeeded") -> int:
    """The exit code of a job that ended: 0 when it ended ``want``, else 1 (why on stderr: the job's error)."""
    state = job.get("state")
    if state == want:
        return EXIT_OK
    if want == "cancelled":
        print(f"blendsplat: error: job {job.get('id')} ended {state} before the cancel took effect",
              file=sys.stderr, flush=True)
    else:
        reason = job.get("error") or ("cancel requested" if state == "cancelled" else "no reason given")
        print(f"blendsplat: error: job {job.get('id')} {state}: {reason}", file=sys.stderr, flush=True)
    return EXIT_JOB


def _wait(client: Client, args: argparse.Namespace, job_id: str, want: str = "succeeded") -> int:
    """Follow a job to its end, show it, and return the exit code (0: it ended ``want``)."""
    watch = Watch(job_id)
    try:
        job = client.wait(job_id, on_event=watch.on_event, on_job=watch.on_job, check=False,
                          timeout=getattr(args, "timeout", None))
    except KeyboardInterrupt:
        watch.close()
        state = f" ({watch.state})" if watch.state else ""
        print(f"\nstopped waiting; job {job_id} goes on{state}. Resume with: {_resume_hint(args, job_id)}",
              file=sys.stderr, flush=True)
        return EXIT_INTERRUPTED
    except errors.Timeout as exc:
        watch.close()
        raise CliError(f"{error_text(exc, SERVER_ENV)}; it goes on ({watch.state or 'not finished'}). Resume with: "
                       f"{_resume_hint(args, job_id)}") from None
    finally:
        watch.close()
    _show(client, job, args.json)
    return _ended(job, want)


def cmd_submit(args: argparse.Namespace) -> int:
    source: Path = args.source
    spec: dict[str, Any] = {"preset": args.preset, "avatar_id": args.avatar_id or _default_avatar_id(source)}
    for name in ("iterations", "resolution", "seed", "webhook_url"):
        if getattr(args, name) is not None:
            spec[name] = getattr(args, name)
    with _client(args) as client, tempfile.TemporaryDirectory(prefix="blendsplat-jobs-") as tmp:
        # What is quick first (the argument, the dataset's manifest), then the server (reachable, the key
        # accepted), and only then the slow part: packing a folder (seconds to minutes) and the upload.
        if source.is_dir():
            check_dataset(source)
        elif source.is_file():
            if not source.name.lower().endswith(ARCHIVE_SUFFIXES + VIDEO_SUFFIXES):
                raise CliError(f"{source} is neither a dataset folder, a .tar.gz, .tar or .zip archive, nor a "
                               "video (.mp4, .mov, .webm, .mkv)")
        else:
            raise CliError(f"{source}: no such dataset folder or archive")
        client.jobs_page(limit=1)  # the server answers the jobs API and accepts the key
        if source.is_dir():
            archive = Path(tmp) / f"{source.resolve().name or 'dataset'}.tar.gz"
            print(f"packing {source} ...", file=sys.stderr, flush=True)
            pack_dataset(source, archive)
        else:
            archive = source
        bar = UploadBar(archive.stat().st_size, archive.name)
        try:
            upload = client.upload(archive, progress=bar)
        finally:
            bar.close()
        upload_id = upload.get("upload_id")
        if not isinstance(upload_id, str):
            raise CliError("the server's upload answer has no upload_id")
        print(f"uploaded {upload.get('frames', '?')} frames of {upload.get('width', '?')}x{upload.get('height', '?')}"
              f" as {upload_id}", file=sys.stderr, flush=True)
        job = client.submit_job(upload_id, **spec)  # with a fresh Idempotency-Key: retried, never made twice
        job_id = job.get("id")
        if not isinstance(job_id, str):
            raise CliError("the server's job answer has no id")
        if not args.wait:
            _show(client, job, args.json)
            return EXIT_OK
        print(f"job {job_id} submitted; following it (Ctrl-C stops waiting, not the job)", file=sys.stderr,
              flush=True)
        return _wait(client, args, job_id)


def _default_avatar_id(source: Path) -> str:
    """The avatar id from the dataset's name: letters, digits, ``-`` and ``_`` (what the bundle store accepts)."""
    name = source.name
    for suffix in ARCHIVE_SUFFIXES + VIDEO_SUFFIXES:
        if name.lower().endswith(suffix):
            name = name[: -len(suffix)]
            break
    cleaned = "".join(c if c.isascii() and (c.isalnum() or c in "-_") else "-" for c in name).strip("-_")
    return cleaned[:64] or "avatar"


def cmd_list(args: argparse.Namespace) -> int:
    with _client(args) as client:
        jobs: list[dict[str, Any]] = []
        cursor = None
        while len(jobs) < args.limit:
            page = client.jobs_page(args.state, min(500, args.limit - len(jobs)), cursor)
            jobs += page.get("jobs") or []
            cursor = page.get("next_cursor")
            if not cursor:
                break
        if args.json:
            _print_json({"jobs": jobs, "next_cursor": cursor})
            return EXIT_OK
        if not jobs:
            sys.stdout.write("no jobs\n" if not args.state else f"no {args.state} jobs\n")
            return EXIT_OK
        sys.stdout.write("".join(line + "\n" for line in job_table(jobs)))
        if cursor:
            sys.stdout.write(f"(more: --limit {args.limit + 50})\n")
        return EXIT_OK


def cmd_show(args: argparse.Namespace) -> int:
    with _client(args) as client:
        _show(client, client.get_job(args.id), args.json)
        return EXIT_OK


def cmd_cancel(args: argparse.Namespace) -> int:
    with _client(args) as client:
        job = client.cancel_job(args.id)
        state = job.get("state")
        if args.wait and state not in TERMINAL:
            print(f"job {args.id}: cancel requested; it stops before its next iteration", file=sys.stderr,
                  flush=True)
            return _wait(client, args, args.id, want="cancelled")
        _show(client, job, args.json)
        if args.wait:
            return _ended(job, want="cancelled")
        if state in TERMINAL and state != "cancelled":
            print(f"job {args.id} had already {state}: nothing to cancel", file=sys.stderr, flush=True)
        return EXIT_OK


def cmd_wait(args: argparse.Namespace) -> int:
    with _client(args) as client:
        return _wait(client, args, args.id)


def cmd_delete(args: argparse.Namespace) -> int:
    with _client(args) as client:
        client.delete_job(args.id)
        if args.json:
            _print_json({"id": args.id, "deleted": True})
        else:
            sys.stdout.write(f"deleted job {args.id}\n")
        return EXIT_OK


def _run(fn: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """A command with the client's error handling: an error (the client's, a usage error, a file that cannot be
    read) -> its message on stderr, exit 2."""

    def run(args: argparse.Namespace) -> int:
        if not getattr(args, "verbose", False):
            logging.getLogger("httpx").setLevel(logging.WARNING)  # no line per request
            logging.getLogger("httpcore").setLevel(logging.WARNING)
        try:
            return fn(args)
        except BlendsplatError as exc:
            print(f"blendsplat: error: {error_text(exc, SERVER_ENV)}", file=sys.stderr, flush=True)
            return EXIT_ERROR
        except (CliError, OSError) as exc:
            print(f"blendsplat: error: {exc}", file=sys.stderr, flush=True)
            return EXIT_ERROR
        except KeyboardInterrupt:
            print("\nblendsplat: interrupted", file=sys.stderr, flush=True)
            return EXIT_INTERRUPTED

    run.__name__ = fn.__name__
    return run


def _positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _job_id(text: str) -> str:
    if not text or not text.isprintable():
        raise argparse.ArgumentTypeError(f"not a job id: {text!r}")
    return text


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds, got {text!r}") from None
    if not value > 0 or not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a positive number of seconds, got {text!r}")
    return value


EPILOG = ("exit status: 0 success (submit --wait, wait: the job succeeded), 1 the job failed or was cancelled, "
          "2 a usage, connection, HTTP or timeout error, 130 Ctrl-C while waiting (the job goes on)")


def add_commands(commands) -> None:
    """Register ``blendsplat jobs ...`` on the ``blendsplat`` parser's subcommands."""
    common = argparse.ArgumentParser(add_help=False)
    c = common.add_argument_group("common options")
    c.add_argument("--server", default=None, metavar="URL",
                   help=f"the service's base URL (default: ${SERVER_ENV}, else {DEFAULT_SERVER})")
    c.add_argument("--api-key", default=None, metavar="KEY",
                   help=f"API key, sent as 'Authorization: Bearer KEY' (default: ${KEY_ENV})")
    c.add_argument("--json", action="store_true", help="print the JSON result (the job: with id and state) on "
                                                       "stdout")

    jobs = commands.add_parser("jobs", help="training jobs on a Blendsplat service: submit, list, show, cancel, "
                                            "wait, delete",
                               description="A client of the training jobs' REST API (/v1/uploads, /v1/jobs). "
                                           "Results go to stdout; progress bars (when stderr is a terminal), state "
                                           "changes and errors to stderr.", epilog=EPILOG)
    sub = jobs.add_subparsers(dest="jobs_command", required=True, metavar="COMMAND")

    def waiting(p: argparse.ArgumentParser) -> None:
        p.add_argument("--timeout", type=_seconds, default=None, metavar="S",
                       help="give up waiting after S seconds (exit 2; the job goes on)")

    s = sub.add_parser("submit", parents=[common], epilog=EPILOG, help="upload a dataset and start a training job",
                       description="Uploads DATASET (a tracked-video folder, docs/tracked-video-format.md, packed "
                                   "into a temporary .tar.gz; or a .tar.gz/.tar/.zip archive of one; or a video, "
                                   ".mp4/.mov/.webm/.mkv, which the job tracks first) with a progress "
                                   "bar, then creates the job (with an Idempotency-Key: a retry after a network "
                                   "error does not make a second job). With --wait, follows it to its end.")
    s.add_argument("source", type=Path, metavar="DATASET|ARCHIVE|VIDEO", help="dataset folder, archive or video")
    s.add_argument("--preset", choices=("tiny", "paper"), default="tiny",
                   help="tiny: minutes on a CPU; paper: the paper's 40k iterations (default tiny)")
    s.add_argument("--iterations", type=_positive, default=None, metavar="N", help="default: the preset's")
    s.add_argument("--avatar-id", default=None, metavar="ID",
                   help="the trained avatar's id in the bundle store (default: from the dataset's name)")
    s.add_argument("--resolution", type=_positive, default=None, metavar="PX",
                   help="longest image side to train at (default: the dataset's)")
    s.add_argument("--seed", type=int, default=None, help="training seed (default 0)")
    s.add_argument("--webhook-url", default=None, metavar="URL",
                   help="the server calls it on the job's state changes (where the server supports webhooks)")
    s.add_argument("--wait", action="store_true", help="follow the job until it ends; exit 0 only if it succeeded")
    waiting(s)
    s.set_defaults(fn=_run(cmd_submit))

    s = sub.add_parser("list", parents=[common], help="jobs, newest first",
                       description="Jobs, newest first (a table, or {jobs, next_cursor} with --json).")
    s.add_argument("--state", choices=STATES, default=None, help="only jobs in this state")
    s.add_argument("--limit", type=_positive, default=20, metavar="N", help="at most N jobs (default 20)")
    s.set_defaults(fn=_run(cmd_list))

    s = sub.add_parser("show", parents=[common], help="one job: state, progress, result, links",
                       description="One job: state, progress, error, result (avatar, held-out PSNR) and links.")
    s.add_argument("id", type=_job_id, help="the job's id (job_...)")
    s.set_defaults(fn=_run(cmd_show))

    s = sub.add_parser("cancel", parents=[common], epilog=EPILOG, help="cancel a job",
                       description="A queued job is cancelled at once; a running one stops before its next "
                                   "iteration. With --wait, follows it until it ends: exit 0 if it ended cancelled, "
                                   "1 if it ended otherwise first.")
    s.add_argument("id", type=_job_id, help="the job's id (job_...)")
    s.add_argument("--wait", action="store_true", help="wait until the job has stopped")
    waiting(s)
    s.set_defaults(fn=_run(cmd_cancel))

    s = sub.add_parser("wait", parents=[common], epilog=EPILOG, help="follow a job until it ends",
                       description="Follows a job with a progress bar (iteration, loss, PSNR, ETA) from its "
                                   "server-sent events, or by polling every second where the server has none. Exit "
                                   "0 if it succeeded, 1 if it failed or was cancelled. Ctrl-C stops waiting, not "
                                   "the job.")
    s.add_argument("id", type=_job_id, help="the job's id (job_...)")
    waiting(s)
    s.set_defaults(fn=_run(cmd_wait))

    s = sub.add_parser("delete", parents=[common], help="delete a job: its row, events and work folder",
                       description="Deletes a job whatever its state: its row, its events and its work folder "
                                   "(a running job stops before its next iteration and commits nothing).")
    s.add_argument("id", type=_job_id, help="the job's id (job_...)")
    s.set_defaults(fn=_run(cmd_delete))
