"""The track stage of a job from a video upload: the video becomes a tracked dataset in the job's work folder, and
the rest of the job (train, evaluate, commit: :class:`~service.jobs.run.JobRun`) trains on it as on an uploaded one.

:func:`tracked_dataset` runs :func:`render_core.tracking.track.track_video` (the built-in CPU tracker, the open head
fitted) on the upload's video with ``crop="auto"`` at :func:`tracking_size`: the job's ``resolution``, else the
video's short side, at most :data:`DEFAULT_SIZE` (never larger than the short side: upsampling adds no detail). The
work folder gets::

    tracked/          the dataset (tracked-video format) the job trains on, with the tracker's contact_sheet.png
    overlay.png       that contact sheet: detected (red) and fitted (green) points on a few frames (artefact
                      "overlay")
    dataset.tar.gz    the tracked dataset as an archive (one top-level folder "dataset"; artefact "dataset"): an
                      upload of its own, as it is
    track.json        the tracker's report (frames kept, dropped runs with reasons, interpolated frames, the
                      reprojection error, timings; artefact "track-report"), written last and atomically: it marks
                      the stage complete

**Resumable.** A job whose work folder holds ``track.json`` and the dataset (an earlier attempt tracked it, then the
worker died or handed the job back) skips tracking and says so in a ``log`` event; anything else an interrupted
stage left is removed and the stage runs again. **Progress**: a ``progress`` event with ``stage: "track"`` at each of
the tracker's steps (``step``: ``start``, ``landmarks``, ``fit``, ``write``, ``done``, or ``other`` for a message of
the tracker this version does not know; ``message``); training's
progress events carry ``stage: "train"``. Each step first looks at the job's row: a cancel or a shutdown stops the
stage there (:class:`TrackInterrupted`), a lost lease raises :class:`~service.jobs.attempt.LeaseLost`.

**Bad input** fails the job with the tracker's named error (``TrackingError: <field>: ...``, e.g. ``face: no face
found in any of the 40 frames``, ``video: ... the stream is corrupt at frame 12``), as does a video in which fewer
than :data:`~service.jobs.video.MIN_VIDEO_FRAMES` frames keep a face; what the stage wrote is removed. Frames without
a face are interpolated when the gap is short and dropped otherwise (the tracker's rule); a ``log`` event reports
both, and several faces in view when the tracker's report counts them (it tracks the largest).
"""

from __future__ import annotations

import json
import shutil
import tarfile
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from render_core.atomic import atomic_path
from render_core.data.portable import MANIFEST

from ..errors import redact
from .attempt import LeaseLost
from .models import EventKind
from .video import MIN_VIDEO_FRAMES, video_limits

if TYPE_CHECKING:
    from .run import JobRun
    from .uploads import Upload

TRACKED = "tracked"
OVERLAY = "overlay.png"
DATASET_ARCHIVE = "dataset.tar.gz"
TRACK_REPORT = "track.json"
SHEET = "contact_sheet.png"  # what the tracker writes into its dataset folder
DEFAULT_SIZE = 512
STEPS = ("start", "landmarks", "fit", "write", "done", "other")  # a track progress event's step
_LEFTOVERS = (TRACKED, OVERLAY, DATASET_ARCHIVE, TRACK_REPORT)


class TrackInterrupted(Exception):
    """A cancel or a shutdown was noticed while the video was tracked: the stage stopped (nothing of it kept)."""


def tracking_size(width: int, height: int, resolution: int | None) -> int:
    """The square crop a ``width`` x ``height`` video is tracked at for a job's ``resolution`` (module docstring)."""
    short = max(1, min(int(width), int(height)))
    return max(16, min(resolution or DEFAULT_SIZE, short))


def is_tracked(workdir: Path) -> bool:
    """Whether an earlier attempt completed the stage in ``workdir``."""
    return (workdir / TRACK_REPORT).is_file() and (workdir / TRACKED / MANIFEST).is_file()


def clear(workdir: Path) -> None:
    """Remove what the stage writes (and what an interrupted one left: the tracker's temporary folders)."""
    for name in _LEFTOVERS:
        path = workdir / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)
    if workdir.is_dir():
        for p in workdir.iterdir():
            if not p.name.startswith(tuple(f".{name}." for name in _LEFTOVERS)):
                continue
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)


def tracked_dataset(run: JobRun, video: Path, upload: Upload, resolution: int | None) -> Path:
    """The tracked dataset of the job's video: an earlier attempt's, or tracked now (module docstring)."""
    workdir = run.workdir
    if is_tracked(workdir):
        run.event(EventKind.LOG, {"message": "the video was tracked by an earlier attempt: not tracked again",
                                  "stage": "track", "resumed": True})
        return workdir / TRACKED
    clear(workdir)
    size = tracking_size(upload.width, upload.height, resolution)
    run.event(EventKind.PROGRESS, _step("start", f"tracking the video ({upload.width}x{upload.height}, "
                                                 f"{upload.frames} frames) at {size}x{size}", size=size))
    try:
        report = _track(run, video, workdir, size)
    except LeaseLost:
        raise  # the folder may be another worker's by now: touch nothing
    except BaseException:
        clear(workdir)
        raise
    run.event(EventKind.PROGRESS, _step("done", _summary(report), frames_kept=report.get("frames_kept")))
    for message in _notes(report):
        run.event(EventKind.LOG, {"message": message, "stage": "track"})
    return workdir / TRACKED


def _track(run: JobRun, video: Path, workdir: Path, size: int) -> dict[str, Any]:
    from render_core.tracking.track import track_video

    out = workdir / TRACKED
    s = run.worker.settings
    report = track_video(video, out, size=size, crop="auto", threads=None, progress=_progress(run),
                         limits=video_limits(s.max_video_seconds, s.max_video_side, s.max_video_frames),
                         min_frames=MIN_VIDEO_FRAMES)  # fewer frames with a face: the tracker's "too short"
    _check(run)
    if (out / SHEET).is_file():
        with atomic_path(workdir / OVERLAY) as tmp:
            shutil.copyfile(out / SHEET, tmp)
    with atomic_path(workdir / DATASET_ARCHIVE) as tmp, tarfile.open(tmp, "w:gz", compresslevel=1) as tar:
        tar.add(out, arcname="dataset")  # the frames are PNG already: light compression
    report = {k: v for k, v in report.items() if k != "out"}  # a server path
    with atomic_path(workdir / TRACK_REPORT) as tmp:
        tmp.write_text(json.dumps(report, indent=2, default=str) + "\n", encoding="utf-8")
    return report


def _check(run: JobRun) -> None:
    """Between steps: LeaseLost when the job is no longer ours, TrackInterrupted on a cancel or a shutdown."""
    if run.attempt.should_stop():
        raise TrackInterrupted(run.job.id)


_SAYS = {"landmarks": "finding the face and its landmarks in every frame ({})",
         "fit": "fitting the head to the landmarks ({})", "write": "writing the dataset: crops, head masks, tracking"}


def _progress(run: JobRun) -> Callable[[str], None]:
    """The tracker's ``progress``: each step (``"<step>: <detail>"``) looked at (:func:`_check`) and recorded."""

    def on_progress(text: str) -> None:
        _check(run)
        step, _, detail = str(text).partition(":")
        step, detail = step.strip(), detail.strip()
        if step in _SAYS:  # our words: the tracker's name paths
            message = _SAYS[step].format(detail)
        else:
            step, message = "other", redact(str(text))[:300]
        run.event(EventKind.PROGRESS, _step(step, message))

    return on_progress


def _step(step: str, message: str, **extra: Any) -> dict[str, Any]:
    return {"stage": "track", "step": step, "message": message, **extra}


def _summary(report: dict[str, Any]) -> str:
    dropped = (report.get("frames_dropped") or {}).get("count", 0)
    return (f"tracked {report.get('frames_kept')} frames at {report.get('size')}x{report.get('size')} "
            f"({dropped} dropped, {report.get('interpolated', 0)} interpolated; reprojection error "
            f"{report.get('reprojection_px')} px)")


def _notes(report: dict[str, Any]) -> list[str]:
    """What the user should know about the tracking: several faces, frames interpolated, stretches dropped."""
    notes = []
    faces = report.get("max_faces")
    if not isinstance(faces, int) and isinstance(report.get("faces"), dict):
        faces = report["faces"].get("max")
    if isinstance(faces, int) and faces > 1:
        notes.append(f"{faces} faces were in view at once: the largest was tracked")
    if report.get("interpolated"):
        notes.append(f"{report['interpolated']} frames without a face were interpolated (short gaps)")
    for run in (report.get("frames_dropped") or {}).get("runs") or []:
        if isinstance(run, dict):
            notes.append(f"frames {run.get('start')} to {run.get('end')} dropped: {run.get('reason')}")
    return notes[:20]
