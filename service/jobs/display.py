"""What ``blendsplat jobs`` shows people (:mod:`service.jobs.cli`): the live view on stderr while it follows a job
(:class:`Watch`: state lines, a bar of iterations with loss, PSNR and ETA), the upload's byte bar
(:class:`UploadBar`), a job's short summary (:func:`summary`) and the jobs' table (:func:`job_table`) on stdout, and
the one line an error of the client (``blendsplat_client``) is shown as (:func:`error_text`). Bars only when stderr
is a terminal.
"""

from __future__ import annotations

import sys
from datetime import UTC, datetime
from typing import Any

from blendsplat_client import BlendsplatError, Event
from blendsplat_client.errors import ConnectionFailed

TERMINAL = frozenset({"succeeded", "failed", "cancelled"})


class Watch:
    """What a command shows on stderr while it follows a job: one line per state change and, when stderr is a
    terminal (or ``bars`` is set), a tqdm bar of iterations with the loss, PSNR and the server's ETA.

    An event stream starts with the job's history: events recorded before the job as first read (its
    ``updated_at``) are counted but not shown again; the first read already showed where the job is."""

    def __init__(self, job_id: str, bars: bool | None = None, stream=None):
        self.job_id, self.stream = job_id, stream or sys.stderr
        self.bars = self.stream.isatty() if bars is None else bars
        self.bar = None
        self.state: str | None = None
        self.postfix: dict[str, str] = {}  # the latest of each figure (a report may carry only some)
        self.events = self.polls = 0
        self.since: datetime | None = None

    def _say(self, text: str) -> None:
        if self.bar is not None:
            self.bar.write(text, file=self.stream)
        else:
            print(text, file=self.stream, flush=True)

    def _state(self, state: str | None, error: str | None = None) -> None:
        if state and state != self.state:
            self.state = state
            self._say(f"job {self.job_id}: {state}" + (f" ({error})" if error else ""))

    def _progress(self, p: dict[str, Any]) -> None:
        total, done = p.get("total_iterations"), p.get("iteration")
        if not self.bars or not isinstance(total, int) or total < 1 or not isinstance(done, int):
            return
        if self.bar is None:
            from tqdm import tqdm

            self.bar = tqdm(total=total, initial=0, desc="train", unit="it", file=self.stream, dynamic_ncols=True,
                            bar_format="{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}{postfix}]")
        if self.bar.total != total:
            self.bar.total = total
        postfix = self.postfix
        if isinstance(p.get("loss"), int | float):
            postfix["loss"] = f"{p['loss']:.4f}"
        if isinstance(p.get("psnr"), int | float):
            postfix["psnr"] = f"{p['psnr']:.2f}"
        if isinstance(p.get("eta_seconds"), int | float):
            postfix["eta"] = _duration(p["eta_seconds"])
        elif done >= total:
            postfix["eta"] = _duration(0)
        if isinstance(p.get("gaussians"), int):
            postfix["gaussians"] = str(p["gaussians"])
        self.bar.set_postfix(postfix, refresh=False)
        self.bar.update(max(0, min(done, total)) - self.bar.n)

    def on_event(self, event: Event) -> None:
        self.events += 1
        recorded = _time(event.data.get("time"))
        if recorded is not None and self.since is not None and recorded <= self.since:
            return  # history the first read already summed up
        if event.event == "progress" and event.data.get("stage") == "track":
            if isinstance(event.data.get("message"), str):
                self._say(f"job {self.job_id}: tracking: {event.data['message']}")
        elif event.event == "progress":
            self._progress(event.data)
        elif event.event == "state":
            self._state(event.data.get("state"), event.data.get("error"))
        elif event.event == "log" and isinstance(event.data.get("message"), str):
            self._say(f"job {self.job_id}: {event.data['message']}")

    def on_job(self, job: dict[str, Any]) -> None:
        self.polls += 1
        if self.since is None:
            self.since = _time(job.get("updated_at"))
        if isinstance(job.get("progress"), dict):
            self._progress(job["progress"])
        self._state(job.get("state"))

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _time(value: Any) -> datetime | None:
    """An ISO 8601 time the server wrote, timezone-aware; None when it is not one."""
    if not isinstance(value, str):
        return None
    try:
        parsed = datetime.fromisoformat(value)
    except ValueError:
        return None
    return parsed if parsed.tzinfo is not None else parsed.replace(tzinfo=UTC)


def _duration(seconds: float) -> str:
    s = max(0, round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60:02d}:{s % 60:02d}"


class UploadBar:
    """Bytes sent of an upload: a tqdm bar on stderr when it is a terminal."""

    def __init__(self, total: int, name: str, stream=None):
        self.stream = stream or sys.stderr
        self.bar = None
        if self.stream.isatty():
            from tqdm import tqdm

            self.bar = tqdm(total=total, desc=f"upload {name}", unit="B", unit_scale=True, unit_divisor=1024,
                            file=self.stream, dynamic_ncols=True)

    def __call__(self, sent: int, total: int) -> None:
        """The client's upload progress: bytes sent so far of ``total``."""
        if self.bar is not None:
            self.bar.update(sent - self.bar.n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def summary(server: str, job: dict[str, Any]) -> str:
    """A few lines about a job for people: id, state, avatar, progress, PSNR, error, links (absolute: on
    ``server``, the base URL)."""

    def url(path: str) -> str:
        return server + path if path.startswith("/") else path

    spec = job.get("spec") or {}
    result = job.get("result") or {}
    progress = job.get("progress") or {}
    links = job.get("links") or {}
    lines = [f"job {job.get('id')}: {job.get('state')}"
             + (" (cancel requested)" if job.get("cancel_requested") and job.get("state") not in TERMINAL else "")]
    avatar = result.get("avatar_id") or spec.get("avatar_id")
    if avatar:
        lines.append(f"  avatar        {avatar}" + (f"  {url(links['avatar'])}" if links.get("avatar") else ""))
    lines.append(f"  preset        {spec.get('preset', '?')}, {spec.get('iterations') or 'default'} iterations")
    if progress.get("iteration") is not None:
        text = f"  progress      {progress.get('iteration')}/{progress.get('total_iterations') or '?'}"
        if isinstance(progress.get("loss"), int | float):
            text += f", loss {progress['loss']:.4f}"
        if isinstance(progress.get("psnr"), int | float):
            text += f", PSNR {progress['psnr']:.2f} dB"
        if isinstance(progress.get("eta_seconds"), int | float) and job.get("state") == "running":
            text += f", ETA {_duration(progress['eta_seconds'])}"
        lines.append(text)
    evaluation = result.get("evaluation") or {}
    if isinstance(evaluation.get("psnr"), int | float):
        text = f"  held-out      PSNR {evaluation['psnr']:.2f} dB"
        if isinstance(evaluation.get("ssim"), int | float):
            text += f", SSIM {evaluation['ssim']:.4f}"
        if isinstance(result.get("seconds"), int | float):
            text += f" ({result['seconds']:.1f} s of training)"
        lines.append(text)
    if job.get("error"):
        lines.append(f"  error         {job['error']}")
    if links.get("self"):
        lines.append(f"  job           {url(links['self'])}")
    for name in ("report", "contact-sheet"):
        if name in (links.get("artefacts") or {}):
            lines.append(f"  {name:<13} {url(links['artefacts'][name])}")
    return "\n".join(lines)


def job_table(jobs: list[dict[str, Any]]) -> list[str]:
    """Jobs as the lines of a table: id, state, progress, avatar, PSNR, creation time."""
    rows = [("ID", "STATE", "PROGRESS", "AVATAR", "PSNR", "CREATED")]
    for job in jobs:
        p = job.get("progress") or {}
        done = f"{p.get('iteration') or 0}/{p.get('total_iterations') or '?'}" if p.get("total_iterations") else ""
        psnr = p.get("psnr")
        rows.append((str(job.get("id")), str(job.get("state")), done, str((job.get("spec") or {}).get("avatar_id", "")),
                     f"{psnr:.2f}" if isinstance(psnr, int | float) else "",
                     str(job.get("created_at", ""))[:19].replace("T", " ")))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return ["  ".join(v.ljust(w) for v, w in zip(r, widths, strict=True)).rstrip() for r in rows]


def error_text(exc: BlendsplatError, server_env: str) -> str:
    """An error of the client as one line: an HTTP error answer as ``STATUS code: message (field F)``, a server
    that cannot be reached with a hint (``server_env``: the variable that names the server)."""
    if isinstance(exc, ConnectionFailed) and exc.message.startswith("cannot reach"):
        return f"{exc.message}; is it running (`blendsplat up`)? Point at another with --server or {server_env}"
    if exc.http_status is not None:
        where = f" (field {exc.field})" if exc.field else ""
        return f"{exc.http_status} {exc.status.code.lower()}: {exc.message}{where}"
    return exc.message
