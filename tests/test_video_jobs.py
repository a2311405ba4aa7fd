"""Jobs from a video (issue 27, the job service's part): `POST /v1/uploads` takes an ordinary video beside the dataset
archives (sniffed by content, probed for the limits without being decoded), and a job from it tracks it (the
built-in CPU tracker), trains, evaluates and commits; the track stage's progress events, overlay and tracked dataset
are the job's; deletion removes them; bad input is a named error that keeps nothing; a job resumed after the track
stage does not track again.

Against real `blendsplat up` processes (service + worker child) on SQLite and PostgreSQL (127.0.0.1:5432; skipped
with the reason when unreachable), and an in-process worker for resumption. The videos are tiny: `blendsplat data
synth --frames 40 --size 128 --seed 8` encoded as H.264 MP4 with PyAV, and solid colours for the rest.
"""

from __future__ import annotations

import asyncio
import io
import json
import shutil
import subprocess
import sys
import tarfile
import threading
import time
from fractions import Fraction
from pathlib import Path

import av
import grpc
import numpy as np
import pytest
from test_jobs_api import DATABASES, ROOT, ServerProcess, _wait, job_database

from blendsplat.v1 import render_pb2 as pb
from blendsplat.v1 import render_pb2_grpc as pb_grpc
from render_core.data import validate_dataset
from service.jobs import EventKind, JobStore
from service.jobs.archive import ArchiveError
from service.jobs.uploads import UploadStore
from service.jobs.video import VideoError, sniff_video, video_limits
from service.jobs.worker import Worker
from service.settings import Settings

UP_ENV = {"BLENDSPLAT_HEARTBEAT_SECONDS": "0.5", "BLENDSPLAT_MAX_VIDEO_SECONDS": "5",
          "BLENDSPLAT_MAX_VIDEO_SIDE": "256", "BLENDSPLAT_MAX_VIDEO_FRAMES": "100"}
JOB = {"preset": "tiny", "iterations": 20, "checkpoint_every": 10, "gaussians": 400, "mouth": 40, "seed": 2}
TRACK_FILES = ("tracked", "overlay.png", "dataset.tar.gz", "track.json")


# ------------------------------------------------------------------------------------------------- videos
def encode(path: Path, frames: list[np.ndarray], fps: int = 30, *, options: dict | None = None,
           pts: list[int] | None = None, time_base: Fraction | None = None, codec: str = "libx264",
           container: str = "mp4") -> Path:
    """Frames (RGB uint8) as a video with PyAV: H.264 yuv420p in MP4 by default, whatever the file's name
    (``options``: the muxer's, e.g. ``movflags=faststart``; ``pts`` in ``time_base``: the frames' timestamps)."""
    with av.open(str(path), "w", format=container, options=options or {}) as out:
        stream = out.add_stream(codec, rate=fps)
        stream.height, stream.width = frames[0].shape[:2]
        stream.pix_fmt = "yuv420p"
        if codec == "libx264":
            stream.options = {"crf": "20", "preset": "ultrafast"}
        if time_base is not None:
            stream.codec_context.time_base = time_base
        for i, rgb in enumerate(frames):
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
            if pts is not None:
                frame.pts, frame.time_base = pts[i], time_base
            for packet in stream.encode(frame):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    return path


def read_png(path: Path) -> np.ndarray:
    with av.open(str(path)) as image:
        return next(image.decode(video=0)).to_ndarray(format="rgb24")


def solid(n: int, width: int = 128, height: int = 128, value: int = 90) -> list[np.ndarray]:
    return [np.full((height, width, 3), value, np.uint8) for _ in range(n)]


@pytest.fixture(scope="module")
def head_frames(tmp_path_factory) -> list[np.ndarray]:
    """The 40 frames of `blendsplat data synth --frames 40 --size 128 --seed 8` (the open head, known answer)."""
    out = tmp_path_factory.mktemp("synth") / "take"
    subprocess.run([sys.executable, "-m", "service.cli", "data", "synth", "--out", str(out), "--frames", "40",
                    "--size", "128", "--seed", "8"], cwd=ROOT, check=True, capture_output=True, timeout=300)
    return [read_png(p) for p in sorted((out / "frames").glob("*.png"))]


@pytest.fixture(scope="module")
def videos(head_frames, tmp_path_factory) -> dict[str, bytes]:
    """The test videos by name: the head as an ordinary MP4, and the hostile ones."""
    d = tmp_path_factory.mktemp("videos")
    clip = encode(d / "clip.mp4", head_frames).read_bytes()
    faststart = encode(d / "faststart.mp4", head_frames, options={"movflags": "faststart"}).read_bytes()
    damaged = bytearray(faststart)  # bytes damaged in the middle of the stream: it decodes up to there
    middle = len(damaged) // 2
    damaged[middle:middle + 2000] = np.random.default_rng(0).integers(0, 256, 2000, np.uint8).tobytes()
    return {
        "clip": clip,
        "no-face": encode(d / "grey.mp4", solid(20)).read_bytes(),
        "not-a-video": b"this is a text file renamed .mp4\n" * 40,
        "too-long": encode(d / "long.mp4", solid(180, 32, 32), fps=30).read_bytes(),  # 6 s (limit 5)
        "too-large": encode(d / "wide.mp4", solid(12, 320, 64)).read_bytes(),  # 320 px (limit 256)
        "too-many-frames": encode(d / "many.mp4", solid(120, 32, 32), fps=120).read_bytes(),  # 120 (limit 100)
        "too-short": encode(d / "short.mp4", head_frames[:5]).read_bytes(),
        "truncated": clip[: len(clip) // 2],  # its index (moov) was at the end: gone
        "truncated-faststart": faststart[: len(faststart) * 6 // 10],  # the index promises frames that are not there
        "corrupt-halfway": bytes(damaged),
    }


# ------------------------------------------------------------------------------------------------- the server
@pytest.fixture(scope="module", params=DATABASES)
def up(request, pg_admin_user, tmp_path_factory):
    """`blendsplat up` (service + worker child) with small video limits, on SQLite or PostgreSQL."""
    with job_database(request.param, pg_admin_user) as url:
        proc = ServerProcess(tmp_path_factory.mktemp("video-jobs") / "data", url, command="up", **UP_ENV)
        yield proc
        assert proc.stop() == 0


def post_video(server: ServerProcess, data: bytes, name: str = "x.bin"):
    return server.http.post("/v1/uploads", files={"file": (name, data, "application/octet-stream")})


def entries(folder: Path) -> set[str]:
    return {p.name for p in folder.iterdir()} if folder.is_dir() else set()


def run_job(server: ServerProcess, upload_id: str, avatar_id: str, timeout: float = 300) -> dict:
    r = server.http.post("/v1/jobs", json={"upload_id": upload_id, "avatar_id": avatar_id, **JOB})
    assert r.status_code == 201, r.text
    job_id = r.json()["id"]
    return _wait(lambda: (j := server.http.get(f"/v1/jobs/{job_id}").json())["state"] in
                 ("succeeded", "failed", "cancelled") and j, timeout, f"job {job_id} to end")


def job_events(server: ServerProcess, job_id: str) -> list:
    """The finished job's whole history from its event stream (it ends with `end`)."""
    from blendsplat_client import Client

    with Client(server.url, api_key=server.key) as client:
        return list(client.events(job_id))


def test_a_video_upload_is_sniffed_probed_and_kept_as_it_is(up, videos):
    r = post_video(up, videos["clip"], "x.bin")  # the name says nothing: the bytes do
    assert r.status_code == 201, r.text
    body = r.json()
    assert body["kind"] == "video" and body["container"] == "mp4" and body["archive"] is None
    assert (body["frames"], body["width"], body["height"], body["fps"]) == (40, 128, 128, 30.0)
    assert abs(body["duration"] - 40 / 30) < 0.01 and body["face_model"] == "open-head-anny"
    assert body["filename"] == "x.bin" and body["size"] == len(videos["clip"])
    assert r.headers["location"] == f"/v1/uploads/{body['upload_id']}"
    assert up.http.get(r.headers["location"]).json() == body
    folder = up.data_dir / "uploads" / body["upload_id"]
    assert entries(folder) == {"upload.json", "video.mp4"}
    assert (folder / "video.mp4").read_bytes() == videos["clip"]
    schema = up.http.get("/openapi.json").json()["components"]["schemas"]["UploadOut"]["properties"]
    assert {"kind", "container", "duration", "fps"} <= set(schema)
    assert up.http.delete(f"/v1/uploads/{body['upload_id']}").status_code == 204
    assert not folder.exists()


@pytest.mark.parametrize(("name", "says"), [
    ("not-a-video", "not a .tar, .tar.gz or .zip archive, nor a video"),
    ("too-long", "BLENDSPLAT_MAX_VIDEO_SECONDS"),
    ("too-large", "BLENDSPLAT_MAX_VIDEO_SIDE"),
    ("too-many-frames", "BLENDSPLAT_MAX_VIDEO_FRAMES"),
    ("too-short", "too short"),
    ("truncated", "cannot be opened as a video"),
    ("truncated-faststart", "truncated"),
])
def test_a_bad_video_is_a_named_422_and_nothing_is_kept(up, videos, name, says):
    uploads = up.data_dir / "uploads"
    before = entries(uploads)
    r = post_video(up, videos[name], f"{name}.mp4")
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    assert error["field"] == "file" and says in error["message"], error
    assert str(up.data_dir) not in error["message"] and ".staging-" not in error["message"]
    assert entries(uploads) == before  # nothing kept, nothing left half-done


def test_a_job_from_a_video_tracks_trains_commits_and_streams_and_deletion_removes_it_all(up, videos):
    r = post_video(up, videos["clip"], "take.mp4")
    assert r.status_code == 201, r.text
    upload_id = r.json()["upload_id"]
    job = run_job(up, upload_id, "from-video")
    assert job["state"] == "succeeded", job
    assert job["result"]["avatar_id"] == "from-video" and job["result"]["iterations"] == 20
    assert job["result"]["evaluation"]["psnr"] > 0  # the tracker held frames out: evaluated on them

    # the track stage's progress, in order, before training's
    events = job_events(up, job["id"])
    track = [e.data for e in events if e.event == "progress" and e.data["stage"] == "track"]
    steps = [d["step"] for d in track]
    assert [k for i, k in enumerate(steps) if i == 0 or k != steps[i - 1]] == ["start", "landmarks", "fit", "write",
                                                                               "done"]
    assert any("frame 30 of 40" in d["message"] for d in track if d["step"] == "landmarks")  # every 5% (30 frames)
    assert all(d["iteration"] is None and d["message"] for d in track)
    assert "tracked 40 frames at 128x128" in track[-1]["message"]
    train = [e for e in events if e.event == "progress" and e.data["stage"] == "train"]
    assert train and train[-1].data["iteration"] == 20
    assert events.index(train[0]) > max(i for i, e in enumerate(events) if e.event == "progress"
                                        and e.data["stage"] == "track")
    assert not any(str(up.data_dir) in json.dumps(e.data) for e in events)

    # the overlay and the tracked dataset are artefacts of the job
    artefacts = job["links"]["artefacts"]
    assert {"overlay", "dataset", "track-report", "report", "preview"} <= set(artefacts)
    overlay = up.http.get(artefacts["overlay"])
    assert overlay.status_code == 200 and overlay.headers["content-type"] == "image/png"
    assert overlay.content.startswith(b"\x89PNG")
    dataset = up.http.get(artefacts["dataset"])
    assert dataset.status_code == 200 and dataset.headers["content-type"] == "application/gzip"
    assert "attachment" in dataset.headers["content-disposition"]
    with tarfile.open(fileobj=io.BytesIO(dataset.content), mode="r:gz") as tar:
        names = tar.getnames()
        assert "dataset/tracking.npz" in names and "dataset/dataset.json" in names
    report = up.http.get(artefacts["track-report"]).json()
    assert report["frames_kept"] == 40 and "out" not in report
    page = up.http.get("/jobs")
    assert page.status_code == 200 and "overlay-img" in page.text

    # the avatar streams
    with grpc.insecure_channel(up.grpc_target) as channel:
        stub = pb_grpc.RenderServiceStub(channel)
        requests = iter([pb.StreamRequest(open=pb.SessionConfig(avatar_id="from-video", width=48, height=48)),
                         pb.StreamRequest(frame=pb.FrameParams(index=1))])
        replies = stub.RenderStream(requests, metadata=(("authorization", f"Bearer {up.key}"),))
        assert next(replies).WhichOneof("msg") == "header"
        frame = next(replies)
        assert frame.WhichOneof("msg") == "frame" and frame.frame.data

    # deletion: the job's work folder (tracked dataset, its archive, the overlay), then the video
    work = up.data_dir / "work" / job["id"]
    assert set(TRACK_FILES) <= entries(work)
    assert up.http.delete(f"/v1/jobs/{job['id']}").status_code == 204
    assert not work.exists() and up.http.get(artefacts["overlay"]).status_code == 404
    assert up.http.delete(f"/v1/uploads/{upload_id}").status_code == 204
    assert not (up.data_dir / "uploads" / upload_id).exists()
    assert up.http.delete("/v1/avatars/from-video").status_code == 204


@pytest.mark.parametrize(("name", "error"), [
    ("no-face", "TrackingError: face: no face found in any of the 20 frames"),
    ("corrupt-halfway", "TrackingError: video: video.mp4: the stream is corrupt at frame"),
])
def test_a_video_the_tracker_refuses_fails_its_job_with_the_named_error_and_keeps_nothing(up, videos, name, error):
    r = post_video(up, videos[name], f"{name}.mp4")
    assert r.status_code == 201, r.text  # its metadata and packets are fine: only decoding finds out
    upload_id = r.json()["upload_id"]
    job = run_job(up, upload_id, f"never-{name}")
    assert job["state"] == "failed" and job["error"].startswith(error), job
    assert str(up.data_dir) not in job["error"]
    assert not set(job["links"]["artefacts"]) & {"overlay", "dataset", "track-report"}
    missing = up.http.get(f"/v1/jobs/{job['id']}/artefacts/overlay")
    assert missing.status_code == 404 and "failed before the video was tracked" in missing.json()["error"]["message"]
    work = up.data_dir / "work" / job["id"]
    assert not entries(work) & set(TRACK_FILES) and not any(n.startswith(".") for n in entries(work))
    assert up.http.get(f"/v1/avatars/never-{name}").status_code == 404
    assert up.http.delete(f"/v1/jobs/{job['id']}").status_code == 204
    assert up.http.delete(f"/v1/uploads/{upload_id}").status_code == 204


def test_the_jobs_page_takes_a_video_shows_tracking_and_the_overlay(up, videos, driver, tmp_path):
    """/jobs in headless Chromium: a video dropped on the page is described as one, the job started from the page
    shows the tracking steps, then the overlay image, and offers the tracked dataset for download."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    if up.jobs_url:
        pytest.skip("the page is the same on both job databases: checked once, on SQLite")
    video = tmp_path / "Take 2.mp4"
    video.write_bytes(videos["clip"])
    driver.get(f"{up.url}/healthz")
    driver.execute_script("sessionStorage.setItem('blendsplat.apiKey', arguments[0])", up.key)
    driver.get(f"{up.url}/jobs")

    def text(element_id: str) -> str:
        return " ".join((driver.find_element(By.ID, element_id).get_attribute("textContent") or "").split())

    def wait(what, condition, timeout: float = 120):
        try:
            return WebDriverWait(driver, timeout, poll_frequency=0.05).until(condition)
        except Exception:  # what the page shows, not a bare timeout
            shown = {i: text(i) for i in ("status", "upload-text", "upload-error", "progress-text", "job-error")}
            pytest.fail(f"timed out waiting for {what}; page: {shown}; log: {up.output()[-2000:]}")

    driver.find_element(By.ID, "file").send_keys(str(video))
    wait("the upload", lambda d: d.find_element(By.TAG_NAME, "body").get_attribute("data-upload") == "done")
    assert "video (mp4), 1.3 s, 40 frames, 128×128 at 30.00 fps" in text("upload-text"), text("upload-text")
    assert driver.find_element(By.ID, "avatar-id").get_attribute("value") == "Take-2"
    iterations = driver.find_element(By.ID, "iterations")
    iterations.clear()
    iterations.send_keys("10")
    driver.find_element(By.ID, "start").click()
    wait("the tracking steps in the log", lambda d: "tracking: tracked 40 frames" in text("events-log"))
    wait("the overlay image", lambda d: d.find_element(By.ID, "overlay-img").is_displayed() and d.execute_script(
        "const i = document.getElementById('overlay-img'); return i.complete && i.naturalWidth > 0;"))
    assert "tracked 40 frames at 128x128" in text("overlay-caption")
    wait("the job to succeed", lambda d: text("job-state") == "succeeded", timeout=300)
    wait("the tracked dataset's download", lambda d: d.find_element(By.ID, "download-dataset").is_displayed())
    driver.save_screenshot(str(tmp_path / "jobs-page-video.png"))
    job_id = text("job-id")
    assert up.http.delete(f"/v1/jobs/{job_id}").status_code == 204
    assert up.http.delete("/v1/avatars/Take-2").status_code == 204


# ------------------------------------------------------------------------------------------------- in process
async def _chunks(data: bytes):
    for start in range(0, len(data), 1 << 16):
        yield data[start:start + (1 << 16)]


def receive(store: UploadStore, data: bytes, filename: str = "x.bin"):
    return asyncio.run(store.receive(_chunks(data), max_bytes=1 << 30, filename=filename))


def test_videos_are_sniffed_by_content_not_by_name(tmp_path, head_frames):
    mp4 = encode(tmp_path / "a.bin", head_frames[:3])
    webm = encode(tmp_path / "b.dat", head_frames[:3], codec="libvpx", container="webm")
    webm_copy = tmp_path / "c.mkv"
    shutil.copyfile(webm, webm_copy)
    archive = tmp_path / "d.mp4"
    with tarfile.open(archive, "w:gz") as tar:
        tar.add(mp4, arcname="x/a.bin")
    assert (sniff_video(mp4), sniff_video(webm), sniff_video(webm_copy)) == ("mp4", "webm", "webm")
    assert sniff_video(archive) is None
    with pytest.raises(ArchiveError):  # an archive named .mp4 is an archive (here: not a dataset's layout)
        receive(UploadStore(tmp_path / "uploads"), archive.read_bytes(), "d.mp4")
    assert entries(tmp_path / "uploads") == set()


def test_a_4k_ten_minute_video_is_refused_by_the_limits_before_it_is_decoded(tmp_path):
    """Two 3840 x 2160 frames ten minutes apart: the default limits (5 minutes) refuse it from the container."""
    black = np.zeros((2160, 3840, 3), np.uint8)
    path = encode(tmp_path / "4k.mp4", [black, black], pts=[0, 600_000], time_base=Fraction(1, 1000))
    store = UploadStore(tmp_path / "uploads", video_limits=video_limits(300, 4096, 9000))
    t0 = time.monotonic()
    with pytest.raises(VideoError) as refused:
        receive(store, path.read_bytes(), "4k.mp4")
    assert time.monotonic() - t0 < 5
    assert refused.value.reason == "duration" and refused.value.field == "file"
    assert "600.0 s, over the limit of 300 s" in str(refused.value)
    assert entries(store.root) == set()


def _gapped(frames: list[np.ndarray]) -> list[np.ndarray]:
    """The head with the face gone for 2 frames (interpolated) and for 8 (dropped: a long gap)."""
    out = [f.copy() for f in frames]
    for i in (8, 9, *range(20, 28)):
        out[i] = solid(1)[0]
    return out


def test_a_job_resumed_after_the_track_stage_does_not_track_again(tmp_path, head_frames, monkeypatch):
    """The worker stops (a shutdown: the job handed back) right after the track stage; the next attempt trains on
    the tracked dataset without tracking again. The video loses the face twice: a short gap is interpolated and a
    long one dropped, and the job says so."""
    import render_core.tracking.track as tracker
    import service.jobs.run as run_module

    data = tmp_path / "data"
    settings = Settings(data_dir=data, jobs_url=f"sqlite:///{data.absolute() / 'jobs.db'}", heartbeat_seconds=0.2,
                        job_lease_seconds=5.0)
    upload = receive(UploadStore(settings.upload_dir), encode(tmp_path / "gaps.mp4", _gapped(head_frames)).read_bytes())
    with JobStore.open(settings.jobs_database_url) as jobs:
        job_id = jobs.submit({**JOB, "upload_id": upload.id, "avatar_id": "resumed"}, max_attempts=3).id
    calls = []
    real_track, real_stage = tracker.track_video, run_module.tracked_dataset
    monkeypatch.setattr(tracker, "track_video", lambda *a, **k: calls.append(1) or real_track(*a, **k))
    stop = threading.Event()

    def stage_then_stop(*args, **kwargs):
        out = real_stage(*args, **kwargs)
        stop.set()  # as SIGTERM would, right after the stage
        return out

    monkeypatch.setattr(run_module, "tracked_dataset", stage_then_stop)
    with Worker(settings) as worker:
        assert worker.run_one(stop).state.value == "queued"  # handed back before the first iteration
        work = settings.work_dir / job_id
        assert set(TRACK_FILES) <= entries(work) and calls == [1]
        marker = (work / "track.json").stat().st_mtime_ns
        job = worker.run_one()
    assert job.state.value == "succeeded", job.error
    assert calls == [1] and (work / "track.json").stat().st_mtime_ns == marker  # not tracked again
    assert validate_dataset(work / "tracked") == []
    # trained on the tracker's output: each frame's pose and expressions learn a correction (train
    # --refine-expressions), which a job from a dataset does not
    summary = json.loads(next(work.rglob("summary.json")).read_text())
    assert summary["refine"] == {"poses": True, "expressions": True}
    report = json.loads((work / "track.json").read_text())
    assert report["frames_dropped"]["count"] == 8 and report["interpolated"] == 2
    with JobStore.open(settings.jobs_database_url) as jobs:
        logs = [e.data["message"] for e in jobs.events(job_id, 0, 500) if e.kind is EventKind.LOG]
    assert any("tracked by an earlier attempt" in m for m in logs), logs
    assert any(m.startswith("frames 20 to 27 dropped: face lost for 8 frames") for m in logs), logs
    assert "2 frames without a face were interpolated (short gaps)" in logs
