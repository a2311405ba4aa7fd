"""`blendsplat jobs` (service/jobs/cli.py over the Python client package, blendsplat_client), the training jobs'
command-line client, against a real `blendsplat up` (the service and one worker child, a temporary data dir, one per
module): submit a dataset folder and wait for it, submit an archive, list, show, Ctrl-C while waiting, cancel then
wait, delete, a wrong server, HTTP errors, no duplicate job when the create POST is retried. What the commands use of
the client's job following (ordered events, resume with Last-Event-ID after a dropped connection, the polling
fallback when the route answers 404 or keeps failing, every job read reported) and the streamed upload body are
tested against fake servers (httpx transports), and the fallback also against the real one.
"""

from __future__ import annotations

import io
import json
import os
import re
import signal
import subprocess
import sys
import tarfile
import threading
import time
from pathlib import Path

import httpx
import pytest
from blendsplat_client import Client, Event, errors
from blendsplat_client._follow import STREAM_FAILURES
from blendsplat_client._rest import CHUNK

from service.cli import main as blendsplat
from service.jobs.display import Watch

ROOT = Path(__file__).resolve().parents[1]
READY = re.compile(r"ready: gRPC on port (\d+), HTTP on port (\d+)")
SERVER_ENV = {"BLENDSPLAT_DEMO_AVATAR": "synthetic", "BLENDSPLAT_DEMO_GAUSSIANS": "2000",
              "BLENDSPLAT_DEMO_BLENDSHAPES": "4", "BLENDSPLAT_WARMUP_SIZE": "32", "BLENDSPLAT_DRAIN_SECONDS": "1",
              "BLENDSPLAT_HEARTBEAT_SECONDS": "0.5", "PYTHONUNBUFFERED": "1"}
COMMANDS = ("submit", "list", "show", "cancel", "wait", "delete")


def clean_env() -> dict[str, str]:
    """The environment without any BLENDSPLAT_* setting of the caller's."""
    return {k: v for k, v in os.environ.items() if not k.startswith("BLENDSPLAT_")}


class Up:
    """A real `blendsplat up` on free loopback ports with its own data dir; its API key when it made one."""

    def __init__(self, data_dir: Path):
        self.data_dir = data_dir
        self.log = data_dir.parent / "up.log"
        with open(self.log, "wb") as out:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "service.cli", "up", "--grpc-port", "0", "--http-port", "0", "--data-dir",
                 str(data_dir), "--host", "127.0.0.1"], cwd=ROOT, env={**clean_env(), **SERVER_ENV}, stdout=out,
                stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 180
        while not (match := READY.search(self.output())):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                pytest.fail(f"`blendsplat up` did not become ready:\n{self.output()[-3000:]}")
            time.sleep(0.1)
        self.url = f"http://127.0.0.1:{match.group(2)}"
        key_file = data_dir / "admin.key"
        self.key = key_file.read_text().strip() if key_file.is_file() else None

    def output(self) -> str:
        return self.log.read_text(errors="replace")

    def client(self, **kwargs) -> Client:
        return Client(self.url, api_key=self.key or "", **kwargs)

    def args(self) -> list[str]:
        """The common options of every `jobs` command for this server."""
        return ["--server", self.url] + (["--api-key", self.key] if self.key else [])

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout=60)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait()


@pytest.fixture(scope="module")
def up(tmp_path_factory):
    server = Up(tmp_path_factory.mktemp("jobs-client") / "data")
    yield server
    server.stop()


@pytest.fixture(scope="module")
def archive(tiny_video_archive, tmp_path_factory) -> Path:
    """The 12-frame 64 x 64 synthetic tracked video (tests/conftest.py) as a .tar.gz file."""
    path = tmp_path_factory.mktemp("archive") / "video.tar.gz"
    path.write_bytes(tiny_video_archive)
    return path


@pytest.fixture(scope="module")
def dataset(tiny_video_archive, tmp_path_factory) -> Path:
    """The same video as a dataset folder."""
    root = tmp_path_factory.mktemp("dataset")
    with tarfile.open(fileobj=io.BytesIO(tiny_video_archive), mode="r:gz") as tar:
        tar.extractall(root, filter="data")
    return root / "video"


def run(capsys, *argv: str) -> tuple[int, str, str]:
    """`blendsplat ARGV` in this process: (exit code, stdout, stderr)."""
    capsys.readouterr()
    try:
        code = blendsplat(list(argv))
    except SystemExit as exc:  # argparse: --help, usage errors
        code = exc.code if isinstance(exc.code, int) else 2
    out, err = capsys.readouterr()
    return code, out, err


def run_process(*argv: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """`blendsplat ARGV` as its own process (what a user runs)."""
    return subprocess.run([sys.executable, "-m", "service.cli", *argv], cwd=ROOT, env=clean_env(), text=True,
                          capture_output=True, timeout=timeout)


def wait_for(predicate, timeout: float, what: str, interval: float = 0.1):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if value := predicate():
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


class Forward(httpx.BaseTransport):
    """A transport to the real server that can answer or fail some requests itself; records every request."""

    def __init__(self, handle=None):
        self.inner, self.handle, self.requests = httpx.HTTPTransport(), handle, []

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        self.requests.append(request)
        if self.handle is not None and (answer := self.handle(request, self.inner)) is not None:
            return answer
        return self.inner.handle_request(request)

    def close(self) -> None:
        self.inner.close()

    def paths(self, method: str | None = None) -> list[str]:
        return [r.url.path for r in self.requests if method is None or r.method == method]


NO_ROUTE = {"error": {"code": "NOT_FOUND", "message": "Not Found", "field": ""}}


def no_events_route(request: httpx.Request, inner) -> httpx.Response | None:
    """A server without GET /v1/jobs/{id}/events: 404 for the route."""
    if request.url.path.endswith("/events"):
        return httpx.Response(404, json=NO_ROUTE)
    return None


# ---------------------------------------------------------------------------------------------------- commands
@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_has_help(capsys, command):
    code, out, _ = run(capsys, "jobs", command, "--help")
    assert code == 0
    assert "--server" in out and "--api-key" in out and "--json" in out
    assert "BLENDSPLAT_SERVER" in out and "BLENDSPLAT_API_KEY" in out


def test_the_commands_use_the_client_package():
    """One HTTP client of the jobs API: the commands call blendsplat_client (clients/python), none of their own."""
    import service.jobs.cli as jobs_cli

    source = Path(jobs_cli.__file__).read_text() + (ROOT / "service" / "jobs" / "display.py").read_text()
    assert "import httpx" not in source and "from blendsplat_client import" in source
    assert not (ROOT / "service" / "jobs" / "client.py").exists()


def test_submit_refuses_what_is_not_a_dataset(capsys, tmp_path):
    (tmp_path / "empty").mkdir()
    code, out, err = run(capsys, "jobs", "submit", str(tmp_path / "empty"), "--server", "http://127.0.0.1:9")
    assert code == 2 and out == ""
    assert "not a tracked-video dataset" in err and "dataset.json" in err
    (tmp_path / "notes.txt").write_text("hello")
    code, _, err = run(capsys, "jobs", "submit", str(tmp_path / "notes.txt"), "--server", "http://127.0.0.1:9")
    assert code == 2 and ".tar.gz, .tar or .zip" in err
    code, _, err = run(capsys, "jobs", "list", "--server", "ftp://example.org")
    assert code == 2 and "http:// or https://" in err


@pytest.fixture(scope="module")
def folder_job(up, dataset, tmp_path_factory):
    """`jobs submit FOLDER --wait --json` running as its own process from the moment its job is created (the jobs the
    other tests submit queue behind it, so they are cancelled while queued): (the process, its stdout and stderr
    files)."""
    logs = tmp_path_factory.mktemp("folder-job")
    out, err = logs / "stdout", logs / "stderr"
    with open(out, "w") as stdout, open(err, "w") as stderr:
        proc = subprocess.Popen([sys.executable, "-m", "service.cli", "jobs", "submit", str(dataset), "--preset",
                                 "tiny", "--iterations", "20", "--avatar-id", "cli-folder", "--wait", "--json",
                                 *up.args()], cwd=ROOT, env=clean_env(), stdout=stdout, stderr=stderr, text=True)
    try:
        wait_for(lambda: "submitted" in err.read_text() or proc.poll() is not None, 120, "the job to be created")
        yield proc, out, err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.fixture(scope="module")
def long_job(up, archive, folder_job):
    """A job submitted from an archive that trains for long (until a test cancels it): (its JSON, the stderr)."""
    done = run_process("jobs", "submit", str(archive), "--iterations", "100000", "--avatar-id", "cli-archive",
                       "--json", *up.args())
    assert done.returncode == 0, done.stderr
    job = json.loads(done.stdout)
    yield job, done.stderr
    with up.client() as client:  # the tests cancelled and deleted it; if one failed, do it here
        for call in (client.cancel_job, client.delete_job):
            try:
                call(job["id"])
            except errors.BlendsplatError:
                pass


def test_submit_an_archive_without_waiting(long_job):
    job, err = long_job
    assert job["state"] in ("queued", "running") and job["spec"]["avatar_id"] == "cli-archive"
    assert job["spec"]["iterations"] == 100000 and "uploaded 12 frames" in err


def test_list_and_show(up, long_job, capsys):
    job, _ = long_job
    code, out, _ = run(capsys, "jobs", "list", "--json", *up.args())
    assert code == 0
    listed = json.loads(out)
    ids = [j["id"] for j in listed["jobs"]]
    assert job["id"] in ids and ids.index(job["id"]) == 0  # newest first
    code, out, _ = run(capsys, "jobs", "list", "--limit", "1", "--json", *up.args())
    assert code == 0 and [j["id"] for j in json.loads(out)["jobs"]] == [job["id"]]
    code, out, _ = run(capsys, "jobs", "list", "--state", "succeeded", "--json", *up.args())
    assert code == 0 and job["id"] not in out and all(j["state"] == "succeeded" for j in json.loads(out)["jobs"])
    code, out, _ = run(capsys, "jobs", "list", *up.args())
    assert code == 0 and out.startswith("ID") and job["id"] in out and "cli-archive" in out
    code, out, _ = run(capsys, "jobs", "show", job["id"], "--json", *up.args())
    assert code == 0
    shown = json.loads(out)
    assert shown["id"] == job["id"] and shown["state"] in ("queued", "running")
    assert shown["spec"] == job["spec"]


def test_a_retried_create_makes_no_second_job(up, archive, long_job):
    """The first POST /v1/jobs reaches the server but its answer is lost (the connection drops): the client sends
    it once more with the same Idempotency-Key and gets the same job; the server has one. (The job queues behind
    the long one and is cancelled while queued.)"""

    def drop_first_answer(request: httpx.Request, inner) -> httpx.Response | None:
        if request.method == "POST" and request.url.path == "/v1/jobs" and not dropped:
            response = inner.handle_request(request)
            response.read()
            dropped.append(response.status_code)
            raise httpx.ReadError("connection reset by peer")
        return None

    def refuse(request: httpx.Request, inner) -> httpx.Response:
        raise httpx.ConnectError("connection refused")

    dropped: list[int] = []
    transport = Forward(drop_first_answer)
    with up.client(transport=transport) as client:
        upload = client.upload(archive)
        spec = {"preset": "tiny", "iterations": 100000, "avatar_id": "retried"}
        job = client.submit_job(upload["upload_id"], idempotency_key="retry-test-1", **spec)
        try:
            assert dropped == [201]
            posts = [r for r in transport.requests if r.method == "POST" and r.url.path == "/v1/jobs"]
            assert len(posts) == 2 and {r.headers["Idempotency-Key"] for r in posts} == {"retry-test-1"}
            same = [j for j in client.jobs_page(limit=500)["jobs"] if j["spec"]["avatar_id"] == "retried"]
            assert [j["id"] for j in same] == [job["id"]]
            refusing = Forward(refuse)
            with up.client(transport=refusing) as other, pytest.raises(errors.ConnectionFailed):
                other.submit_job(upload["upload_id"], idempotency_key=None, **spec)  # no key: no retry (two jobs)
            assert len(refusing.requests) == 1
        finally:
            client.cancel_job(job["id"])
            client.delete_job(job["id"])


def test_ctrl_c_stops_waiting_not_the_job(up, long_job, tmp_path):
    job, _ = long_job
    err = tmp_path / "wait.err"
    with open(err, "w") as stderr:
        # SIGINT as a terminal gives it: a run started in the background by a shell without job control (nohup
        # ... &) ignores SIGINT, and its children would inherit that
        proc = subprocess.Popen([sys.executable, "-m", "service.cli", "jobs", "wait", job["id"], *up.args()],
                                cwd=ROOT, env=clean_env(), stdout=subprocess.PIPE, stderr=stderr, text=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        wait_for(lambda: f"job {job['id']}: " in err.read_text(), 60, "wait to report the job's state")
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err.read_text()
    assert f"Resume with: blendsplat jobs wait {job['id']} --server {up.url}" in err.read_text()
    assert out == ""
    with up.client() as client:
        after = client.get_job(job["id"])
    assert after["state"] in ("queued", "running") and not after["cancel_requested"]


def test_cancel_then_wait_exits_1_and_the_polling_fallback_sees_it(up, long_job, capsys):
    job, _ = long_job
    # a follower on a server without the event stream: it polls the job every second
    transport = Forward(no_events_route)
    followed: dict = {}
    watch = Watch(job["id"], bars=False, stream=io.StringIO())

    def follow():
        with up.client(transport=transport) as client:
            try:
                followed["job"] = client.wait(job["id"], on_event=watch.on_event, on_job=watch.on_job, timeout=240,
                                              check=False)
            except Exception as exc:  # reported below
                followed["error"] = exc

    follower = threading.Thread(target=follow)
    follower.start()
    wait_for(lambda: any(p.endswith("/events") for p in transport.paths()), 30, "the follower to try the events")

    code, out, err = run(capsys, "jobs", "cancel", job["id"], "--json", *up.args())
    assert code == 0, err
    cancelled = json.loads(out)
    assert cancelled["id"] == job["id"] and (cancelled["cancel_requested"] or cancelled["state"] == "cancelled")

    code, out, err = run(capsys, "jobs", "wait", job["id"], "--json", "--timeout", "240", *up.args())
    assert code == 1
    assert json.loads(out)["state"] == "cancelled"
    assert f"job {job['id']} cancelled" in err

    follower.join(60)
    assert "error" not in followed, followed.get("error")
    assert followed["job"]["state"] == "cancelled"
    job_path = f"/v1/jobs/{job['id']}"
    assert transport.paths().count(job_path + "/events") == 1  # tried once: the route is missing, not the job
    assert watch.events == 0 and watch.polls >= 2  # the first read, then a poll a second until it ended
    assert watch.state == "cancelled" and "cancelled" in watch.stream.getvalue()

    code, out, err = run(capsys, "jobs", "cancel", job["id"], "--wait", *up.args())  # already ended cancelled
    assert code == 0 and f"job {job['id']}: cancelled" in out


def test_delete_removes_the_job(up, long_job, capsys):
    job, _ = long_job
    code, out, err = run(capsys, "jobs", "delete", job["id"], *up.args())
    assert code == 0 and f"deleted job {job['id']}" in out
    code, out, err = run(capsys, "jobs", "show", job["id"], *up.args())
    assert code == 2 and out == ""
    assert f"error: 404 not_found: no job '{job['id']}'" in err
    code, _, err = run(capsys, "jobs", "delete", job["id"], *up.args())
    assert code == 2 and "404 not_found" in err


def test_a_wrong_server_exits_2_saying_so(capsys):
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # nothing listens there once it is closed
    for command in (["list"], ["show", "job_x"], ["wait", "job_x"], ["cancel", "job_x"], ["delete", "job_x"]):
        code, out, err = run(capsys, "jobs", *command, "--server", f"http://127.0.0.1:{port}")
        assert code == 2 and out == ""
        assert f"cannot reach the server at http://127.0.0.1:{port}" in err and "--server" in err


def test_submit_checks_the_server_before_packing_the_dataset(dataset, capsys, monkeypatch):
    """Packing a dataset folder takes seconds to minutes: a wrong server (or a refused key) is said before it."""
    import socket

    from service.jobs import cli as jobs_cli

    packed = []
    monkeypatch.setattr(jobs_cli, "pack_dataset", lambda folder, out: packed.append(folder))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # nothing listens there once it is closed
    code, out, err = run(capsys, "jobs", "submit", str(dataset), "--server", f"http://127.0.0.1:{port}")
    assert code == 2 and out == "" and f"cannot reach the server at http://127.0.0.1:{port}" in err
    assert packed == [] and "packing" not in err


def test_http_errors_print_the_server_s_code_and_message(up, archive, capsys):
    code, out, err = run(capsys, "jobs", "submit", str(archive), "--avatar-id", "no spaces allowed",
                         *up.args())
    assert code == 2 and out == ""
    assert re.search(r"error: 422 invalid_argument: .*\(field avatar_id\)", err), err
    code, out, err = run(capsys, "jobs", "show", "job_doesnotexist", *up.args())
    assert code == 2 and "error: 404 not_found: no job 'job_doesnotexist'" in err
    secret = "not-a-key-0123456789"
    code, out, err = run(capsys, "jobs", "list", "--server", up.url, "--api-key", secret)
    if up.key:  # the server checks keys
        assert code == 2 and "error: 401 " in err
    assert secret not in out + err


def test_submit_a_dataset_folder_waits_until_it_succeeded(up, folder_job, capsys):
    proc, stdout, stderr = folder_job
    proc.wait(timeout=600)
    err = stderr.read_text()
    assert proc.returncode == 0, err
    job = json.loads(stdout.read_text())  # stdout holds the job's JSON and nothing else
    assert job["state"] == "succeeded" and job["id"].startswith("job_")
    assert job["result"]["avatar_id"] == "cli-folder" and job["spec"]["iterations"] == 20
    assert "uploaded 12 frames" in err and f"job {job['id']}: succeeded" in err
    if up.key:
        assert up.key not in stdout.read_text() + err
    code, out, _ = run(capsys, "jobs", "show", job["id"], *up.args())
    assert code == 0
    assert f"job {job['id']}: succeeded" in out and "cli-folder" in out and "PSNR" in out
    assert f"{up.url}/v1/avatars/cli-folder" in out and f"{up.url}/v1/jobs/{job['id']}" in out
    code, out, err = run(capsys, "jobs", "wait", job["id"], "--json", *up.args())
    assert code == 0 and json.loads(out)["state"] == "succeeded"


def test_the_real_event_stream_replays_a_finished_job(up):
    """Where the server has GET /v1/jobs/{id}/events (issue 16): a finished job's recorded events, in order, then
    the stream closes."""
    with up.client() as client:
        finished = client.jobs_page(state="succeeded", limit=1)["jobs"]
        if not finished:
            pytest.skip("no finished job (the submit test did not run)")
        events = list(client.events(finished[0]["id"], read_timeout=30))
    progress = [e.data["iteration"] for e in events if e.event == "progress"]
    assert progress and progress == sorted(progress) and progress[-1] == 20
    states = [e.data.get("state") for e in events if e.event == "state"]
    assert states[-1] == "succeeded"
    ids = [int(e.id) for e in events if e.id is not None and e.id.isdigit()]
    assert ids == sorted(ids)


# ------------------------------------------------------------------------------------------ fake servers
def fake_client(handler) -> Client:
    """A client of a fake server (``handler``: request -> response), no key."""
    return Client("http://fake", api_key="", transport=httpx.MockTransport(handler))


def job_json(state: str, **progress) -> dict:
    return {"id": "job_fake", "state": state, "spec": {"avatar_id": "fake", "preset": "tiny"},
            "progress": progress, "error": None, "result": None, "cancel_requested": False,
            "links": {"self": "/v1/jobs/job_fake"}}


def sse(*events: tuple[int, str, dict]) -> list[bytes]:
    return [f"id: {i}\nevent: {kind}\ndata: {json.dumps(data)}\n\n".encode() for i, kind, data in events]


def test_events_arrive_in_order_and_resume_after_a_dropped_connection():
    """The stream drops after two events; the client reconnects with Last-Event-ID and gets the rest."""
    seen_headers: list[httpx.Headers] = []
    gets: list[str] = []

    def first():
        yield from sse((1, "state", {"state": "running"}),
                       (2, "progress", {"iteration": 5, "total_iterations": 10, "loss": 0.5, "psnr": 20.0,
                                        "eta_seconds": 3.0, "fraction": 0.5, "gaussians": 100}))
        yield b": keep-alive\n\nid: 3\nevent: log\ndata: {\"message\": \"half"  # cut in the middle of an event
        raise httpx.RemoteProtocolError("peer closed connection without sending complete message body")

    def second():
        yield from sse((3, "log", {"message": "halfway"}), (4, "progress", {"iteration": 10, "total_iterations": 10}),
                       (5, "state", {"state": "succeeded", "error": None}))
        yield b'event: end\ndata: {"state": "succeeded"}\n\n'

    streams = iter([first, second])

    def handler(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/events"):
            seen_headers.append(request.headers)
            return httpx.Response(200, headers={"content-type": "text/event-stream"}, content=next(streams)())
        gets.append(request.url.path)
        return httpx.Response(200, json=job_json("succeeded" if len(gets) > 2 else "running"))

    received: list[Event] = []
    stream = io.StringIO()
    watch = Watch("job_fake", bars=True, stream=stream)
    with Client("http://fake", api_key="k-123", transport=httpx.MockTransport(handler)) as client:
        client._sleep = lambda s: None
        job = client.wait("job_fake", on_event=lambda e: (received.append(e), watch.on_event(e)))
    watch.close()
    assert job["state"] == "succeeded"
    assert [e.id for e in received] == ["1", "2", "3", "4", "5"]
    assert [e.event for e in received] == ["state", "progress", "log", "progress", "state"]
    assert received[2].data == {"message": "halfway"}  # the event cut in half was not delivered twice
    assert "Last-Event-ID" not in seen_headers[0] and seen_headers[1]["Last-Event-ID"] == "2"
    assert all(h["Authorization"] == "Bearer k-123" for h in seen_headers)
    assert all(h["Accept"] == "text/event-stream" for h in seen_headers)
    assert gets == ["/v1/jobs/job_fake"] * 3  # at the start, after the drop, at the end
    drawn = stream.getvalue()
    assert "10/10" in drawn and "loss=0.5000" in drawn and "psnr=20.00" in drawn and "eta=00:00" in drawn


def test_polling_when_the_events_route_is_missing_or_keeps_failing():
    states = iter(["queued", "running", "running", "running", "succeeded"])

    def run_fake(events_answer) -> tuple[dict, list[str], list[float]]:
        requests: list[str] = []
        naps: list[float] = []

        def handler(request: httpx.Request) -> httpx.Response:
            requests.append(request.url.path)
            if request.url.path.endswith("/events"):
                return events_answer()
            return httpx.Response(200, json=job_json(next(states), iteration=len(requests), total_iterations=10))

        with fake_client(handler) as client:
            client._sleep = naps.append
            job = client.wait("job_fake", on_job=reads.append)
        return job, requests, naps

    reads: list[dict] = []
    job, requests, naps = run_fake(lambda: httpx.Response(404, json=NO_ROUTE))
    assert job["state"] == "succeeded" and [r["state"] for r in reads] == ["queued", "running", "running", "running",
                                                                            "succeeded"]
    assert requests[:3] == ["/v1/jobs/job_fake", "/v1/jobs/job_fake/events", "/v1/jobs/job_fake"]
    assert requests.count("/v1/jobs/job_fake/events") == 1 and naps == [1.0] * 3  # polled every second

    states = iter(["running"] * 5 + ["succeeded"])
    job, requests, naps = run_fake(lambda: httpx.Response(503, json={"error": {"code": "UNAVAILABLE",
                                                                              "message": "draining"}}))
    assert job["state"] == "succeeded"
    assert requests.count("/v1/jobs/job_fake/events") == STREAM_FAILURES
    assert naps[:2] == [0.5, 1.0] and naps[2:] == [1.0] * (len(naps) - 2)  # backoff, then polling

    # a 404 for the job (not the route) is the job's: an error, no polling
    def job_gone(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/events") or gone:
            gone.append(True)
            return httpx.Response(404, json={"error": {"code": "NOT_FOUND", "message": "no job 'job_fake'",
                                                       "field": "job_id"}})
        return httpx.Response(200, json=job_json("running"))

    gone: list[bool] = []
    with fake_client(job_gone) as client, pytest.raises(errors.NotFound, match="no job 'job_fake'") as info:
        client._sleep = lambda s: None
        client.wait("job_fake")
    assert info.value.http_status == 404 and info.value.field == "job_id"


def test_a_job_deleted_while_followed_ends_the_wait():
    def handler(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/events"):
            body = b'id: 7\nevent: state\ndata: {"state": "running"}\n\nevent: end\ndata: {"state": "deleted"}\n\n'
            return httpx.Response(200, headers={"content-type": "text/event-stream; charset=utf-8"}, content=body)
        return httpx.Response(200, json=job_json("running"))

    with fake_client(handler) as client, pytest.raises(errors.NotFound, match="job job_fake was deleted"):
        client._sleep = lambda s: None
        client.wait("job_fake")


def test_the_replayed_history_is_not_shown_again():
    """A stream starts with the job's history: what was recorded before the first read is not printed again."""
    out = io.StringIO()
    watch = Watch("job_h", bars=False, stream=out)
    watch.on_job({**job_json("running"), "updated_at": "2026-01-01T10:00:05Z"})
    for i, (when, state) in enumerate([("10:00:00", "queued"), ("10:00:05", "running"), ("10:00:09", "cancelled")]):
        watch.on_event(Event("state", {"state": state, "time": f"2026-01-01T{when}.000001+00:00"}, str(i)))
    watch.on_event(Event("log", {"message": "old news", "time": "2026-01-01T09:59:00+00:00"}, "9"))
    assert out.getvalue().splitlines() == ["job job_h: running", "job job_h: cancelled"]
    assert watch.events == 4 and watch.state == "cancelled"


def test_a_wait_times_out():
    def handler(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/events"):
            return httpx.Response(404, json=NO_ROUTE)
        return httpx.Response(200, json=job_json("running"))

    with fake_client(handler) as client, pytest.raises(errors.Timeout, match="timed out after 0.3 s"):
        client.wait("job_fake", timeout=0.3, poll_seconds=0.05)


def test_the_upload_is_streamed_in_pieces_with_its_length(tmp_path):
    data = os.urandom(2 * CHUNK + 12345)
    archive = tmp_path / "take.tar.gz"
    archive.write_bytes(data)
    seen: dict = {}

    class Server(httpx.BaseTransport):  # reads the body piece by piece, as a socket would send it
        def handle_request(self, request: httpx.Request) -> httpx.Response:
            pieces = [bytes(piece) for piece in request.stream]
            seen.update(headers=request.headers, pieces=pieces, url=str(request.url))
            return httpx.Response(201, json={"upload_id": "upl_x", "frames": 1})

    sent: list[tuple[int, int]] = []
    with Client("http://fake:8080/", api_key="secret-key", transport=Server()) as client:
        assert client.upload(archive, progress=lambda n, total: sent.append((n, total)))["upload_id"] == "upl_x"
    body = b"".join(seen["pieces"])
    assert len(seen["pieces"]) >= 4 and max(map(len, seen["pieces"])) <= CHUNK
    assert sent == [(CHUNK, len(data)), (2 * CHUNK, len(data)), (len(data), len(data))]
    headers = seen["headers"]
    assert int(headers["Content-Length"]) == len(body) and "Transfer-Encoding" not in headers
    assert headers["Authorization"] == "Bearer secret-key" and "secret" not in seen["url"]
    boundary = headers["Content-Type"].split("boundary=")[1]
    assert headers["Content-Type"].startswith("multipart/form-data")
    head, _, rest = body.partition(b"\r\n\r\n")
    assert head.startswith(f"--{boundary}\r\n".encode())
    assert b'Content-Disposition: form-data; name="file"; filename="take.tar.gz"' in head
    assert rest == data + f"\r\n--{boundary}--\r\n".encode()
