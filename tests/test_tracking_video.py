"""Stage 1 of the tracker (render_core/tracking/video.py, crop.py): videos made here with PyAV - H.264 in MP4, MOV,
VP9 in WebM, H.264 in MKV, a rotated one, a variable-rate one, a corrupt one, a truncated one, non-videos, and ones
over the limits that are refused from their metadata without being decoded."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import av
import numpy as np
import pytest

from render_core.errors import TrackingError
from render_core.tracking.crop import Window, crop_frame, crop_windows, whole_frame
from render_core.tracking.video import VideoLimits, VideoReader, probe_video, resample_plan

W, H = 64, 48


def _picture(i: int, w: int = W, h: int = H, noise: bool = False) -> np.ndarray:
    """Frame i: grey level 8 i (its index, read back from the decoded frame's mean), a white 8x8 mark top-left."""
    if noise:
        img = np.random.default_rng(i).integers(0, 256, (h, w, 3), dtype=np.uint8)
    else:
        img = np.full((h, w, 3), 8 * i + 4, dtype=np.uint8)
    img[:8, :8] = 255
    return img


def write_video(path: Path, n: int = 12, *, fps: int = 30, codec: str = "libx264", fmt: str | None = None,
                w: int = W, h: int = H, rotation: int | None = None, tags: dict | None = None,
                pts_ms: list[int] | None = None, noise: bool = False, faststart: bool = False) -> Path:
    """An n-frame video; ``rotation``: the display matrix (degrees counter-clockwise); ``pts_ms``: timestamps."""
    with av.open(str(path), "w", format=fmt, options={"movflags": "faststart"} if faststart else {}) as c:
        s = c.add_stream(codec, rate=fps)
        s.width, s.height, s.pix_fmt = w, h, "yuv420p"
        s.options = {"crf": "10"} if codec == "libx264" else {}
        if rotation is not None:
            s.set_display_rotation(rotation)
        for k, v in (tags or {}).items():
            s.metadata[k] = v
        if pts_ms is not None:
            s.codec_context.time_base = Fraction(1, 1000)
        for i in range(n):
            f = av.VideoFrame.from_ndarray(_picture(i, w, h, noise), format="rgb24")
            if pts_ms is not None:
                f.pts, f.time_base = pts_ms[i], Fraction(1, 1000)
            for p in s.encode(f):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    return path


def _index(rgb: np.ndarray) -> int:
    """The index written into a frame by _picture (its grey level away from the mark)."""
    return int(round((float(rgb[-16:, -16:].mean()) - 4) / 8))


def _field(exc: pytest.ExceptionInfo) -> str:
    return exc.value.field


@pytest.mark.parametrize(("name", "codec", "fmt", "container"), [
    ("clip.mp4", "libx264", None, "mov"),
    ("clip.mov", "libx264", None, "mov"),
    ("clip.mkv", "libx264", "matroska", "matroska"),
    ("clip.webm", "libvpx-vp9", "webm", "matroska"),
])
def test_a_constant_rate_video_is_read_frame_for_frame(tmp_path, name, codec, fmt, container):
    reader = VideoReader(write_video(tmp_path / name, codec=codec, fmt=fmt))
    assert (reader.info.container, reader.info.width, reader.info.height, reader.info.rotation) == (container, W, H, 0)
    frames = list(reader)
    assert [f.index for f in frames] == [f.source for f in frames] == list(range(12))
    assert [_index(f.rgb) for f in frames] == list(range(12))
    assert frames[0].rgb.shape == (H, W, 3) and frames[0].rgb.dtype == np.uint8
    report = reader.report()
    assert report["resampled"] is False and report["fps"] == report["source_fps"] == 30.0
    assert (report["frames"], report["repeated"], report["skipped"]) == (12, 0, 0)


def test_the_display_matrix_turns_a_portrait_phone_video_upright(tmp_path):
    # a phone's portrait video: landscape pictures, "rotate 90 degrees clockwise" in the display matrix
    reader = VideoReader(write_video(tmp_path / "portrait.mp4", rotation=-90))
    assert (reader.info.rotation, reader.info.width, reader.info.height) == (270, H, W)
    rgb = next(iter(reader)).rgb
    assert rgb.shape == (W, H, 3)
    assert rgb[:8, -8:].min() > 240 and rgb[:8, :8].max() < 100  # the top-left mark is now top-right


def test_a_legacy_rotate_tag_is_honoured(tmp_path):
    reader = VideoReader(write_video(tmp_path / "tagged.mkv", fmt="matroska", tags={"rotate": "180"}))
    assert reader.info.rotation == 180 and (reader.info.width, reader.info.height) == (W, H)
    rgb = next(iter(reader)).rgb
    assert rgb[-8:, -8:].min() > 240 and rgb[:8, :8].max() < 100  # the mark is now bottom-right


def test_a_variable_rate_video_is_resampled_to_the_nearest_frames(tmp_path):
    pts = [0, 33, 50, 100, 200, 210, 220, 300, 400, 433]
    path = write_video(tmp_path / "vfr.mp4", n=len(pts), pts_ms=pts)
    reader = VideoReader(path, fps=30)
    frames = list(reader)
    # output k at k/30 s shows the source frame nearest in time (the earlier on a tie)
    expected = [0, 1, 2, 3, 3, 4, 4, 6, 7, 7, 7, 8, 8, 9]
    assert [f.source for f in frames] == expected
    assert [_index(f.rgb) for f in frames] == expected
    assert [round(f.time, 4) for f in frames] == [round(k / 30, 4) for k in range(len(expected))]
    report = reader.report()
    assert report["resampled"] is True and (report["repeated"], report["skipped"]) == (5, 1)
    # by default: the source's own average rate, (10 - 1) frames over 0.433 s
    default = VideoReader(path)
    assert default.report()["resampled"] is True and abs(default.report()["fps"] - 9 / 0.433) < 0.01


def test_a_constant_rate_video_changes_rate_only_when_asked(tmp_path):
    path = write_video(tmp_path / "cfr.mp4", n=12)
    assert VideoReader(path, fps=30).report()["resampled"] is False
    half = VideoReader(path, fps=15)
    assert [f.source for f in half] == [0, 2, 4, 6, 8, 10]
    assert resample_plan([Fraction(k, 10) for k in range(4)], Fraction(20)) == [0, 0, 1, 1, 2, 2, 3]


def test_a_stream_corrupt_halfway_is_named_with_its_frame(tmp_path):
    path = write_video(tmp_path / "noise.mp4", n=40, w=128, h=96, noise=True, faststart=True)
    data = bytearray(path.read_bytes())
    start = data.find(b"mdat")
    middle = start + (len(data) - start) // 2
    data[middle:middle + 4000] = np.random.default_rng(1).integers(0, 256, 4000, dtype=np.uint8).tobytes()
    path.write_bytes(bytes(data))
    reader = VideoReader(path)
    got = []
    with pytest.raises(TrackingError) as e:
        for f in reader:
            got.append(f.index)
    assert _field(e) == "video" and "corrupt" in str(e.value)
    assert 5 < len(got) < 40 and f"frame {len(got)}" in str(e.value)


def test_a_truncated_upload_is_refused(tmp_path):
    path = write_video(tmp_path / "cut.mp4", n=40, w=128, h=96, noise=True, faststart=True)
    path.write_bytes(path.read_bytes()[: path.stat().st_size * 2 // 3])
    with pytest.raises(TrackingError) as e:
        list(VideoReader(path))
    assert _field(e) == "video"


def test_what_is_not_a_video_is_refused_by_name(tmp_path):
    text = tmp_path / "notes.mp4"
    text.write_text("not a video\n" * 100)
    empty = tmp_path / "empty.mkv"
    empty.write_bytes(b"")
    png = tmp_path / "image.mp4"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    audio = tmp_path / "audio.mp4"
    with av.open(str(audio), "w") as c:
        s = c.add_stream("aac", rate=44100)
        frame = av.AudioFrame.from_ndarray(np.zeros((1, 1024), np.float32), format="fltp", layout="mono")
        frame.sample_rate = 44100
        for p in [*s.encode(frame), *s.encode()]:
            c.mux(p)
    for path, words in ((text, "not a video"), (empty, "not a video"), (png, "not a video"),
                        (audio, "no video stream"), (tmp_path / "missing.mp4", "cannot read")):
        with pytest.raises(TrackingError) as e:
            VideoReader(path)
        assert _field(e) == "video" and words in str(e.value), (path, str(e.value))


def test_limits_are_refused_from_the_metadata_without_decoding(tmp_path):
    # 60 frames whose pictures are all zeroed: decoding any of them fails, so the limit's error shows it never did
    path = write_video(tmp_path / "long.mp4", n=60, w=128, h=96, noise=True, faststart=True)
    data = bytearray(path.read_bytes())
    start = data.find(b"mdat") + 8
    data[start:] = bytes(len(data) - start)
    path.write_bytes(bytes(data))
    with pytest.raises(TrackingError) as e:
        VideoReader(path, limits=VideoLimits(frames=50))
    assert _field(e) == "frames" and "60 frames" in str(e.value)
    with pytest.raises(TrackingError) as e:
        VideoReader(path, limits=VideoLimits(seconds=1.5))
    assert _field(e) == "duration"
    with pytest.raises(TrackingError) as e:
        VideoReader(path, limits=VideoLimits(long_side=100))
    assert _field(e) == "resolution" and "128x96" in str(e.value)
    with pytest.raises(TrackingError) as e:  # within the limits, the zeroed pictures are found corrupt
        VideoReader(path)
    assert _field(e) == "video"


def test_the_default_limits(tmp_path):
    assert VideoLimits() == VideoLimits(seconds=300.0, long_side=4096, frames=9000)
    # ten minutes in two frames
    with pytest.raises(TrackingError) as e:
        probe_video(write_video(tmp_path / "slow.mp4", n=2, pts_ms=[0, 600_000]))
    assert _field(e) == "duration"
    with pytest.raises(TrackingError) as e:
        probe_video(write_video(tmp_path / "wide.mp4", n=2, w=4112, h=16))
    assert _field(e) == "resolution" and "4096" in str(e.value)
    # a container that declares nothing is held to the limits as its packets are read
    reader = VideoReader(write_video(tmp_path / "short.webm", n=12, codec="libvpx-vp9", fmt="webm"),
                         limits=VideoLimits(frames=12))
    assert len(reader) == 12
    with pytest.raises(TrackingError) as e:  # 12 source frames become 24 at 60 fps
        len(VideoReader(tmp_path / "short.webm", fps=60, limits=VideoLimits(frames=20)))
    assert _field(e) == "frames"


def test_a_bad_rate_is_refused(tmp_path):
    path = write_video(tmp_path / "a.mp4", n=2)
    for fps in (0, -5, 1000):
        with pytest.raises(TrackingError) as e:
            VideoReader(path, fps=fps)
        assert _field(e) == "fps"


# ------------------------------------------------------------------------------------------------------- crops
def test_crop_none_keeps_the_whole_frame_with_the_principal_point_at_the_centre():
    K = np.array([[900.0, 0.0, 960.0], [0.0, 900.0, 540.0], [0.0, 0.0, 1.0]])
    for fw, fh, w, h in ((1920, 1080, 512, 512), (1081, 1921, 512, 288), (640, 480, 320, 240)):
        window = whole_frame(fw, fh, w, h)
        Kc = window.intrinsics(np.array([[900.0, 0, fw / 2], [0, 900.0, fh / 2], [0, 0, 1]]))
        assert np.allclose(Kc[:2, 2], [w / 2, h / 2])
        corners = window.to_crop(np.array([[0.0, 0.0], [fw, fh]]))
        assert (corners >= -1e-9).all() and (corners[:, 0] <= w + 1e-9).all() and (corners[:, 1] <= h + 1e-9).all()
    window = crop_windows(None, 1920, 1080, 512, 512, mode="none")[0]
    assert np.allclose(window.intrinsics(K)[0, 0], 900.0 * 512 / 1920)
    rgb = np.full((1080, 1920, 3), 200, np.uint8)
    out = crop_frame(rgb, window)
    assert out.shape == (512, 512, 3)
    assert out[:100].max() == 0 and out[-100:].max() == 0 and out[200:300].min() == 200  # bars above and below


def test_a_fixed_head_crop_covers_every_face_and_keeps_the_intrinsics():
    boxes = np.array([[300, 200, 400, 330], [np.nan] * 4, [340, 210, 440, 340], [320, 190, 420, 320]], float)
    windows = crop_windows(boxes, 1280, 720, 256, 256)
    assert len(windows) == 4 and len(set(windows)) == 1
    win = windows[0]
    assert win.w == win.h and win.x0 <= 300 and win.x0 + win.w >= 440 and win.y0 <= 190 and win.y0 + win.h >= 340
    # a frame point lands where the window's mapping says
    rgb = np.zeros((720, 1280, 3), np.uint8)
    rgb[250:260, 370:380] = 255
    out = crop_frame(rgb, win)
    centre = win.to_crop(np.array([[375.0, 255.0]]))[0]
    ys, xs = np.nonzero(out[..., 0] > 64)
    assert abs(xs.mean() + 0.5 - centre[0]) < 0.6 and abs(ys.mean() + 0.5 - centre[1]) < 0.6


def test_a_following_crop_moves_with_the_face_and_a_window_stays_inside_the_frame():
    boxes = np.array([[100 + 10 * i, 100, 200 + 10 * i, 200] for i in range(20)], float)
    windows = crop_windows(boxes, 640, 480, 128, 128, mode="follow", smooth=5)
    xs = [w.x0 for w in windows]
    assert xs == sorted(xs) and xs[-1] > xs[0]
    near_edge = crop_windows(np.array([[0, 0, 100, 100]], float), 640, 480, 128, 128)[0]
    assert near_edge.x0 == 0 and near_edge.y0 == 0
    assert Window(0, 0, 64, 64, 128, 128).scale == (2.0, 2.0)
    for bad in ({"mode": "zoom"}, {"mode": "fixed", "scale": 0.0}):
        with pytest.raises(TrackingError) as e:
            crop_windows(boxes, 640, 480, 128, 128, **bad)
        assert _field(e) == "crop"
    with pytest.raises(TrackingError) as e:
        crop_windows(np.full((3, 4), np.nan), 640, 480, 128, 128)
    assert _field(e) == "crop"
    with pytest.raises(TrackingError) as e:
        crop_windows(boxes, 640, 480, 4, 128)
    assert _field(e) == "size"
