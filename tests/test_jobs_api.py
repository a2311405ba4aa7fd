"""The training jobs' REST API (service/jobs/api.py) against real `blendsplat serve` processes: the embedded SQLite
job database and PostgreSQL (127.0.0.1:5432, a database of the test module's own, dropped after; skipped with the
reason when unreachable). Uploads (tar.gz, zip, hostile, too large), jobs (submit, read, pages, state filter,
Idempotency-Key, cancel, artefacts), real deletion (files and rows gone), restart and retention at start, metrics;
and `blendsplat up` end to end: an upload trains in its worker child and the avatar streams over gRPC.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import secrets
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import grpc
import httpx
import pytest
from conftest import postgres_database
from test_archive import HOSTILE, make_dataset, tar_archive, zip_archive

from blendsplat.v1 import render_pb2 as pb
from blendsplat.v1 import render_pb2_grpc as pb_grpc
from render_core.bundle import write_bundle
from render_core.tools.synth import synth_avatar
from service.errors import NotFound
from service.jobs import JobStore

ROOT = Path(__file__).resolve().parents[1]
MAX_DATASET_BYTES = 1 << 20  # the test servers' upload limit
READY = re.compile(r"ready: gRPC on port (\d+), HTTP on port (\d+)")
ENV = {"BLENDSPLAT_DEMO_AVATAR": "none", "BLENDSPLAT_WARMUP_SIZE": "32", "BLENDSPLAT_DRAIN_SECONDS": "1",
       "BLENDSPLAT_MAX_DATASET_BYTES": str(MAX_DATASET_BYTES), "PYTHONUNBUFFERED": "1"}


class ServerProcess:
    """A real `blendsplat <command>` process (serve or up) on free loopback ports, logging to a file."""

    def __init__(self, data_dir: Path, jobs_url: str | None = None, command: str = "serve", **env: str):
        self.data_dir, self.jobs_url = Path(data_dir), jobs_url
        self.data_dir.mkdir(parents=True, exist_ok=True)
        environment = {k: v for k, v in os.environ.items() if not k.startswith("BLENDSPLAT_")}
        environment.update(ENV)
        environment.update(env)
        if jobs_url:
            environment["BLENDSPLAT_JOBS_URL"] = jobs_url
        self.log = self.data_dir.parent / f"{self.data_dir.name}-{command}-{secrets.token_hex(3)}.log"
        with open(self.log, "wb") as out:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "service.cli", command, "--grpc-port", "0", "--http-port", "0", "--data-dir",
                 str(self.data_dir), "--host", "127.0.0.1"], cwd=ROOT, env=environment, stdout=out,
                stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 120
        while not (match := READY.search(self.output())):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.proc.kill()
                pytest.fail(f"`blendsplat {command}` did not become ready:\n{self.output()[-3000:]}")
            time.sleep(0.1)
        self.grpc_target = f"127.0.0.1:{match.group(1)}"
        self.url = f"http://127.0.0.1:{match.group(2)}"
        self.key = (data_dir / "admin.key").read_text().strip()  # secure by default: the admin key it made
        self.http = httpx.Client(base_url=self.url, timeout=60, headers={"Authorization": f"Bearer {self.key}"})

    def output(self) -> str:
        return self.log.read_text(errors="replace")

    def stop(self) -> int:
        self.http.close()
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout=60)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait()


# ------------------------------------------------------------------------------------------------- fixtures
@contextlib.contextmanager
def job_database(kind: str, pg_admin_user) -> Iterator[str | None]:
    """A job database for a server: None (the embedded SQLite file in its data dir) or the URL of a fresh
    PostgreSQL database, dropped afterwards (the test skips, saying why, when PostgreSQL is unreachable)."""
    if kind == "sqlite":
        yield None
        return
    with postgres_database(pg_admin_user, "blendsplat_api_test") as url:
        yield url


DATABASES = ["sqlite", pytest.param("postgresql", marks=pytest.mark.external)]


@pytest.fixture(scope="module", params=DATABASES)
def jobs_url(request, pg_admin_user):
    """The job database of the module's server."""
    with job_database(request.param, pg_admin_user) as url:
        yield url


@pytest.fixture(scope="module")
def server(jobs_url, tmp_path_factory):
    proc = ServerProcess(tmp_path_factory.mktemp("api") / "data", jobs_url)
    yield proc
    assert proc.stop() == 0


@pytest.fixture(scope="module")
def db(server):
    """The server's job database, opened by the test (to check rows are gone)."""
    with JobStore.open(server.jobs_url or f"sqlite:///{(server.data_dir / 'jobs.db').absolute()}") as store:
        yield store


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> dict[str, bytes]:
    """A valid portable dataset (4 frames of 32 x 32), by relative path."""
    root = make_dataset(tmp_path_factory.mktemp("dataset") / "ds")
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def archives(dataset, tmp_path_factory) -> dict[str, bytes]:
    folder = tmp_path_factory.mktemp("archives")
    return {"tar.gz": tar_archive(folder / "a.tgz", dataset, prefix="take/", gz=True).read_bytes(),
            "zip": zip_archive(folder / "a.zip", dataset).read_bytes()}


def post_upload(server: ServerProcess, data, name: str = "take.tgz") -> httpx.Response:
    return server.http.post("/v1/uploads", files={"file": (name, data, "application/octet-stream")})


def upload(server: ServerProcess, archives) -> str:
    r = post_upload(server, archives["tar.gz"])
    assert r.status_code == 201, r.text
    return r.json()["upload_id"]


def submit(server: ServerProcess, upload_id: str, key: str | None = None, **spec) -> httpx.Response:
    headers = {"Idempotency-Key": key} if key else {}
    return server.http.post("/v1/jobs", json={"upload_id": upload_id, "avatar_id": "ada", **spec}, headers=headers)


def error(r: httpx.Response, status: int, code: str, field: str | None = None) -> str:
    assert r.status_code == status, r.text
    body = r.json()["error"]
    assert body["code"] == code, body
    if field is not None:
        assert body["field"] == field, body
    return body["message"]


def upload_entries(server: ServerProcess) -> list[str]:
    return sorted(p.name for p in (server.data_dir / "uploads").iterdir())


# ---------------------------------------------------------------------------------------------------- uploads
@pytest.mark.parametrize("kind", ["tar.gz", "zip"])
def test_an_upload_is_streamed_validated_and_published(server, archives, kind):
    raw = archives[kind]
    r = post_upload(server, raw, f"C:\\takes\\take.{kind}")
    assert r.status_code == 201, r.text
    body = r.json()
    upload_id = body["upload_id"]
    assert r.headers["location"] == f"/v1/uploads/{upload_id}" == body["links"]["self"]
    assert (body["size"], body["frames"], body["width"], body["height"], body["face_model"]) == (
        len(raw), 4, 32, 32, "flame")
    assert body["archive"] == kind and body["filename"] == f"take.{kind}" and len(body["sha256"]) == 64
    assert server.http.get(f"/v1/uploads/{upload_id}").json() == body
    assert upload_id in {u["upload_id"] for u in server.http.get("/v1/uploads").json()["uploads"]}
    folder = server.data_dir / "uploads" / upload_id
    assert sorted(p.name for p in folder.iterdir()) == ["dataset", "upload.json"]  # the archive is not kept


def test_a_multipart_body_in_small_odd_pieces_with_other_fields(server, archives):
    """The streaming parser across piece boundaries (headers, boundary and data split anywhere), form fields
    before and after the file."""
    boundary = "x-7f3a"
    head = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"note\"\r\n\r\nfirst take\r\n"
            f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"t.zip\"\r\n"
            f"Content-Type: application/zip\r\n\r\n").encode()
    tail = f"\r\n--{boundary}\r\nContent-Disposition: form-data; name=\"after\"\r\n\r\nx\r\n--{boundary}--\r\n"
    body = head + archives["zip"] + tail.encode()

    def pieces():
        for start in range(0, len(body), 97):
            yield body[start:start + 97]

    r = server.http.post("/v1/uploads", content=pieces(),
                         headers={"content-type": f"multipart/form-data; boundary={boundary}"})
    assert r.status_code == 201, r.text
    assert r.json()["size"] == len(archives["zip"]) and r.json()["filename"] == "t.zip"


@pytest.mark.parametrize("name", ["traversal", "absolute", "symlink", "hard link", "corrupt tar.gz", "not an archive"])
def test_a_hostile_archive_is_refused_with_its_reason_and_leaves_nothing(server, dataset, tmp_path, name):
    build, limits, reason, member = HOSTILE[name]
    assert limits is None  # the server's limits are the defaults
    before = upload_entries(server)
    message = error(post_upload(server, build(tmp_path / "evil", dataset).read_bytes()), 422, "INVALID_ARGUMENT",
                    "file")
    if member:
        assert member in message, message
    assert upload_entries(server) == before


def test_an_invalid_dataset_and_malformed_bodies_are_refused(server, dataset, tmp_path):
    before = upload_entries(server)
    broken = {k: v for k, v in dataset.items() if k != "tracking.npz"}
    message = error(post_upload(server, tar_archive(tmp_path / "b.tar", broken).read_bytes()), 422,
                    "INVALID_ARGUMENT", "file")
    assert "the dataset is not valid" in message and "tracking.npz" in message
    # no 'file' field, not multipart at all, a truncated multipart body
    r = server.http.post("/v1/uploads", files={"other": ("x", b"abc")})
    assert "no form field 'file'" in error(r, 422, "INVALID_ARGUMENT", "file")
    r = server.http.post("/v1/uploads", content=b"hello", headers={"content-type": "application/gzip"})
    assert "multipart/form-data" in error(r, 422, "INVALID_ARGUMENT", "file")
    boundary = "b0undary"
    body = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"a.tgz\"\r\n\r\n").encode() \
        + b"x" * 1000
    r = server.http.post("/v1/uploads", content=body,
                         headers={"content-type": f"multipart/form-data; boundary={boundary}"})
    assert "truncated" in error(r, 422, "INVALID_ARGUMENT", "file")
    assert upload_entries(server) == before


def test_a_client_that_goes_away_mid_upload_leaves_nothing(server, archives):
    import socket

    before = upload_entries(server)
    boundary = "gone"
    head = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"t.tgz\"\r\n\r\n").encode()
    host, port = server.url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port))) as sock:
        sock.sendall(f"POST /v1/uploads HTTP/1.1\r\nHost: {host}\r\nContent-Length: 900000\r\n"
                     f"Authorization: Bearer {server.key}\r\n"
                     f"Content-Type: multipart/form-data; boundary={boundary}\r\n\r\n".encode()
                     + head + archives["tar.gz"][:500])
        time.sleep(0.5)  # the server is receiving the file part
        assert any(p.startswith(".incoming-") for p in upload_entries(server))
    _wait(lambda: upload_entries(server) == before, 10, "the abandoned upload to be removed")


def test_a_too_large_upload_is_413_and_leaves_nothing(server):
    before = upload_entries(server)
    # declared too large: refused before the body is read
    r = post_upload(server, os.urandom(MAX_DATASET_BYTES + 200_000))
    assert "larger than" in error(r, 413, "INVALID_ARGUMENT", "file")
    # streamed without a length (chunked): refused once the file part passes the limit
    boundary = "streamed"

    def body():
        yield f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"big.tgz\"\r\n\r\n".encode()
        for _ in range(MAX_DATASET_BYTES // 65536 + 2):
            yield b"\0" * 65536
        yield f"\r\n--{boundary}--\r\n".encode()

    r = server.http.post("/v1/uploads", content=body(),
                         headers={"content-type": f"multipart/form-data; boundary={boundary}"})
    assert "larger than" in error(r, 413, "INVALID_ARGUMENT", "file")
    assert upload_entries(server) == before


# ------------------------------------------------------------------------------------------------------- jobs
def test_a_job_is_submitted_and_read_back(server, archives):
    upload_id = upload(server, archives)
    r = submit(server, upload_id, preset="tiny", iterations=30, resolution=64, seed=5)
    assert r.status_code == 201, r.text
    job = r.json()
    assert r.headers["location"] == f"/v1/jobs/{job['id']}" == job["links"]["self"]
    assert job["state"] == "queued" and job["attempts"] == 0 and job["max_attempts"] == 3
    assert job["spec"] == {"upload_id": upload_id, "preset": "tiny", "iterations": 30, "avatar_id": "ada",
                           "resolution": 64, "seed": 5}
    assert job["progress"] == {**dict.fromkeys(["fraction", "iteration", "eta_seconds", "loss", "psnr", "gaussians"]),
                               "total_iterations": 30}
    assert job["error"] is job["result"] is job["started_at"] is job["finished_at"] is None
    assert job["links"]["cancel"] == f"/v1/jobs/{job['id']}/cancel" and job["links"]["artefacts"] == {}
    assert job["links"]["upload"] == f"/v1/uploads/{upload_id}" and job["links"]["avatar"] is None
    assert server.http.get(f"/v1/jobs/{job['id']}").json() == job
    # the defaults
    assert submit(server, upload_id).json()["spec"] == {"upload_id": upload_id, "preset": "tiny",
                                                        "iterations": None, "avatar_id": "ada", "resolution": None,
                                                        "seed": 0}


@pytest.mark.parametrize("spec, field", [
    ({"iterations": 0}, "iterations"), ({"iterations": 1_000_001}, "iterations"), ({"preset": "huge"}, "preset"),
    ({"avatar_id": "no spaces"}, "avatar_id"), ({"avatar_id": "x.tmp"}, "avatar_id"), ({"seed": -1}, "seed"),
    ({"resolution": 8}, "resolution"), ({"webhook": "http://x"}, "webhook"), ({"upload_id": "../etc"}, "upload_id"),
])
def test_a_bad_job_request_is_422_naming_the_field(server, archives, spec, field):
    body = {"upload_id": upload(server, archives), "avatar_id": "ada", **spec}
    error(server.http.post("/v1/jobs", json=body), 422, "INVALID_ARGUMENT", field)


def test_a_job_for_a_missing_upload_is_404_and_an_unknown_job_too(server):
    assert "no upload" in error(submit(server, "upl_" + "x" * 22), 404, "NOT_FOUND", "upload_id")
    for method, path in (("GET", "/v1/jobs/job_nope"), ("POST", "/v1/jobs/job_nope/cancel"),
                         ("DELETE", "/v1/jobs/job_nope"), ("GET", "/v1/jobs/job_nope/artefacts/report"),
                         ("GET", "/v1/uploads/upl_" + "y" * 22), ("DELETE", "/v1/uploads/upl_" + "y" * 22)):
        assert server.http.request(method, path).status_code == 404, (method, path)
    error(server.http.get("/v1/uploads/upl_nope"), 422, "INVALID_ARGUMENT", "upload_id")  # not an upload id


def test_jobs_are_listed_newest_first_in_pages_and_by_state(server, archives):
    upload_id = upload(server, archives)
    ids = [submit(server, upload_id, seed=i).json()["id"] for i in range(5)]
    for job_id in ids[1:3]:
        assert server.http.post(f"/v1/jobs/{job_id}/cancel").status_code == 202
    seen, cursor, pages = [], None, 0
    while True:
        r = server.http.get("/v1/jobs", params={"limit": 2, **({"cursor": cursor} if cursor else {})})
        assert r.status_code == 200, r.text
        page = r.json()
        assert len(page["jobs"]) <= 2
        seen += [j["id"] for j in page["jobs"]]
        pages += 1
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert len(seen) == len(set(seen)) and pages == (len(seen) + 1) // 2
    assert [i for i in seen if i in ids] == ids[::-1]  # newest first
    cancelled = server.http.get("/v1/jobs", params={"state": "cancelled", "limit": 500}).json()
    assert {j["state"] for j in cancelled["jobs"]} == {"cancelled"}
    assert set(ids[1:3]) <= {j["id"] for j in cancelled["jobs"]}
    assert not set(ids[:1] + ids[3:]) & {j["id"] for j in cancelled["jobs"]}
    error(server.http.get("/v1/jobs", params={"state": "paused"}), 422, "INVALID_ARGUMENT", "state")
    error(server.http.get("/v1/jobs", params={"limit": 0}), 422, "INVALID_ARGUMENT", "limit")
    error(server.http.get("/v1/jobs", params={"cursor": "not-a-cursor"}), 422, "INVALID_ARGUMENT", "cursor")


def test_an_idempotency_key_gives_the_same_job(server, archives):
    upload_id = upload(server, archives)
    key = f"key-{secrets.token_hex(4)}"
    first = submit(server, upload_id, key, iterations=10)
    assert first.status_code == 201
    again = submit(server, upload_id, key, iterations=10, preset="tiny")  # the same request once defaults apply
    assert again.status_code == 200 and again.json()["id"] == first.json()["id"]
    assert again.headers["location"] == first.headers["location"]
    message = error(submit(server, upload_id, key, iterations=11), 409, "FAILED_PRECONDITION", "idempotency_key")
    assert first.json()["id"] in message
    other = submit(server, upload_id, key + "-b", iterations=10)
    assert other.status_code == 201 and other.json()["id"] != first.json()["id"]
    assert submit(server, upload_id, iterations=10).json()["id"] not in (first.json()["id"], other.json()["id"])


def test_cancel_of_a_queued_job(server, archives):
    job_id = submit(server, upload(server, archives)).json()["id"]
    r = server.http.post(f"/v1/jobs/{job_id}/cancel")
    assert r.status_code == 202 and r.json()["state"] == "cancelled" and r.json()["cancel_requested"] is True
    assert r.json()["finished_at"] is not None and r.json()["error"]
    again = server.http.post(f"/v1/jobs/{job_id}/cancel")  # already finished: left as it is
    assert again.status_code == 200 and again.json()["state"] == "cancelled"


def test_artefacts_are_served_from_the_work_folder_only(server, archives):
    job_id = submit(server, upload(server, archives)).json()["id"]
    message = error(server.http.get(f"/v1/jobs/{job_id}/artefacts/report"), 404, "NOT_FOUND", "name")
    assert "no report yet" in message
    message = error(server.http.get(f"/v1/jobs/{job_id}/artefacts/secrets"), 422, "INVALID_ARGUMENT", "name")
    assert "'report', 'summary', 'curves', 'contact-sheet', 'preview', 'truth' or 'log'" in message  # the enum
    for bad in ("..%2F..%2Fjobs.db", "%2E%2E", "report.json", "log.jsonl", "%2Fetc%2Fpasswd"):
        assert server.http.get(f"/v1/jobs/{job_id}/artefacts/{bad}").status_code in (404, 422), bad
    work = server.data_dir / "work" / job_id
    work.mkdir(parents=True)
    (work / "report.json").write_text('{"psnr": 30.0}')
    (work / "preview.png").write_bytes(b"\x89PNG fake")
    (work / "log.jsonl").symlink_to(server.data_dir / "jobs.db" if not server.jobs_url else "/etc/passwd")
    r = server.http.get(f"/v1/jobs/{job_id}/artefacts/report")
    assert r.status_code == 200 and r.json() == {"psnr": 30.0} and r.headers["content-type"] == "application/json"
    r = server.http.get(f"/v1/jobs/{job_id}/artefacts/preview")
    assert r.status_code == 200 and r.content == b"\x89PNG fake" and r.headers["content-type"] == "image/png"
    assert server.http.get(f"/v1/jobs/{job_id}/artefacts/log").status_code == 404  # a symlink is never followed
    links = server.http.get(f"/v1/jobs/{job_id}").json()["links"]["artefacts"]
    assert links == {"report": f"/v1/jobs/{job_id}/artefacts/report", "preview": f"/v1/jobs/{job_id}/artefacts/preview"}


# --------------------------------------------------------------------------------------------------- deletion
def test_delete_of_a_job_removes_its_row_events_and_work_folder(server, db, archives):
    job_id = submit(server, upload(server, archives)).json()["id"]
    work = server.data_dir / "work" / job_id
    (work / "checkpoints").mkdir(parents=True)
    (work / "checkpoints" / "ckpt_4.pt").write_bytes(b"weights")
    (work / "preview.png").write_bytes(b"face")
    assert db.events(job_id)
    assert server.http.delete(f"/v1/jobs/{job_id}").status_code == 204
    assert not work.exists() and not [p for p in work.parent.iterdir() if job_id in p.name]
    with pytest.raises(NotFound):
        db.get(job_id)
    with pytest.raises(NotFound):
        db.events(job_id)
    assert server.http.get(f"/v1/jobs/{job_id}").status_code == 404
    assert server.http.delete(f"/v1/jobs/{job_id}").status_code == 404


def test_delete_of_an_upload_is_refused_while_a_job_needs_it_then_removes_it_and_derived_folders(server, db,
                                                                                                    archives):
    upload_id = upload(server, archives)
    finished = submit(server, upload_id).json()["id"]
    server.http.post(f"/v1/jobs/{finished}/cancel")
    (server.data_dir / "work" / finished).mkdir(parents=True)
    (server.data_dir / "work" / finished / "preview.png").write_bytes(b"face")
    queued = submit(server, upload_id).json()["id"]
    message = error(server.http.delete(f"/v1/uploads/{upload_id}"), 409, "FAILED_PRECONDITION", "upload_id")
    assert queued in message and finished not in message
    assert (server.data_dir / "uploads" / upload_id).is_dir()
    server.http.post(f"/v1/jobs/{queued}/cancel")
    assert server.http.delete(f"/v1/uploads/{upload_id}").status_code == 204
    assert not (server.data_dir / "uploads" / upload_id).exists()
    assert not [p for p in (server.data_dir / "uploads").iterdir() if upload_id in p.name]
    assert not (server.data_dir / "work" / finished).exists()  # face images derived from the upload
    assert db.get(finished).state == "cancelled"  # the row stays (no image data)
    assert server.http.get(f"/v1/uploads/{upload_id}").status_code == 404
    assert upload_id not in {u["upload_id"] for u in server.http.get("/v1/uploads").json()["uploads"]}
    assert "no upload" in error(submit(server, upload_id), 404, "NOT_FOUND", "upload_id")


def test_delete_of_an_avatar_removes_its_files_and_cached_copy(server, tmp_path):
    write_bundle(synth_avatar(gaussians=300, blendshapes=3, seed=1), tmp_path / "a.bundle", precision="fp16")
    assert server.http.put("/v1/avatars/gone", content=(tmp_path / "a.bundle").read_bytes()).status_code == 201
    assert server.http.post("/v1/avatars/gone/load").json()["loaded"] is True
    bundles = server.data_dir / "bundles"
    assert {"gone.bundle", "gone.bundle.verified"} <= {p.name for p in bundles.iterdir()}
    assert server.http.delete("/v1/avatars/gone").status_code == 204
    assert not [p for p in bundles.iterdir() if p.name.startswith("gone")]
    assert "no avatar" in error(server.http.get("/v1/avatars/gone"), 404, "NOT_FOUND")
    assert "gone" not in {a["id"] for a in server.http.get("/v1/avatars").json()["avatars"]}
    with grpc.insecure_channel(server.grpc_target) as channel:
        with pytest.raises(grpc.RpcError) as caught:
            pb_grpc.RenderServiceStub(channel).Render(pb.RenderRequest(avatar_id="gone", width=16, height=16),
                                                      metadata=(("authorization", f"Bearer {server.key}"),))
    assert caught.value.code() == grpc.StatusCode.NOT_FOUND  # not served from a cached copy
    assert server.http.delete("/v1/avatars/gone").status_code == 404
    error(server.http.delete("/v1/avatars/bad%20id"), 422, "INVALID_ARGUMENT", "avatar_id")


# -------------------------------------------------------------------------------------------- operations
def test_metrics_report_the_queue_by_state_and_uploads(server, archives):
    submit(server, upload(server, archives))
    text = server.http.get("/metrics").text
    counts = {m.group(1): float(m.group(2)) for m in re.finditer(r'^blendsplat_jobs\{state="(\w+)"\} (\S+)$', text,
                                                                  re.M)}
    assert set(counts) == {"queued", "running", "succeeded", "failed", "cancelled"}
    listed = server.http.get("/v1/jobs", params={"state": "queued", "limit": 500}).json()["jobs"]
    assert counts["queued"] == len(listed) >= 1
    assert "blendsplat_jobs_database_up 1.0" in text
    assert re.search(r'^blendsplat_dataset_uploads_total\{result="accepted"\} [1-9]', text, re.M)
    assert re.search(r'^blendsplat_jobs_submitted_total\{result="created"\} [1-9]', text, re.M)


def test_the_openapi_documents_the_routes_and_models(server):
    spec = server.http.get("/openapi.json").json()
    paths = spec["paths"]
    assert {"/v1/uploads", "/v1/uploads/{upload_id}", "/v1/jobs", "/v1/jobs/{job_id}", "/v1/jobs/{job_id}/cancel",
            "/v1/jobs/{job_id}/artefacts/{name}", "/v1/avatars/{avatar_id}"} <= set(paths)
    assert "delete" in paths["/v1/avatars/{avatar_id}"] and "delete" in paths["/v1/jobs/{job_id}"]
    body = paths["/v1/uploads"]["post"]["requestBody"]["content"]["multipart/form-data"]["schema"]
    assert body["required"] == ["file"] and "413" in paths["/v1/uploads"]["post"]["responses"]
    request = spec["components"]["schemas"]["JobSpec"]
    assert request["properties"]["avatar_id"]["pattern"] and request["required"] == ["upload_id", "avatar_id"]


def test_a_restart_loses_no_job_and_retention_runs_at_start(tmp_path, archives):
    """SQLite: jobs survive a restart of the API process. At the next start with short retention periods the
    expired upload is deleted (not the one a queued job still needs) and so is a finished job's work folder; the
    rows stay."""
    first = ServerProcess(tmp_path / "data")
    try:
        kept, expired = upload(first, archives), upload(first, archives)
        queued = submit(first, kept).json()
        done = submit(first, expired).json()["id"]
        first.http.post(f"/v1/jobs/{done}/cancel")
        (tmp_path / "data" / "work" / done).mkdir(parents=True)
        (tmp_path / "data" / "work" / done / "preview.png").write_bytes(b"face")
        before = first.http.get("/v1/jobs").json()["jobs"]
    finally:
        assert first.stop() == 0
    time.sleep(1.0)
    second = ServerProcess(tmp_path / "data", BLENDSPLAT_UPLOAD_RETENTION_HOURS="0.0001",
                           BLENDSPLAT_WORK_RETENTION_HOURS="0.0001")
    try:
        after = second.http.get("/v1/jobs").json()["jobs"]
        assert [(j["id"], j["state"], j["spec"]) for j in after] == [(j["id"], j["state"], j["spec"])
                                                                      for j in before]
        assert second.http.get(f"/v1/jobs/{queued['id']}").json()["state"] == "queued"
        deadline = time.monotonic() + 30
        while (tmp_path / "data" / "uploads" / expired).exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not (tmp_path / "data" / "uploads" / expired).exists()
        assert (tmp_path / "data" / "uploads" / kept).is_dir()  # a queued job needs it
        assert not (tmp_path / "data" / "work" / done).exists()
        assert second.http.get(f"/v1/jobs/{done}").json()["state"] == "cancelled"
        assert second.http.get(f"/v1/uploads/{expired}").status_code == 404
    finally:
        assert second.stop() == 0


def test_the_sweep_removes_orphaned_work_folders_and_leftovers(tmp_path):
    """In process: a work folder whose job row is gone (a worker wrote after the job was deleted) is removed once
    untouched for a minute; a job's own folder and fresh orphans are kept; unfinished deletions are cleaned."""
    from service.access.auth import Access
    from service.access.keys import KeyStore
    from service.jobs.training import Training, open_stores
    from service.settings import Settings

    settings = Settings(data_dir=tmp_path / "data", jobs_url=f"sqlite:///{tmp_path / 'data' / 'jobs.db'}")
    jobs, uploads = open_stores(settings)
    training = Training(settings, jobs, uploads, access=Access(settings, KeyStore(jobs.engine)),
                        writable=lambda avatar_id, writer: None)
    try:
        live = training.jobs.submit({"upload_id": "upl_" + "a" * 20, "avatar_id": "a"}).id
        work = settings.work_dir
        for name in (live, "job_orphan_old", "job_orphan_new", ".deleting-job_x-1234", "notes"):
            (work / name).mkdir(parents=True)
            (work / name / "preview.png").write_bytes(b"face")
        old = time.time() - 120
        os.utime(work / "job_orphan_old", (old, old))
        report = training.sweep()
        assert sorted(p.name for p in work.iterdir()) == sorted([live, "job_orphan_new", "notes"])
        assert report.uploads == report.work_folders == [] and report.stale == 1
    finally:
        training.close()


def test_a_missing_artefact_of_a_finished_job_says_why(tmp_path):
    """In process: the 404 of an artefact a finished job lacks says the real reason (no held-out frames, figures
    the worker could not draw, cancelled, failed, work folder gone), not "written when training ends"."""
    from service.access.auth import Access
    from service.access.keys import KeyStore
    from service.jobs.training import Training, open_stores
    from service.settings import Settings

    settings = Settings(data_dir=tmp_path / "data", jobs_url=f"sqlite:///{tmp_path / 'data' / 'jobs.db'}")
    jobs, uploads = open_stores(settings)
    training = Training(settings, jobs, uploads, access=Access(settings, KeyStore(jobs.engine)),
                        writable=lambda avatar_id, writer: None)

    def finished(state: str, error: str | None = None, **files: dict) -> str:
        job_id = training.jobs.submit({"upload_id": "upl_" + "a" * 20, "avatar_id": "a"}).id
        assert training.jobs.claim("w", 60).id == job_id
        training.jobs.finish(job_id, "w", state, error=error, result={"avatar_id": "a"} if not error else None)
        work = training.work_folder(job_id)
        work.mkdir(parents=True)
        for name, body in files.items():
            (work / f"{name}.json").write_text(json.dumps(body))
        return job_id

    def why(job_id: str, name: str) -> str:
        with pytest.raises(NotFound) as caught:
            training.artefact(job_id, name)
        return str(caught.value)

    try:
        no_test = finished("succeeded", summary={"plots": {"curves": "curves.png"}})
        assert "no held-out (test) frames" in why(no_test, "contact-sheet") and "when training ends" not in why(
            no_test, "contact-sheet")
        assert "no held-out (test) frames" in why(no_test, "report")
        no_plots = finished("succeeded", summary={"eval": {"psnr": 30.0}, "plots": {"skipped": "matplotlib is not "
                                                                                    "installed: pip install x"}},
                            report={"plots": {"skipped": "matplotlib is not installed: pip install x"}})
        assert "could not draw it (matplotlib is not installed" in why(no_plots, "contact-sheet")
        assert "could not draw the training curves (matplotlib" in why(no_plots, "curves")
        assert "cancelled before training ended" in why(finished("cancelled", error="cancelled"), "contact-sheet")
        assert "failed before training ended (RuntimeError: boom)" in why(
            finished("failed", error="RuntimeError: boom"), "report")
        gone = finished("succeeded")
        shutil.rmtree(training.work_folder(gone))
        assert "work folder is gone" in why(gone, "contact-sheet")
        queued = training.jobs.submit({"upload_id": "upl_" + "a" * 20, "avatar_id": "q"}).id
        assert "has no contact-sheet yet (contact_sheet.png is written by the worker when training ends)" in why(
            queued, "contact-sheet")
    finally:
        training.close()


# ------------------------------------------------------------------------------------------- end to end
def _children(pid: int) -> list[int]:
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(entry.name))
    return out


def _wait(predicate, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.2)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


@pytest.fixture(scope="module")
def video_archive(tiny_video_archive) -> bytes:
    return tiny_video_archive


@pytest.mark.slow
@pytest.mark.parametrize("database", DATABASES)
def test_up_trains_a_submitted_job_and_the_avatar_streams_over_grpc(tmp_path, video_archive, database,
                                                                    pg_admin_user):
    """`blendsplat up`: the service plus its worker child (niced, restarted when it dies). A job submitted over
    REST trains, succeeds with its artefacts, and its avatar streams over gRPC; then deleting the job, the upload
    and the avatar leaves none of their files; SIGTERM stops both processes."""
    with job_database(database, pg_admin_user) as url:
        _up_end_to_end(tmp_path, video_archive, url)


def _up_end_to_end(tmp_path: Path, video_archive: bytes, jobs_url: str | None) -> None:
    up = ServerProcess(tmp_path / "data", jobs_url, command="up", BLENDSPLAT_HEARTBEAT_SECONDS="0.5")
    try:
        workers = _wait(lambda: _children(up.proc.pid), 30, "the worker child")
        assert len(workers) == 1
        assert os.getpriority(os.PRIO_PROCESS, workers[0]) == os.getpriority(os.PRIO_PROCESS, up.proc.pid) + 10
        os.kill(workers[0], signal.SIGKILL)  # an unexpected death: up starts another
        restarted = _wait(lambda: [p for p in _children(up.proc.pid) if p != workers[0]], 30, "a new worker")
        assert "exited unexpectedly" in up.output()

        r = up.http.post("/v1/uploads", files={"file": ("video.tar.gz", video_archive, "application/gzip")})
        assert r.status_code == 201, r.text
        t0 = time.monotonic()
        job = submit(up, r.json()["upload_id"], avatar_id="trained", iterations=30, seed=2).json()
        job = _wait(lambda: (j := up.http.get(f"/v1/jobs/{job['id']}").json())["state"] in
                    ("succeeded", "failed", "cancelled") and j, 300, "the job to end")
        print(f"submit to succeeded: {time.monotonic() - t0:.1f} s")
        assert job["state"] == "succeeded", job
        assert job["attempts"] == 1 and job["progress"]["iteration"] == 30 and job["progress"]["fraction"] == 1.0
        result = job["result"]
        assert result["avatar_id"] == "trained" and result["iterations"] == 30 and result["digest"]
        assert job["links"]["avatar"] == "/v1/avatars/trained"
        assert {"report", "summary", "preview", "truth", "log"} <= set(job["links"]["artefacts"])
        truth = up.http.get(job["links"]["artefacts"]["truth"])  # the preview's frame from the dataset
        assert truth.status_code == 200 and truth.content.startswith(b"\x89PNG")
        report = up.http.get(job["links"]["artefacts"]["report"])
        assert report.status_code == 200 and "psnr" in json.dumps(report.json())
        assert up.http.get(job["links"]["avatar"]).json()["digest"] == result["digest"]

        with grpc.insecure_channel(up.grpc_target) as channel:
            stub = pb_grpc.RenderServiceStub(channel)
            requests = iter([pb.StreamRequest(open=pb.SessionConfig(avatar_id="trained", width=48, height=48)),
                             pb.StreamRequest(frame=pb.FrameParams(index=1))])
            replies = stub.RenderStream(requests, metadata=(("authorization", f"Bearer {up.key}"),))
            assert next(replies).WhichOneof("msg") == "header"
            frame = next(replies)
            assert frame.WhichOneof("msg") == "frame" and frame.frame.index == 1 and frame.frame.data
        assert _children(up.proc.pid) == restarted

        # cancel over REST of a running job: its worker stops it before the next iteration
        long = submit(up, job["spec"]["upload_id"], avatar_id="never", iterations=100_000).json()
        _wait(lambda: (up.http.get(f"/v1/jobs/{long['id']}").json()["progress"]["iteration"] or 0) >= 2, 120,
              "the long job to train")
        r = up.http.post(f"/v1/jobs/{long['id']}/cancel")
        assert r.status_code == 202 and r.json()["state"] == "running" and r.json()["cancel_requested"] is True
        cancelled = _wait(lambda: (j := up.http.get(f"/v1/jobs/{long['id']}").json())["state"] != "running" and j,
                          60, "the cancel")
        assert cancelled["state"] == "cancelled" and cancelled["progress"]["iteration"] < 100_000
        assert up.http.get("/v1/avatars/never").status_code == 404  # nothing committed
        assert up.http.delete(f"/v1/jobs/{long['id']}").status_code == 204

        # deletion after a real training: the work folder (checkpoints, previews, bundle copy), the dataset, the
        # avatar's files
        data = tmp_path / "data"
        assert (data / "work" / job["id"] / "checkpoints").is_dir()
        assert up.http.delete(f"/v1/jobs/{job['id']}").status_code == 204
        assert up.http.delete(f"/v1/uploads/{job['spec']['upload_id']}").status_code == 204
        assert up.http.delete("/v1/avatars/trained").status_code == 204
        assert [p.name for p in (data / "work").iterdir()] == []
        assert [p.name for p in (data / "uploads").iterdir()] == []
        assert [p.name for p in (data / "bundles").iterdir()] == []
        assert up.http.get("/v1/jobs").json()["jobs"] == []
    finally:
        code = up.stop()
    assert code == 0
    assert not Path(f"/proc/{restarted[0]}").exists() or "zombie" in Path(f"/proc/{restarted[0]}/status").read_text()
    assert "worker stopped (exit code 0)" in up.output()
