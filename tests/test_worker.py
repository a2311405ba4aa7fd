"""The training worker (service/jobs/worker.py) against real parts: a SQLite job database, a real upload (a tar.gz of a
synthetic dataset received by the UploadStore), the Trainer, the bundle store, and worker processes killed with
SIGKILL and stopped with SIGTERM.

The jobs are short: 12 frames at 64 x 64, the tiny preset shrunk through the spec's optional knobs (400 face and
40 mouth Gaussians, a checkpoint every 4 iterations), 40 iterations.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import typing
import urllib.request
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from render_core import read_bundle
from render_core.bundle import read_manifest
from render_core.data import read_dataset
from render_core.train.presets import PRESETS
from render_core.train.trainer import Trainer, last_checkpoint
from service.errors import InvalidArgument
from service.jobs import EventKind, JobState, JobStore
from service.jobs.resize import dataset_at, resample, scaled_intrinsics, training_size
from service.jobs.schemas import JobSpec
from service.jobs.uploads import UploadStore
from service.jobs.worker import Worker, add_arguments
from service.settings import Settings
from service.store import BundleStore

ROOT = Path(__file__).resolve().parents[1]
SPEC = {"preset": "tiny", "iterations": 40, "seed": 3, "resolution": None, "checkpoint_every": 4, "gaussians": 400,
        "mouth": 40}
FAST = {"heartbeat_seconds": 0.2, "job_lease_seconds": 2.0}  # the tests' lease: 2 s, a heartbeat every 0.2 s


@pytest.fixture(scope="module")
def archive(tiny_video_archive) -> bytes:
    """The 12-frame 64 x 64 synthetic tracked video (tests/conftest.py)."""
    return tiny_video_archive


def make_settings(data_dir: Path, **overrides) -> Settings:
    """The tests' settings: a SQLite job database in ``data_dir`` whatever the environment says."""
    return Settings(data_dir=data_dir, jobs_url=f"sqlite:///{data_dir.absolute() / 'jobs.db'}", **{**FAST, **overrides})


def upload(settings: Settings, archive: bytes) -> str:
    """Publish the dataset through the UploadStore (as POST /v1/uploads does); its upload id."""

    async def chunks():
        for start in range(0, len(archive), 1 << 16):
            yield archive[start:start + (1 << 16)]

    store = UploadStore(settings.upload_dir)
    return asyncio.run(store.receive(chunks(), max_bytes=1 << 30, filename="dataset.tar.gz")).id


def submit(settings: Settings, upload_id: str, avatar_id: str, **spec) -> str:
    with JobStore.open(settings.jobs_database_url) as jobs:
        return jobs.submit({**SPEC, "upload_id": upload_id, "avatar_id": avatar_id, **spec},
                           max_attempts=settings.job_max_attempts).id


def events(jobs: JobStore, job_id: str, kind: EventKind | None = None) -> list:
    out, after = [], 0
    while batch := jobs.events(job_id, after_id=after, limit=500):
        out += batch
        after = batch[-1].id
    return [e for e in out if kind is None or e.kind == kind]


def wait_for(predicate, timeout: float, what: str, interval: float = 0.05):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def start_worker(settings: Settings, tmp_path: Path, worker_id: str, *extra: str) -> tuple[subprocess.Popen, Path]:
    """``python -m service.jobs.worker`` as a real process; its log file."""
    env = {**os.environ, "BLENDSPLAT_JOB_LEASE_SECONDS": str(settings.job_lease_seconds),
           "BLENDSPLAT_HEARTBEAT_SECONDS": str(settings.heartbeat_seconds), "PYTHONUNBUFFERED": "1"}
    logfile = tmp_path / f"{worker_id}.log"
    with open(logfile, "wb") as out:
        command = [sys.executable, "-m", "service.jobs.worker", "--data-dir", str(settings.data_dir),
                   "--jobs-url", settings.jobs_database_url, "--worker-id", worker_id, *extra]
        proc = subprocess.Popen(command, cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT)
    return proc, logfile


def checkpoint_iteration(path: str | Path) -> int:
    return int(Path(path).stem.split("_")[1])


def bundle_tensors(path: Path) -> tuple[dict, dict]:
    """A bundle's tensors and its manifest without the creation time."""
    manifest = read_manifest(path)
    manifest["provenance"].pop("created_at", None)
    manifest.pop("digest", None)
    return load_file(str(path)), manifest


@pytest.fixture(scope="module")
def reference(archive, tmp_path_factory):
    """One job trained to success by an in-process worker (also the uninterrupted run the SIGKILL test compares
    with): (settings, worker, job)."""
    settings = make_settings(tmp_path_factory.mktemp("reference"))
    job_id = submit(settings, upload(settings, archive), "ref")
    with Worker(settings, worker_id="reference") as worker:
        t0 = time.perf_counter()
        job = worker.run_one()
        seconds = time.perf_counter() - t0
    assert job is not None and job.id == job_id
    print(f"reference job: {seconds:.1f} s")
    return settings, worker, job


# ------------------------------------------------------------------------------------------------------ success
def test_a_job_trains_commits_its_avatar_and_records_its_progress(reference):
    settings, worker, job = reference
    assert job.state is JobState.SUCCEEDED and job.error is None and job.attempts == 1
    assert job.iteration == 40 and job.total_iterations == 40 and job.fraction == 1.0 and job.gaussians > 0
    # The avatar is in the store, verified, and loads.
    store = BundleStore(settings.bundle_dir)
    path = store.existing("ref")
    assert store.verified(path)
    avatar = read_bundle(path)
    assert avatar.num_gaussians > 0
    result = job.result
    assert set(result) == {"avatar_id", "digest", "evaluation", "final_psnr", "iterations", "seconds"}
    assert result["avatar_id"] == "ref" and result["digest"] == store.manifest("ref")["digest"]
    assert result["iterations"] == 40 and result["seconds"] > 0 and result["final_psnr"] > 5
    assert set(result["evaluation"]) == {"psnr", "ssim", "psnr_head"} and result["evaluation"]["psnr"] > 5
    # The work folder holds the artefacts the REST side serves.
    work = settings.work_dir / job.id
    for name in ("log.jsonl", "summary.json", "curves.png", "report.json", "contact_sheet.png", "preview.png",
                 "avatar.bundle"):
        assert (work / name).is_file(), name
    # The JSON artefacts (served to API clients) name files relative to the work folder: no path of this machine's.
    for name in ("report.json", "summary.json"):
        text = (work / name).read_text()
        assert str(settings.data_dir.resolve()) not in text and str(settings.data_dir) not in text, name
    assert json.loads((work / "report.json").read_text())["contact_sheet"] == "contact_sheet.png"
    summary = json.loads((work / "summary.json").read_text())
    assert summary["bundle"] == "avatar.bundle"
    assert summary["refine"] == {"poses": False, "expressions": False}  # a dataset's tracking is taken as it is
    assert job.checkpoint_path == str(work / "checkpoints" / "ckpt_0000040.pt") and Path(job.checkpoint_path).is_file()
    assert (work / "avatar.bundle").read_bytes() == path.read_bytes()
    assert not list(work.glob(".*"))  # no temporary preview left
    # Events: the states, throttled progress, a preview per checkpoint.
    with JobStore.open(settings.jobs_database_url) as jobs:
        states = [e.data["state"] for e in events(jobs, job.id, EventKind.STATE)]
        progress = [e.data for e in events(jobs, job.id, EventKind.PROGRESS)]
        previews = [e.data for e in events(jobs, job.id, EventKind.PREVIEW)]
        logs = [e.data for e in events(jobs, job.id, EventKind.LOG)]
    assert states == ["queued", "running", "succeeded"]
    assert previews == [{"iteration": i, "path": "preview.png"} for i in range(4, 41, 4)]
    assert progress and progress[-1]["iteration"] == 40 and len(progress) < 40  # at heartbeats, not every step
    assert set(progress[-1]) == {"iteration", "total_iterations", "fraction", "eta_seconds", "loss", "psnr",
                                 "gaussians"}
    assert [p["iteration"] for p in progress] == sorted({p["iteration"] for p in progress})
    assert not any("resumed_from" in e for e in logs)
    # Metrics in the worker's own registry.
    registry = worker.metrics.registry
    assert registry.get_sample_value("blendsplat_worker_jobs_finished_total", {"state": "succeeded"}) == 1
    assert registry.get_sample_value("blendsplat_worker_heartbeats_total", {"result": "ok"}) >= 1
    assert registry.get_sample_value("blendsplat_worker_job_seconds_count", {"state": "succeeded"}) == 1


# ------------------------------------------------------------------------------------------------------ SIGKILL
def test_a_killed_worker_s_job_resumes_on_the_next_worker_and_equals_an_uninterrupted_run(reference, archive,
                                                                                           tmp_path):
    ref_settings, _, ref_job = reference
    settings = make_settings(tmp_path / "data")
    job_id = submit(settings, upload(settings, archive), "killed")
    proc, logfile = start_worker(settings, tmp_path, "doomed")
    jobs = JobStore.open(settings.jobs_database_url)
    try:
        checkpoint = wait_for(lambda: jobs.get(job_id).checkpoint_path, 120, "a checkpoint", interval=0.02)
        os.kill(proc.pid, signal.SIGKILL)
        assert proc.wait(30) == -signal.SIGKILL
        killed = jobs.get(job_id)
        assert killed.state is JobState.RUNNING and killed.lease_owner == "doomed", logfile.read_text()
        assert checkpoint_iteration(checkpoint) >= 4
        # The lease runs out (2 s); the next worker sweeps, claims and resumes from the last checkpoint.
        wait_for(lambda: jobs.get(job_id).lease_expires_at < datetime.now(UTC), 10, "the lease to expire")
        left = last_checkpoint(settings.work_dir / job_id)
        with Worker(settings, worker_id="rescuer") as worker:
            job = worker.run_one()
        assert job.id == job_id and job.state is JobState.SUCCEEDED, job.error
        assert job.attempts == 2
        resumed = [e.data for e in events(jobs, job_id, EventKind.LOG) if "resumed_from" in e.data]
        assert [r["resumed_from"] for r in resumed] == [checkpoint_iteration(left)]
        assert 0 < resumed[0]["resumed_from"] < 40  # trained on after the resume
        print(f"killed at checkpoint {checkpoint_iteration(checkpoint)}, resumed from {resumed[0]['resumed_from']}")
        states = [(e.data["state"], e.data.get("reason")) for e in events(jobs, job_id, EventKind.STATE)]
        assert states == [("queued", None), ("running", None), ("queued", "lease expired"), ("running", None),
                          ("succeeded", None)]
    finally:
        if proc.poll() is None:
            proc.kill()
        jobs.close()
    # The same avatar as the uninterrupted run's: every tensor bit-identical, the manifest equal but its time.
    got = bundle_tensors(BundleStore(settings.bundle_dir).existing("killed"))
    want = bundle_tensors(BundleStore(ref_settings.bundle_dir).existing("ref"))
    assert got[0].keys() == want[0].keys()
    for key in want[0]:
        assert torch.equal(got[0][key], want[0][key]), key
    assert got[1] == want[1]
    assert job.result["final_psnr"] == ref_job.result["final_psnr"]
    assert job.result["evaluation"] == ref_job.result["evaluation"]


# ------------------------------------------------------------------------------------------------------- cancel
def record_steps(monkeypatch) -> list[tuple[float, float, int]]:
    """(start, end, iteration) of every training step from now on, appended as each step ends."""
    steps: list[tuple[float, float, int]] = []
    real_step = Trainer.step

    def step(self):
        start = time.monotonic()
        event = real_step(self)
        steps.append((start, time.monotonic(), event.iteration))
        return event

    monkeypatch.setattr(Trainer, "step", step)
    return steps


def run_one_in_thread(settings) -> tuple[Worker, threading.Thread, dict]:
    """A worker processing one job in a thread; ``outcome["job"]`` is what run_one returned."""
    worker = Worker(settings, worker_id="w")
    outcome: dict = {}
    thread = threading.Thread(target=lambda: outcome.setdefault("job", worker.run_one()))
    thread.start()
    return worker, thread, outcome


def test_cancel_stops_the_job_within_one_iteration(archive, tmp_path, monkeypatch):
    """A cancel requested (by another store connection, as the REST side does) while the worker trains: no
    iteration starts after the request reached the database; the job ends cancelled with its checkpoint."""
    settings = make_settings(tmp_path)
    job_id = submit(settings, upload(settings, archive), "never", iterations=200, checkpoint_every=100)
    steps = record_steps(monkeypatch)
    worker, thread, outcome = run_one_in_thread(settings)
    try:
        with JobStore.open(settings.jobs_database_url) as api:
            wait_for(lambda: len(steps) >= 3, 60, "three iterations", interval=0.01)
            job = api.request_cancel(job_id)
            requested = time.monotonic()
            assert job.state is JobState.RUNNING and job.cancel_requested
            thread.join(60)
            ended = time.monotonic()
    finally:
        thread.join(60)
        worker.close()
    job = outcome["job"]
    assert job.state is JobState.CANCELLED
    assert not [s for s in steps if s[0] > requested]  # no step started after the request
    last = steps[-1][2]
    assert last <= [s for s in steps if s[0] <= requested][-1][2]  # the step in flight was the last
    assert job.error == f"cancelled at iteration {last}"
    work = settings.work_dir / job_id
    assert last_checkpoint(work).name == f"ckpt_{last:07d}.pt" and job.checkpoint_path == str(last_checkpoint(work))
    assert json.loads((work / "log.jsonl").read_text().splitlines()[-1])["iteration"] == last
    assert not BundleStore(settings.bundle_dir).ids() and not (work / "avatar.bundle").exists()
    print(f"cancel: request -> cancelled {ended - requested:.2f} s (a step takes "
          f"{(steps[-1][1] - steps[1][0]) / (len(steps) - 1):.2f} s)")


def test_a_job_deleted_while_it_trains_stops_and_nothing_is_committed(archive, tmp_path, monkeypatch):
    """The job is no longer the worker's (deleted here; a sweep to another worker reads the same): training stops
    before the next iteration, without a final checkpoint, and nothing enters the store."""
    settings = make_settings(tmp_path)
    job_id = submit(settings, upload(settings, archive), "orphan", iterations=5000, checkpoint_every=1000)
    steps = record_steps(monkeypatch)
    worker, thread, outcome = run_one_in_thread(settings)
    try:
        with JobStore.open(settings.jobs_database_url) as api:
            wait_for(lambda: len(steps) >= 3, 60, "three iterations", interval=0.01)
            api.delete(job_id)
            deleted = time.monotonic()
            thread.join(60)
    finally:
        thread.join(60)
        worker.close()
    assert not thread.is_alive() and outcome["job"] is None
    assert not [s for s in steps if s[0] > deleted]
    assert not list((settings.work_dir / job_id / "checkpoints").glob("*.pt"))  # no final checkpoint
    assert not BundleStore(settings.bundle_dir).ids()
    assert worker.metrics.registry.get_sample_value("blendsplat_worker_jobs_finished_total", {"state": "lost"}) == 1


# ------------------------------------------------------------------------------------------------------ SIGTERM
def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_sigterm_checkpoints_and_hands_the_job_back_then_it_resumes(archive, tmp_path):
    settings = make_settings(tmp_path / "data")
    upload_id = upload(settings, archive)
    port = free_port()
    proc, logfile = start_worker(settings, tmp_path, "leaving", "--metrics-port", str(port))
    jobs = JobStore.open(settings.jobs_database_url)
    try:
        wait_for(lambda: "started" in logfile.read_text(), 60, "the worker to start")
        time.sleep(0.3)  # idle: waiting for work
        submitted = time.monotonic()
        job_id = submit(settings, upload_id, "later", iterations=5000)
        wait_for(lambda: jobs.get(job_id).state is JobState.RUNNING, 10, "the claim", interval=0.01)
        latency = time.monotonic() - submitted
        wait_for(lambda: jobs.get(job_id).checkpoint_path, 120, "a checkpoint", interval=0.02)
        scraped = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10).read().decode()
        assert "blendsplat_worker_heartbeats_total" in scraped
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(60) == 0, logfile.read_text()
        job = jobs.get(job_id)
        assert job.state is JobState.QUEUED and job.attempts == 0 and job.lease_owner is None
        assert Path(job.checkpoint_path) == last_checkpoint(settings.work_dir / job_id)
        stopped_at = checkpoint_iteration(job.checkpoint_path)
        assert 4 <= stopped_at < 5000
        last_state = events(jobs, job_id, EventKind.STATE)[-1].data
        assert last_state["state"] == "queued" and last_state["reason"] == "released"
        # The next worker resumes from that checkpoint (attempt 1 again, but the work folder has a checkpoint);
        # stopped at once, it hands the job back at the same iteration.
        stop = threading.Event()
        stop.set()
        with Worker(settings, worker_id="next") as worker:
            job = worker.run_one(stop)
        assert job.state is JobState.QUEUED and job.attempts == 0
        resumed = [e.data for e in events(jobs, job_id, EventKind.LOG) if "resumed_from" in e.data]
        assert [r["resumed_from"] for r in resumed] == [stopped_at]
        assert checkpoint_iteration(job.checkpoint_path) == stopped_at
    finally:
        if proc.poll() is None:
            proc.kill()
        jobs.close()
    assert latency <= 2.0
    print(f"submit -> running with an idle worker: {latency:.2f} s")


# ----------------------------------------------------------------------------------------------------- failures
def test_failing_jobs_end_failed_with_the_reason(archive, tmp_path):
    settings = make_settings(tmp_path)
    uploads = UploadStore(settings.upload_dir)
    gone = upload(settings, archive)
    flame = upload(settings, archive)
    record = settings.upload_dir / flame / "upload.json"  # as if the dataset had been tracked with FLAME
    record.write_text(json.dumps({**json.loads(record.read_text()), "face_model": "flame-2023"}))
    deleted = submit(settings, gone, "a")
    no_model = submit(settings, flame, "b")
    bad = submit(settings, flame, "c", preset="huge")
    uploads.delete(gone)
    with Worker(settings, worker_id="w") as worker:
        finished = {job.id: job for job in (worker.run_one(), worker.run_one(), worker.run_one())}
        assert worker.run_one() is None
        assert worker.metrics.registry.get_sample_value("blendsplat_worker_jobs_finished_total",
                                                        {"state": "failed"}) == 3
    assert {j.state for j in finished.values()} == {JobState.FAILED}
    assert finished[deleted].error.startswith("NotFound: spec.upload_id: ")
    assert gone in finished[deleted].error and "does not exist" in finished[deleted].error
    assert finished[no_model].error.startswith("NotFound: face_model: ")
    assert "'flame-2023'" in finished[no_model].error and "facemodels/flame-2023" in finished[no_model].error
    assert str(settings.data_dir.absolute()) not in finished[no_model].error  # clients read it: no server path
    assert finished[bad].error.startswith("InvalidArgument: spec.preset: ") and "'huge'" in finished[bad].error
    assert all(len(j.error) <= 2000 and j.result is None for j in finished.values())
    assert not BundleStore(settings.bundle_dir).ids()


def test_spec_checks_and_the_command_options():
    spec = JobSpec.parse({"upload_id": "upl_" + "a" * 22, "preset": "paper", "iterations": None, "avatar_id": "x",
                          "resolution": 256, "future": 1})
    assert spec.seed == 0 and spec.iterations is None and spec.resolution == 256 and not spec.preset_overrides()
    for key, value in (("iterations", 0), ("seed", -1), ("seed", True), ("avatar_id", "../x"), ("upload_id", "x"),
                       ("checkpoint_every", 1.5), ("iterations", 1_000_001), ("iterations", "30"), ("resolution", 8),
                       ("resolution", 8193), ("seed", 2**32), ("preset", "huge"), ("avatar_id", "x.tmp"),
                       ("gaussians", 200_001), ("mouth", 0), ("webhook_url", "ftp://example.com/x")):
        with pytest.raises(InvalidArgument, match=f"spec.{key}"):
            JobSpec.parse({"upload_id": "upl_" + "a" * 22, "preset": "tiny", "avatar_id": "x", key: value})
    assert set(typing.get_args(JobSpec.model_fields["preset"].annotation)) == set(PRESETS)
    args = add_arguments(argparse.ArgumentParser()).parse_args([])
    assert vars(args) == {"device": "cpu", "data_dir": None, "jobs_url": None, "worker_id": None, "once": False,
                          "metrics_port": 0}
    args = add_arguments(argparse.ArgumentParser()).parse_args(
        ["--device", "cuda", "--data-dir", "/d", "--jobs-url", "sqlite:///j.db", "--worker-id", "w", "--once",
         "--metrics-port", "9100"])
    assert (args.device, args.data_dir, args.jobs_url, args.worker_id, args.once, args.metrics_port) == (
        "cuda", Path("/d"), "sqlite:///j.db", "w", True, 9100)


# --------------------------------------------------------------------------------------------------- resolution
def _png_size(path: Path) -> tuple[int, int]:
    header = path.read_bytes()[:24]
    assert header[:8] == b"\x89PNG\r\n\x1a\n"
    return int.from_bytes(header[16:20], "big"), int.from_bytes(header[20:24], "big")


def test_a_job_trains_at_its_resolution(archive, tmp_path, monkeypatch):
    """``resolution`` 32 on the 64 x 64 dataset: the Trainer the worker builds trains on the dataset resampled to
    32 x 32 (targets, cameras, preview and summary at that size), its intrinsics halved, and the job says so."""
    settings = make_settings(tmp_path)
    upload_id = upload(settings, archive)
    job_id = submit(settings, upload_id, "half", resolution=32, iterations=4, checkpoint_every=4)
    trained: list[tuple[Path, int, int]] = []
    real_init = Trainer.__init__

    def spy(self, data_dir, *args, **kwargs):
        real_init(self, data_dir, *args, **kwargs)
        trained.append((Path(data_dir), self.dataset.tracking.width, self.dataset.tracking.height))

    monkeypatch.setattr(Trainer, "__init__", spy)
    with Worker(settings, worker_id="w") as worker:
        job = worker.run_one()
    assert job.id == job_id and job.state is JobState.SUCCEEDED, job.error
    work = settings.work_dir / job_id
    assert [(size, height) for _, size, height in trained] == [(32, 32)]
    data_dir = trained[0][0]
    assert data_dir == work / "dataset_32x32"
    assert json.loads((work / "summary.json").read_text())["size"] == [32, 32]
    assert _png_size(work / "preview.png") == _png_size(work / "truth.png") == (32, 32)
    original, resized = read_dataset(UploadStore(settings.upload_dir).path(upload_id)), read_dataset(data_dir)
    assert (resized.tracking.width, resized.tracking.height, len(resized)) == (32, 32, len(original))
    assert np.allclose(resized.tracking.K[:, :2], original.tracking.K[:, :2] / 2, atol=1e-5)
    assert np.array_equal(resized.tracking.K[:, 2], original.tracking.K[:, 2])
    for name in ("R", "t", "expression", "joint_rotations", "eyelids", "train", "test"):
        assert np.array_equal(getattr(resized.tracking, name), getattr(original.tracking, name)), name
    assert resized.frame(0).shape == (32, 32, 3) and resized.mask(0).shape == (32, 32)
    assert abs(float(resized.frame(0).mean()) - float(original.frame(0).mean())) < 2 / 255  # filtered, not picked
    with JobStore.open(settings.jobs_database_url) as jobs:
        notes = [e.data for e in events(jobs, job_id, EventKind.LOG) if "resolution" in e.data]
    assert notes == [{"message": "resolution 32: training at 32x32 (the dataset is 64x64)", "resolution": 32,
                      "width": 32, "height": 32}]


def test_resampling_a_dataset_keeps_the_picture_and_the_cameras(archive, tmp_path):
    assert training_size(640, 480, 320) == (320, 240)
    assert training_size(480, 640, 100) == (75, 100)
    assert training_size(640, 480, None) == training_size(640, 480, 640) == training_size(640, 480, 4096) == (640, 480)
    # a flat image stays flat; detail finer than the new pixels averages out instead of aliasing
    assert np.allclose(resample(np.full((64, 48, 3), 0.25, np.float32), 24, 32), 0.25)
    stripes = np.zeros((64, 64), np.float32)
    stripes[:, ::2] = 1.0
    smooth = resample(stripes, 16, 16)
    assert np.allclose(smooth[:, 1:-1], 0.5, atol=1e-3) and np.allclose(smooth, 0.5, atol=0.05)  # edges: clamped
    # a point keeps its place in the picture (pixel origin at the top-left corner)
    K = np.array([[[500.0, 0.0, 321.0], [0.0, 480.0, 239.0], [0.0, 0.0, 1.0]]], np.float32)
    point = np.array([0.05, -0.03, 0.6], np.float32)
    u, v, w = K[0] @ point
    u2, v2, w2 = scaled_intrinsics(K, 320 / 640, 240 / 480)[0] @ point
    assert np.allclose([u2 / w2 / 320, v2 / w2 / 240], [u / w / 640, v / w / 480])
    # the dataset: its own folder when it is no larger, else one resampled copy, reused (a resumed job's)
    settings = make_settings(tmp_path)
    source = UploadStore(settings.upload_dir).path(upload(settings, archive))
    assert dataset_at(source, 64, tmp_path) == (source, (64, 64), (64, 64))
    first = dataset_at(source, 48, tmp_path / "work")
    assert first == (tmp_path / "work" / "dataset_48x48", (48, 48), (64, 64))
    stamp = (first[0] / "dataset.json").stat().st_mtime_ns
    assert dataset_at(source, 48, tmp_path / "work") == first
    assert (first[0] / "dataset.json").stat().st_mtime_ns == stamp
