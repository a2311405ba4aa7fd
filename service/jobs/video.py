"""Video uploads: an ordinary video (MP4, MOV, WebM, MKV) taken as an upload beside the dataset archives, and
tracked into a dataset by the job that trains on it (:mod:`service.jobs.track`).

- **Sniffed by content, never by name** (:func:`sniff_video`): an ISO base media file (MP4, MOV: a box type at
  offset 4, ``ftyp`` for any modern file, ``moov``/``mdat``/``wide``/``free``/``skip``/``pnot`` for old QuickTime)
  or an EBML stream (WebM, MKV: ``1A 45 DF A3``). The upload store asks this before it treats the file as an
  archive, so a video named ``x.bin`` is a video and an archive named ``x.mp4`` an archive.
- **Probed, not decoded** (:func:`probe_upload`): the container's metadata against the limits (``max_video_seconds``,
  ``max_video_side``, ``max_video_frames`` in the settings) before any frame is decoded, then the first frame (the
  stream must decode, and its rotation gives the size as displayed), then every packet's timestamp (demuxed, not
  decoded: the real frame count and span against the same limits, so a file whose header lies is refused too; a
  file holding fewer frames than its container declares is refused as truncated). A 4K ten-minute file is refused
  from its header in milliseconds. Fewer than :data:`MIN_VIDEO_FRAMES` frames is refused as too short. A stream that
  is corrupt inside (bytes damaged, not missing) is found when the job decodes it: the job fails, naming the frame.
- Every refusal is one :class:`VideoError` (an ``InvalidArgument``: HTTP 422, ``field`` ``"file"``) whose
  ``reason`` is the tracker's field (``video``: not a video we read, or corrupt; ``duration``, ``resolution``,
  ``frames``: over a limit) or ``too_short``; the message names the problem and the limit, never a server path.

The same limits (:func:`video_limits`, a :class:`render_core.tracking.video.VideoLimits` from the settings) are
the tracker's when the job tracks the video, so an upload accepted here is never refused by the tracker later.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from render_core.errors import TrackingError

from ..errors import InvalidArgument

__all__ = ["CONTAINERS", "MIN_VIDEO_FRAMES", "VideoError", "VideoMeta", "probe_upload", "sniff_video",
           "tracker_limits", "video_limits"]

CONTAINERS = ("mp4", "mov", "webm", "mkv")
MIN_VIDEO_FRAMES = 10  # fewer is too short to train an avatar on
EBML_MAGIC = b"\x1a\x45\xdf\xa3"
_LEGACY_QUICKTIME = (b"moov", b"mdat", b"wide", b"free", b"skip", b"pnot")  # first boxes of pre-ftyp QuickTime files
_SNIFF_BYTES = 4096


class VideoError(InvalidArgument):
    """A video upload was refused: ``reason`` is ``video`` (not a video the tracker reads, or corrupt), ``duration``,
    ``resolution``, ``frames`` (over a limit) or ``too_short``; ``field`` is ``"file"``."""

    def __init__(self, problem: str, *, reason: str):
        self.problem, self.reason = problem, reason
        super().__init__(problem, field="file")


@dataclass(frozen=True)
class VideoMeta:
    """What a probe found: ``container`` (one of :data:`CONTAINERS`), ``codec``, ``width`` x ``height`` as displayed,
    ``fps`` (the frames' average rate), ``duration`` (seconds the frames span, one frame interval included) and
    ``frames`` (in the stream)."""

    container: str
    codec: str
    width: int
    height: int
    fps: float
    duration: float
    frames: int


def sniff_video(path: str | os.PathLike) -> str | None:
    """The container of the video at ``path`` from its first bytes (``mp4``, ``mov``, ``webm`` or ``mkv``), None
    when the bytes are not those of a video."""
    with open(path, "rb") as f:
        head = f.read(_SNIFF_BYTES)
    if head.startswith(EBML_MAGIC):
        return "webm" if b"webm" in head[:64] else "mkv"
    if len(head) < 12:
        return None
    if head[4:8] == b"ftyp":
        return "mov" if head[8:12] == b"qt  " else "mp4"
    if head[4:8] in _LEGACY_QUICKTIME and head[257:262] != b"ustar":  # never a tar whose first name has those bytes
        return "mov"
    return None


def tracker_limits():
    """The tracker's own :class:`~render_core.tracking.video.VideoLimits` (what the settings default to)."""
    from render_core.tracking.video import VideoLimits

    return VideoLimits()


def video_limits(seconds: float, side: int, frames: int):
    """The :class:`~render_core.tracking.video.VideoLimits` of the settings: an upload is checked against them, and
    the job's tracker applies them (module docstring)."""
    from render_core.tracking.video import VideoLimits

    return VideoLimits(seconds=float(seconds), long_side=int(side), frames=int(frames))


def _detail(exc: TrackingError, path: Path) -> str:
    """The tracker's message about the file at ``path``, saying "the video" for the stored file's name."""
    return str(exc.detail).replace(str(path), "the video").replace(path.name, "the video")


def probe_upload(path: str | os.PathLike, container: str, limits) -> VideoMeta:
    """Check the video at ``path`` (sniffed as ``container``) against ``limits`` (a
    :class:`~render_core.tracking.video.VideoLimits`) without decoding more than its first frame; its metadata.
    :class:`VideoError` for a refusal (module docstring)."""
    from render_core.tracking.video import average_rate, probe_video, scan_times

    path = Path(path)
    try:
        info = probe_video(path, limits)
        times, _ = scan_times(path, limits)
    except TrackingError as exc:
        reason = exc.field if exc.field in ("duration", "resolution", "frames") else "video"
        raise VideoError(_explained(reason, _detail(exc, path)), reason=reason) from None
    except MemoryError:
        raise
    except Exception as exc:  # PyAV on hostile bytes: whatever it raises is the file's fault
        raise VideoError(f"not a video the tracker reads (MP4, MOV, WebM, MKV): {type(exc).__name__}",
                         reason="video") from None
    rate = average_rate(times)
    if info.fps and abs(info.fps - rate) <= rate / 200:
        rate = info.fps  # the container's rate, when the frames agree with it
    frames = len(times)
    if info.frames and info.frames - frames > max(2, info.frames // 20):  # a few: packets an edit list discards
        raise VideoError(f"the video is truncated or corrupt: its container declares {info.frames} frames, the file "
                         f"holds {frames}", reason="video")
    if frames < MIN_VIDEO_FRAMES:
        raise VideoError(f"the video is too short: {frames} frame{'s' if frames != 1 else ''}, at least "
                         f"{MIN_VIDEO_FRAMES} are needed to train an avatar", reason="too_short")
    duration = float(times[-1] - times[0]) + (1.0 / float(rate) if rate else 0.0)
    return VideoMeta(container=container, codec=str(info.codec), width=int(info.width), height=int(info.height),
                     fps=round(float(rate), 3), duration=round(duration, 3), frames=frames)


_LIMIT_SETTINGS = {"duration": ("the video is too long", "BLENDSPLAT_MAX_VIDEO_SECONDS"),
                   "resolution": ("the video is too large", "BLENDSPLAT_MAX_VIDEO_SIDE"),
                   "frames": ("the video has too many frames", "BLENDSPLAT_MAX_VIDEO_FRAMES")}


def _explained(reason: str, detail: str) -> str:
    """The refusal's message: over a limit, what and which setting; else the tracker's own words."""
    if reason not in _LIMIT_SETTINGS:
        return detail
    what, setting = _LIMIT_SETTINGS[reason]
    return f"{what}: {detail} ({setting})"
