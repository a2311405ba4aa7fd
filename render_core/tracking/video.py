"""Stage 1: an ordinary video in - checked, decoded upright, at a constant frame rate.

:class:`VideoReader` takes an MP4/MOV (``mov`` demuxer) or WebM/MKV (``matroska`` demuxer) file - recognised by its
first bytes, never by its name: no other FFmpeg demuxer ever sees the file - and yields :class:`Frame` s (RGB uint8,
upright). In three steps, each refusing what it can as early as it can:

1. :func:`probe_video`: the container's metadata. Over a limit of :class:`VideoLimits` (duration, long side,
   frame count; defaults 5 minutes, 4096 pixels, 9000 frames) is a :class:`~render_core.errors.TrackingError` on
   ``duration``, ``resolution`` or ``frames`` before any frame is decoded. Then the first frame is decoded for the
   rotation: the display matrix (phones' portrait videos), else a legacy ``rotate`` tag (degrees clockwise), rounded
   to a multiple of 90 degrees and applied to every frame.
2. The timestamps: every packet of the stream is read (demuxed, not decoded) - the limits again, on the real count
   and span - and the output plan made: a constant-rate video (every interval within ``max(1 ms, 2 ticks)`` of the
   median) is passed through untouched at its own rate, unless another ``fps`` is asked; otherwise (a variable rate,
   or another rate asked) output frame k at time k / fps shows the source frame nearest in time (the earlier one on
   a tie), up to half an output interval past the last source frame: frames repeat or are skipped, never blended.
   The default rate is the source's: the container's average rate when the frames agree with it (within 0.5%),
   else (N - 1) frames over their span.
3. Decoding, frame by frame. Not a video (unrecognised bytes, no video stream, FFmpeg refusing it) is a
   TrackingError on ``video``; so is a stream that fails halfway (a decoding error, a frame the decoder flags as
   corrupt, or fewer frames than the packets promised), naming the frame.

Cropping to the training resolution is :mod:`.crop`.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np

from ..errors import TrackingError

MAGIC_MATROSKA = b"\x1a\x45\xdf\xa3"
MP4_BOXES = (b"ftyp", b"moov", b"mdat", b"free", b"wide", b"skip", b"pnot")
MAX_FPS = 240


@dataclass(frozen=True)
class VideoLimits:
    """What a video may be: at most ``seconds`` long, ``long_side`` pixels on its longer side, ``frames`` frames
    (after resampling, too)."""

    seconds: float = 300.0
    long_side: int = 4096
    frames: int = 9000


@dataclass(frozen=True)
class VideoInfo:
    """A video's metadata: ``width`` x ``height`` as displayed (after ``rotation``, degrees counter-clockwise applied
    to the decoded pictures: 0, 90, 180 or 270), the stream's average ``fps``, ``duration`` in seconds and ``frames``
    as the container declares them (None when it does not)."""

    path: str
    container: str
    codec: str
    width: int
    height: int
    rotation: int
    fps: Fraction
    duration: float | None
    frames: int | None


@dataclass(frozen=True)
class Frame:
    """Output frame ``index`` at ``time`` seconds (index / fps), showing source frame ``source`` (its index in
    presentation order) of time ``source_time`` (seconds from the first frame); ``rgb`` ``[H, W, 3]`` uint8 upright."""

    index: int
    time: float
    source: int
    source_time: float
    rgb: np.ndarray


def _sniff(path: Path) -> str:
    """The demuxer for ``path`` from its first bytes; not a video we read: TrackingError on ``video``."""
    try:
        with open(path, "rb") as f:
            head = f.read(12)
    except OSError as e:
        raise TrackingError(f"cannot read {path.name}: {e.strerror or e}", field="video") from None
    if head.startswith(MAGIC_MATROSKA):
        return "matroska"
    if len(head) >= 8 and head[4:8] in MP4_BOXES:
        return "mov"
    raise TrackingError(f"{path.name} is not a video this tracker reads (MP4, MOV, WebM or MKV)", field="video")


def _open(path: Path, demuxer: str):
    import av

    try:
        container = av.open(str(path), mode="r", format=demuxer)
    except Exception as e:  # PyAV raises many error types for hostile input
        raise TrackingError(f"{path.name} cannot be opened as a video: {_oneline(e)}", field="video") from None
    if not container.streams.video:
        container.close()
        raise TrackingError(f"{path.name} holds no video stream", field="video")
    return container


def _oneline(e: BaseException) -> str:
    return (" / ".join(s.strip() for s in str(e).splitlines() if s.strip()) or type(e).__name__)[:300]


def _check_limits(limits: VideoLimits, *, width: int = 0, height: int = 0, seconds: float | None = None,
                  frames: int | None = None, what: str = "the container declares") -> None:
    if max(width, height) > limits.long_side:
        raise TrackingError(f"{width}x{height} is over the limit of {limits.long_side} pixels on the long side",
                            field="resolution")
    if seconds is not None and seconds > limits.seconds:
        raise TrackingError(f"{what} {seconds:.1f} s, over the limit of {limits.seconds:g} s", field="duration")
    if frames is not None and frames > limits.frames:
        raise TrackingError(f"{what} {frames} frames, over the limit of {limits.frames}", field="frames")


def _rotation(frame, stream) -> int:
    """Degrees counter-clockwise to turn decoded pictures upright: the display matrix, else a ``rotate`` tag."""
    degrees = float(frame.rotation or 0)
    if degrees == 0:
        tags = {k.lower(): v for k, v in stream.metadata.items()}
        try:
            degrees = -float(tags.get("rotate", 0))  # the tag is clockwise
        except ValueError:
            degrees = 0.0
    return int(round(degrees / 90.0)) % 4 * 90


def probe_video(path: str | os.PathLike, limits: VideoLimits = VideoLimits()) -> VideoInfo:
    """The video's metadata, its limits checked before decoding anything but the first frame (module docstring)."""
    path = Path(path)
    demuxer = _sniff(path)
    container = _open(path, demuxer)
    try:
        stream = container.streams.video[0]
        ctx = stream.codec_context
        width, height = int(ctx.width or 0), int(ctx.height or 0)
        if stream.duration is not None and stream.time_base is not None:
            duration = float(stream.duration * stream.time_base)
        else:
            duration = container.duration / 1e6 if container.duration else None
        fps = stream.average_rate or stream.guessed_rate
        declared = int(stream.frames) if stream.frames else None
        estimated = declared or (int(duration * fps + 0.5) if duration and fps else None)
        _check_limits(limits, width=width, height=height, seconds=duration, frames=estimated)
        try:
            first = next(container.decode(stream), None)
        except Exception as e:
            raise TrackingError(f"{path.name}: the first frame does not decode: {_oneline(e)}", field="video") from None
        if first is None:
            raise TrackingError(f"{path.name}: the video stream holds no frame", field="video")
        rotation = _rotation(first, stream)
        if rotation in (90, 270):
            width, height = height, width
        return VideoInfo(str(path), demuxer, ctx.name, width, height, rotation, Fraction(fps or 0), duration, declared)
    finally:
        container.close()


def scan_times(path: str | os.PathLike, limits: VideoLimits = VideoLimits()) -> tuple[list[Fraction], Fraction]:
    """(The presentation times (seconds, exact) of every frame of the video stream, sorted; the stream's time base),
    from its packets alone (nothing decoded); the frame-count and duration limits checked as they come."""
    path = Path(path)
    container = _open(path, _sniff(path))
    times: list[Fraction] = []
    try:
        stream = container.streams.video[0]
        tb = stream.time_base
        try:
            for packet in container.demux(stream):
                stamp = packet.pts if packet.pts is not None else packet.dts
                if stamp is None or packet.size == 0 or packet.is_discard:
                    continue
                times.append(Fraction(stamp) * tb)
                if len(times) > limits.frames:
                    _check_limits(limits, frames=len(times), what="the stream holds at least")
        except TrackingError:
            raise
        except Exception as e:
            raise TrackingError(f"{path.name}: the stream is corrupt after {len(times)} frames: {_oneline(e)}",
                                field="video") from None
    finally:
        container.close()
    if not times:
        raise TrackingError(f"{path.name}: the video stream holds no frame", field="video")
    times.sort()
    _check_limits(limits, seconds=float(times[-1] - times[0]), what="the frames span")
    return times, tb


def is_constant_rate(times: list[Fraction], tick: Fraction) -> bool:
    """Whether every interval between consecutive ``times`` is within max(1 ms, 2 ticks) of their median."""
    if len(times) < 3:
        return True
    steps = np.diff(np.array([float(t) for t in times]))
    return bool(np.abs(steps - np.median(steps)).max() <= max(1e-3, 2 * float(tick)))


def average_rate(times: list[Fraction]) -> Fraction:
    """Frames per second over the frames' span ((N - 1) / span), as a simple fraction (denominator <= 1001)."""
    if len(times) < 2 or times[-1] == times[0]:
        return Fraction(30)
    return (Fraction(len(times) - 1) / (times[-1] - times[0])).limit_denominator(1001)


def resample_plan(times: list[Fraction], fps: Fraction) -> list[int]:
    """For each output frame k (time k / fps from the first frame), the index of the source frame nearest in time
    (the earlier on a tie), while k / fps is less than half an output interval past the last source frame."""
    start, end = times[0], times[-1] - times[0]
    plan: list[int] = []
    i = 0
    k = 0
    while Fraction(k) / fps < end + Fraction(1, 2) / fps:
        t = Fraction(k) / fps + start
        while i + 1 < len(times) and times[i + 1] - t < t - times[i]:
            i += 1
        plan.append(i)
        k += 1
    return plan


class VideoReader:
    """Frames of a video, upright, at a constant rate (module docstring). ``info`` is read on construction (the
    metadata limits checked); iterating decodes. ``fps``: the output rate (None: the source's)."""

    def __init__(self, path: str | os.PathLike, fps: float | Fraction | None = None,
                 limits: VideoLimits = VideoLimits()):
        self.path, self.limits = Path(path), limits
        if fps is not None and not (0 < float(fps) <= MAX_FPS):
            raise TrackingError(f"must be in (0, {MAX_FPS}], got {fps}", field="fps")
        self.requested_fps = None if fps is None else Fraction(fps).limit_denominator(1001)
        self.info = probe_video(self.path, limits)
        self._plan: list[int] | None = None
        self.source_frames = 0
        self.source_fps = self.info.fps
        self.fps = self.requested_fps or self.info.fps
        self.resampled = False

    def plan(self) -> list[int]:
        """The source frame of each output frame (step 2 of the module docstring; read once)."""
        if self._plan is None:
            times, tick = scan_times(self.path, self.limits)
            self._times, self.source_frames = times, len(times)
            rate = average_rate(times)
            declared = self.info.fps
            if declared and abs(declared - rate) <= rate / 200:  # the container's rate, when the frames agree
                rate = declared
            self.source_fps = rate
            self.fps = self.requested_fps or rate
            same = self.requested_fps is None or abs(self.requested_fps - rate) <= rate / 1000
            self.resampled = not (same and is_constant_rate(times, tick))
            plan = resample_plan(times, self.fps) if self.resampled else list(range(len(times)))
            _check_limits(self.limits, frames=len(plan), what=f"at {float(self.fps):g} fps the video has")
            self._plan = plan
        return self._plan

    def __len__(self) -> int:
        return len(self.plan())

    def __iter__(self) -> Iterator[Frame]:
        plan = self.plan()
        times = self._times
        wanted: dict[int, list[int]] = {}
        for k, i in enumerate(plan):
            wanted.setdefault(i, []).append(k)
        yield from self._decode(plan, times, wanted)

    def _decode(self, plan: list[int], times: list[Fraction], wanted: dict[int, list[int]]) -> Iterator[Frame]:
        index = {t: i for i, t in enumerate(times)}
        container = _open(self.path, self.info.container)
        name = self.path.name
        emitted = 0
        try:
            stream = container.streams.video[0]
            tb = stream.time_base
            frames = container.decode(stream)
            while emitted < len(plan):
                try:
                    frame = next(frames, None)
                except Exception as e:
                    raise TrackingError(f"{name}: the stream is corrupt at frame {emitted}: {_oneline(e)}",
                                        field="video") from None
                if frame is None:
                    raise TrackingError(f"{name}: the stream ended at frame {emitted} of {len(plan)} (truncated or "
                                        "corrupt)", field="video")
                if frame.is_corrupt:
                    raise TrackingError(f"{name}: frame {emitted} is corrupt", field="video")
                i = index.get(Fraction(frame.pts) * tb) if frame.pts is not None else None
                if i is None or i not in wanted:
                    continue
                rgb = np.rot90(frame.to_ndarray(format="rgb24"), self.info.rotation // 90)
                rgb = np.ascontiguousarray(rgb)
                rgb.flags.writeable = False  # shared by the output frames that repeat it
                for k in wanted.pop(i):
                    yield Frame(k, float(k / self.fps), i, float(times[i] - times[0]), rgb)
                    emitted += 1
        finally:
            container.close()

    def report(self) -> dict:
        """What was read: source and output frame counts and rates, resampled or not, repeats and skips."""
        plan = self.plan()
        used = set(plan)
        return {"container": self.info.container, "codec": self.info.codec, "width": self.info.width,
                "height": self.info.height, "rotation": self.info.rotation, "source_frames": self.source_frames,
                "source_fps": float(self.source_fps), "fps": float(self.fps), "frames": len(plan),
                "resampled": self.resampled, "repeated": len(plan) - len(used),
                "skipped": self.source_frames - len(used)}
