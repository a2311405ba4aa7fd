"""Hardening, second round (issue 28): the storage quota charges what is stored, and the smaller findings of 9.

Finding 5: an upload counts as extracted, not as its archive (a small archive of zeros no longer passes the quota);
an extraction out of proportion to its archive (zeros, or a swarm of tiny files) is refused before it is written;
a tenant's uploads are bounded in files; a job's work folder counts, a running job that takes its tenant past the
quota fails, and an over-quota tenant cannot submit; open streams' Redis leases come back after Redis restarts
empty. Finding 9: a killed server's upload temp files and unfinished deletions go at the next start (an upload
another process is receiving is spared), a torn checkpoint's temp file goes when the job resumes, idempotent
replays and 409s do not use the hourly job allowance, and deleting a 100,000-file upload does not block.

Against real servers (tests/conftest.py's LiveServer; a `blendsplat serve` process where it is killed), a real
worker, the real trainer and the real Redis at 127.0.0.1:6379 (database 9, a prefix of the test's own)."""

from __future__ import annotations

import asyncio
import io
import os
import secrets
import socket
import tarfile
import threading
import time
import uuid
from datetime import timedelta
from pathlib import Path

import httpx
import pytest
import torch
from conftest import LiveServer

from render_core.data.generate import synth_dataset
from render_core.train import Trainer, get_preset
from render_core.train.trainer import checkpoint_dir, last_checkpoint
from service.access.limits import RateLimited, RedisLimits
from service.jobs.models import JobRecord
from service.jobs.uploads import UploadStore

QUOTA = 8 << 20  # tenant_storage_bytes of the module's server (a tiny job's work folder is about 120 MB)
MAX_FILES = 100  # tenant_max_files: the tiny dataset upload is 31 entries on disk
REDIS_URL = "redis://127.0.0.1:6379/9"  # never database 0


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    s = LiveServer(tmp_path_factory.mktemp("quota") / "data", auth="keys", tenant_storage_bytes=QUOTA,
                   tenant_max_files=MAX_FILES, key_jobs_per_hour=2)
    yield s
    s.stop()


@pytest.fixture(scope="module")
def http(server):
    with httpx.Client(base_url=server.http_url, timeout=120) as client:
        yield client


def key(server, tenant: str) -> dict:
    return {"Authorization": f"Bearer {server.keys.create(tenant, ('jobs',))[1]}"}


def with_extra(archive: bytes, extra: list[tuple[str, bytes]]) -> bytes:
    """The tiny dataset archive (its members under ``video/``) with ``extra`` files added to the dataset folder."""
    out = io.BytesIO()
    with tarfile.open(fileobj=io.BytesIO(archive), mode="r:gz") as src, \
            tarfile.open(fileobj=out, mode="w:gz") as dst:
        for member in src.getmembers():
            dst.addfile(member, src.extractfile(member) if member.isfile() else None)
        for name, data in extra:
            info = tarfile.TarInfo(f"video/{name}")
            info.size = len(data)
            dst.addfile(info, io.BytesIO(data))
    return out.getvalue()


def post(http, headers: dict, archive: bytes) -> httpx.Response:
    return http.post("/v1/uploads", files={"file": ("v.tgz", archive)}, headers=headers)


def temp_entries(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith(".")) if folder.is_dir() else []


def tenant_uploads(server, tenant: str) -> list[str]:
    return [u.id for u in server.service.training.uploads.list() if u.tenant == tenant]


# ------------------------------------------------------------------------------------ 5. bytes stored
def test_an_upload_counts_against_the_quota_as_extracted_not_as_its_archive(server, http, tiny_video_archive):
    headers = key(server, "inflated")
    archive = with_extra(tiny_video_archive, [("padding.bin", bytes(QUOTA + (1 << 20)))])
    assert len(archive) < QUOTA // 50  # the archive is small; its extraction is not (under the ratio's 16 MiB)
    r = post(http, headers, archive)
    assert r.status_code == 429 and "quota" in r.json()["error"]["message"], r.text
    assert tenant_uploads(server, "inflated") == []
    assert temp_entries(server.service.settings.upload_dir) == []  # nothing kept, extracted or not
    ok = post(http, headers, tiny_video_archive)
    assert ok.status_code == 201, ok.text
    record = server.service.training.uploads.get(ok.json()["upload_id"])
    assert record.stored_bytes >= sum(p.stat().st_size for p in server.service.training.uploads.path(
        record.id).rglob("*") if p.is_file()) and record.files > 20


def test_an_extraction_out_of_proportion_to_its_archive_is_refused_and_nothing_is_kept(server, http,
                                                                                       tiny_video_archive):
    """Both shapes of the probe's hostile archives, each between the old ratio bound (200, on the members' bytes)
    and max_extraction_ratio (50, on what they take on disk): zeros behind some incompressible bytes (3.6 MB became
    402 MB), and a swarm of empty files (1.48 MB became 394 MB and 100,000 inodes). Refused even for an admin key
    (the quota spares it, the ratio does not); an honest dataset passes."""
    upload_dir = server.service.settings.upload_dir
    before = set(tenant_uploads(server, "admin"))
    zeros = with_extra(tiny_video_archive, [("noise.bin", os.urandom(320 << 10)), ("zeros.bin", bytes(20 << 20))])
    out = io.BytesIO()
    with tarfile.open(fileobj=out, mode="w:gz") as tar:  # the swarm: empty files only
        tar.addfile(tarfile.TarInfo("video/dataset.json"), io.BytesIO(b""))
        for i in range(20_000):
            tar.addfile(tarfile.TarInfo(f"video/f/{i:05d}"), io.BytesIO(b""))
    swarm = out.getvalue()
    for archive in (zeros, swarm):
        r = post(http, server.headers, archive)
        error = r.json()["error"]
        assert r.status_code == 422 and error["field"] == "file", r.text
        assert "max_extraction_ratio" in error["message"] and "bomb" in error["message"], r.text
        assert set(tenant_uploads(server, "admin")) == before and temp_entries(upload_dir) == []
    assert post(http, server.headers, tiny_video_archive).status_code == 201


def test_a_tenants_uploads_are_bounded_in_files(server, http, tiny_video_archive):
    headers = key(server, "many-files")
    kept = []
    while True:
        r = post(http, headers, tiny_video_archive)
        if r.status_code != 201:
            break
        kept.append(r.json()["upload_id"])
        assert len(kept) <= MAX_FILES // 20, "the file bound never refused an upload"
    assert r.status_code == 429 and "tenant_max_files" in r.json()["error"]["message"], r.text
    files = sum(server.service.training.uploads.get(u).files for u in kept)
    assert files <= MAX_FILES < files + server.service.training.uploads.get(kept[0]).files
    assert sorted(tenant_uploads(server, "many-files")) == sorted(kept)
    assert http.delete(f"/v1/uploads/{kept[0]}", headers=headers).status_code == 204
    assert post(http, headers, tiny_video_archive).status_code == 201  # room again


def test_a_jobs_work_folder_counts_and_a_job_past_the_quota_fails(server, http, tiny_video_archive):
    """The job trains until its first checkpoint takes the tenant past its quota: it fails with the named error and
    commits nothing; its work folder, recorded on its row, keeps the tenant over the quota (uploads and job
    submissions refused) until the job is deleted."""
    from service.jobs.worker import Worker

    headers = key(server, "trainer")
    upload = post(http, headers, tiny_video_archive).json()["upload_id"]
    r = http.post("/v1/jobs", json={"upload_id": upload, "preset": "tiny", "iterations": 6, "checkpoint_every": 2,
                                    "avatar_id": "over-quota"}, headers=headers)
    assert r.status_code == 201, r.text
    job_id = r.json()["id"]
    with Worker(server.service.settings, worker_id="quota-worker") as worker:
        assert worker.run_one().id == job_id
    job = http.get(f"/v1/jobs/{job_id}", headers=headers).json()
    assert job["state"] == "failed" and job["error"].startswith("StorageQuotaExceeded: "), job
    assert "tenant_storage_bytes" in job["error"], job
    work = server.service.settings.work_dir / job_id
    assert last_checkpoint(work).name == "ckpt_0000002.pt"  # it failed at its first checkpoint, not at the end
    assert http.get("/v1/avatars/over-quota", headers=server.headers).status_code == 404  # nothing committed
    jobs = server.service.training.jobs
    with jobs.engine.connect() as connection:
        recorded = connection.execute(JobRecord.__table__.select().where(JobRecord.id == job_id)).first().work_bytes
    assert recorded > QUOTA and jobs.tenant_work_bytes("trainer") == recorded
    r = post(http, headers, tiny_video_archive)
    assert r.status_code == 429 and "quota" in r.json()["error"]["message"], r.text
    r = http.post("/v1/jobs", json={"upload_id": upload, "preset": "tiny", "iterations": 6, "avatar_id": "again"},
                  headers=headers)
    assert r.status_code == 429 and "quota" in r.json()["error"]["message"], r.text
    with jobs.engine.begin() as connection:  # as a job recorded before work folders counted
        connection.execute(JobRecord.__table__.update().where(JobRecord.id == job_id).values(work_bytes=None))
    assert jobs.tenant_work_bytes("trainer") == 0
    server.service.training.sweep()  # retention measures such a work folder once
    assert jobs.tenant_work_bytes("trainer") == recorded
    assert http.delete(f"/v1/jobs/{job_id}", headers=headers).status_code == 204
    assert jobs.tenant_work_bytes("trainer") == 0
    assert post(http, headers, tiny_video_archive).status_code == 201


@pytest.fixture
def redis_url():
    try:
        socket.create_connection(("127.0.0.1", 6379), timeout=2).close()
    except OSError as e:
        pytest.skip(f"Redis at 127.0.0.1:6379 is unreachable ({e})")
    return REDIS_URL


def test_open_streams_are_counted_again_after_redis_restarts_empty(redis_url):
    """Two replicas: one holds a key's 3 streams (its limit). Redis loses everything (a restart without
    persistence: the test's keys deleted); within seconds the holder has written its leases back, so the other
    replica is refused again, and a release still frees a slot."""
    import redis

    prefix = f"blendsplat-test:{uuid.uuid4().hex[:8]}:"
    holder = RedisLimits(redis_url, prefix=prefix, lease_seconds=3.0, renew_seconds=0.2)
    other = RedisLimits(redis_url, prefix=prefix, lease_seconds=3.0, renew_seconds=0.2)
    direct = redis.Redis.from_url(redis_url)
    try:
        releases = [holder.take_stream("k1", 3) for _ in range(3)]
        with pytest.raises(RateLimited):
            other.take_stream("k1", 3)
        lost = direct.keys(f"{prefix}*")
        assert lost and direct.delete(*lost)  # Redis restarted empty
        assert direct.zcard(f"{prefix}streams:k1") == 0
        deadline = time.monotonic() + 5
        while direct.zcard(f"{prefix}streams:k1") < 3:
            assert time.monotonic() < deadline, "the open streams' leases never came back"
            time.sleep(0.05)
        assert direct.ttl(f"{prefix}streams:k1") > 0  # a dead replica's leases still expire
        with pytest.raises(RateLimited):
            other.take_stream("k1", 3)
        releases[0]()
        deadline = time.monotonic() + 5
        while True:
            try:
                other.take_stream("k1", 3)()
                break
            except RateLimited:
                assert time.monotonic() < deadline, "the released stream's slot never came back"
                time.sleep(0.05)
        time.sleep(0.5)  # a few renewals later the released lease is still gone
        assert direct.zcard(f"{prefix}streams:k1") == 2
    finally:
        holder.close()
        other.close()
        leftover = direct.keys(f"{prefix}*")
        if leftover:
            direct.delete(*leftover)
        direct.close()


# ------------------------------------------------------------------------------------ 9. the smaller ones
def test_a_killed_servers_upload_temp_files_and_unfinished_deletions_go_at_the_next_start(tmp_path,
                                                                                         tiny_video_archive):
    from tests.test_hardening_resources import Serve, _raw

    data = tmp_path / "data"
    uploads = data / "uploads"
    a = Serve(data)
    try:
        boundary = "killed"
        head = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"v.tgz\"\r\n\r\n").encode()
        s = _raw(a.http_port, b"POST /v1/uploads HTTP/1.1\r\nHost: x\r\n" + a.auth
                 + f"Content-Type: multipart/form-data; boundary={boundary}\r\nContent-Length: 900000\r\n\r\n".encode(),
                 head + tiny_video_archive[:4000])
        deadline = time.monotonic() + 10
        while not any(n.endswith(".tmp") for n in temp_entries(uploads)):
            assert time.monotonic() < deadline, "the upload never reached the disk"
            time.sleep(0.05)
        a.proc.kill()
        a.proc.wait()
        s.close()
    finally:
        a.stop()
    assert [n for n in temp_entries(uploads) if n.startswith(".incoming-") and n.endswith(".tmp")]
    doomed = uploads / ".deleting-upl_killedmidway0000000-0a1b2c3d"  # a deletion the killed server had not finished
    (doomed / "dataset").mkdir(parents=True)
    for i in range(200):
        (doomed / "dataset" / f"{i}.png").write_bytes(b"x")
    b = Serve(data)
    try:
        assert not [n for n in temp_entries(uploads) if not n.startswith(".deleting-")]  # gone before it is ready
        deadline = time.monotonic() + 30
        while temp_entries(uploads):
            assert time.monotonic() < deadline, f"the trash was never emptied: {temp_entries(uploads)}"
            time.sleep(0.1)
        assert "uploads: removed 1 leftovers of interrupted uploads" in b.output()
    finally:
        b.stop()


def test_cleaning_spares_an_upload_another_process_is_receiving(tmp_path, tiny_video_archive):
    """Two stores on one folder (two replicas): one cleans, with no grace at all, while the other receives; the
    upload in progress keeps its files and is published."""
    root = tmp_path / "uploads"
    receiver, cleaner = UploadStore(root), UploadStore(root)
    go = threading.Event()

    async def body():
        yield tiny_video_archive[:1000]
        await asyncio.to_thread(go.wait, 30)
        yield tiny_video_archive[1000:]

    result: dict = {}
    thread = threading.Thread(target=lambda: result.update(upload=asyncio.run(receiver.receive(
        body(), max_bytes=1 << 30))))
    thread.start()
    deadline = time.monotonic() + 10
    while not any(n.endswith(".tmp") for n in temp_entries(root)):
        assert time.monotonic() < deadline
        time.sleep(0.02)
    assert cleaner.clean_stale(timedelta(0)) == 0 and any(n.endswith(".tmp") for n in temp_entries(root))
    go.set()
    thread.join(30)
    assert result["upload"].frames == 12 and temp_entries(root) == []


@pytest.fixture(scope="module")
def toy(head, tmp_path_factory):
    out = tmp_path_factory.mktemp("toy") / "data"
    synth_dataset(out, frames=6, size=64, seed=1, facemodel=head)
    return out


def test_a_torn_checkpoint_leaves_no_temp_file_and_a_resumed_run_removes_a_killed_ones(toy, head, tmp_path,
                                                                                     monkeypatch):
    preset = get_preset("tiny").with_(gaussians=300, mouth=20, checkpoint_every=1000, log_every=1)
    work = tmp_path / "work"
    first = Trainer(toy, work, preset, iterations=4, seed=3, facemodel=head)
    first.step()
    good = first.checkpoint()
    first.step()
    real_save = torch.save

    def torn(state, path, *args, **kwargs):  # the disk fills halfway through the write
        Path(path).write_bytes(b"half a checkpoint")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch, "save", torn)
    with pytest.raises(OSError, match="No space left"):
        first.checkpoint()
    monkeypatch.setattr(torch, "save", real_save)
    assert sorted(p.name for p in checkpoint_dir(work).iterdir()) == [good.name]  # the failed write left nothing
    # what a SIGKILL mid-write leaves (no exception handler ran): its temporary files stay, until the job resumes
    killed = [checkpoint_dir(work) / f".ckpt_0000002.pt.{secrets.token_hex(8)}.tmp",
              work / f".summary.json.{secrets.token_hex(8)}.tmp"]
    for path in killed:
        path.write_bytes(b"torn")
    resumed = Trainer(toy, work, preset, iterations=4, facemodel=head)
    assert resumed.resume() and resumed.iteration == 1
    assert not any(p.exists() for p in killed)
    assert sorted(p.name for p in checkpoint_dir(work).iterdir()) == [good.name] and last_checkpoint(work) == good


def test_idempotent_replays_and_conflicts_do_not_use_the_hourly_job_allowance(server, http, tiny_video_archive):
    headers = key(server, "replayer")  # key_jobs_per_hour = 2 on this server
    upload = post(http, headers, tiny_video_archive).json()["upload_id"]
    spec = {"upload_id": upload, "preset": "tiny", "iterations": 5, "avatar_id": "replayed"}

    def submit(idempotency: str, **changes) -> httpx.Response:
        return http.post("/v1/jobs", json={**spec, **changes}, headers=headers | {"Idempotency-Key": idempotency})

    first = submit("k1")
    assert first.status_code == 201, first.text
    for _ in range(3):
        replay = submit("k1")
        assert replay.status_code == 200 and replay.json()["id"] == first.json()["id"], replay.text
    for _ in range(2):
        assert submit("k1", avatar_id="other").status_code == 409
    second = submit("k2")
    assert second.status_code == 201, second.text  # the allowance's second job
    third = submit("k3")
    assert third.status_code == 429 and "job submissions" in third.json()["error"]["message"], third.text
    assert submit("k1").status_code == 200  # a replay is still answered
    for job in (first, second):
        assert http.delete(f"/v1/jobs/{job.json()['id']}", headers=headers).status_code == 204


def test_deleting_a_100k_file_upload_answers_at_once_and_its_files_go_in_the_background(server, http,
                                                                                       tiny_video_archive):
    uploads = server.service.training.uploads
    upload_id = post(http, server.headers, tiny_video_archive).json()["upload_id"]
    folder = uploads.path(upload_id)
    for d in range(100):  # as a dataset of 100,000 small files would be
        (folder / "extra" / f"{d:03d}").mkdir(parents=True)
        for i in range(1000):
            os.close(os.open(folder / "extra" / f"{d:03d}" / f"{i:04d}", os.O_WRONLY | os.O_CREAT, 0o644))
    monkey_wait, uploads.trash.wait = uploads.trash.wait, 0.0  # measure the deletion itself, not the grace wait
    try:
        t0 = time.monotonic()
        r = http.delete(f"/v1/uploads/{upload_id}", headers=server.headers)
        elapsed = time.monotonic() - t0
    finally:
        uploads.trash.wait = monkey_wait
    assert r.status_code == 204 and elapsed < 5, (r.status_code, elapsed)
    assert http.get(f"/v1/uploads/{upload_id}", headers=server.headers).status_code == 404  # gone at once
    assert upload_id not in {u["upload_id"] for u in http.get("/v1/uploads", headers=server.headers).json()["uploads"]}
    in_trash = [n for n in temp_entries(uploads.root) if n.startswith(f".deleting-{upload_id}-")]
    assert in_trash, "the files were removed before the answer (the deletion blocked)"
    assert uploads.trash.drain(120) and temp_entries(uploads.root) == []
