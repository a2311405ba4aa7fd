"""Hardening (issue 14), resources and lifecycle, against real `blendsplat serve` processes where the behaviour is
the server's: sizes checked before anything is read or mapped (the cache budget against the bundle file, a declared
request body), no plain-text 500 (malformed bodies are named 4xx, anything unexpected a typed 500 with a logged
error id), a stalled upload times out and leaves nothing, an upload in flight at SIGTERM gets 503 and the drain
keeps its time, a missing store stays missing and not ready, temp files of a killed server are cleaned at start, and
a restart with odd bundles (no blendshapes, no mouth, larger than the cache) comes up."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import resource
import signal
import socket
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import httpx
import pytest

from render_core.bundle import write_bundle
from render_core.tools.synth import synth_avatar
from service.errors import ResourceExhausted, Unavailable
from service.metrics import Metrics
from service.store import BundleStore

CACHE_BYTES = 2 << 20  # the demo avatar fits, "a-big" (about 8 MB of file) does not
DRAIN, DELAY, BODY_TIMEOUT = 2.0, 0.0, 1.0
MARGIN = 1.5  # process teardown after the drain (interpreter exit, the job database closed)


def _free_ports(n: int) -> list[int]:
    socks = [socket.socket() for _ in range(n)]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


class Serve:
    """One `blendsplat serve` process on loopback, its log in ``<data>/../serve-N.log``."""

    count = 0

    def __init__(self, data: Path, wait_ready: bool = True, **env: str):
        Serve.count += 1
        self.data = data
        self.grpc_port, self.http_port = _free_ports(2)
        self.url = f"http://127.0.0.1:{self.http_port}"
        self.log = data.parent / f"serve-{Serve.count}.log"
        environ = {**os.environ, "BLENDSPLAT_DEMO_AVATAR": "synthetic", "BLENDSPLAT_DEMO_GAUSSIANS": "500",
                   "BLENDSPLAT_DEMO_BLENDSHAPES": "4", "BLENDSPLAT_WARMUP_SIZE": "32",
                   "BLENDSPLAT_CACHE_BYTES": str(CACHE_BYTES), "BLENDSPLAT_DRAIN_SECONDS": str(DRAIN),
                   "BLENDSPLAT_SHUTDOWN_DELAY_SECONDS": str(DELAY),
                   "BLENDSPLAT_BODY_TIMEOUT_SECONDS": str(BODY_TIMEOUT), "BLENDSPLAT_RENDER_THREADS": "1", **env}
        environ.pop("BLENDSPLAT_JOBS_URL", None)
        with open(self.log, "w") as out:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "service.cli", "serve", "--grpc-port", str(self.grpc_port), "--http-port",
                 str(self.http_port), "--data-dir", str(data), "--host", "127.0.0.1"],
                env=environ, stdout=out, stderr=subprocess.STDOUT)
        self.http = httpx.Client(base_url=self.url, timeout=30)
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            assert self.proc.poll() is None, f"serve exited ({self.proc.returncode}): {self.output()[-2000:]}"
            try:
                r = self.http.get("/readyz", timeout=2)
                if r.status_code == 200 or (not wait_ready and "warm_up" in r.json().get("reasons", {})
                                            and "not rendered yet" not in r.json()["reasons"]["warm_up"]):
                    self.key = (data / "admin.key").read_text().strip()  # created before the warm-up
                    self.http.headers["Authorization"] = f"Bearer {self.key}"
                    self.auth = f"Authorization: Bearer {self.key}\r\n".encode()  # for raw requests
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        pytest.fail(f"serve did not come up: {self.output()[-2000:]}")

    def output(self) -> str:
        return self.log.read_text(errors="replace")

    def rss(self) -> int:
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) << 10
        raise AssertionError("no VmRSS")

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.http.close()


def _raw(port: int, head: bytes, body: bytes = b"", timeout: float = 15) -> socket.socket:
    s = socket.create_connection(("127.0.0.1", port), timeout=timeout)
    s.sendall(head + body)
    return s


def _read_all(s: socket.socket) -> bytes:
    """Everything the server sends until it closes the connection (the socket's timeout applies)."""
    data = b""
    while chunk := s.recv(65536):
        data += chunk
    return data


def _staged(store: Path) -> list[str]:
    return sorted(p.name for p in store.iterdir() if p.name.endswith(".tmp")) if store.is_dir() else []


def _odd_bundles(folder: Path) -> dict[str, Path]:
    """k0: no blendshapes; m0: no mouth Gaussians; a-big: about 8 MB of file, more than CACHE_BYTES."""
    folder.mkdir(parents=True, exist_ok=True)
    k0 = synth_avatar(gaussians=200, blendshapes=1, seed=4, mouth=12)
    k0 = replace(k0, deltas=k0.deltas.map(lambda t: t[:0]), expression_names=[])
    avatars = {"k0": k0, "m0": synth_avatar(gaussians=200, blendshapes=3, seed=5, mouth=0),
               "a-big": synth_avatar(gaussians=5000, blendshapes=8, seed=6)}
    paths = {}
    for name, avatar in avatars.items():
        paths[name] = folder / f"{name}.bundle"
        write_bundle(avatar, paths[name])
    return paths


@pytest.fixture(scope="module")
def odd(tmp_path_factory) -> dict[str, Path]:
    return _odd_bundles(tmp_path_factory.mktemp("odd-bundles"))


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    s = Serve(tmp_path_factory.mktemp("hardening-a") / "data")
    yield s
    s.stop()


def test_avatars_without_blendshapes_or_mouth_upload_over_an_id_and_render(server, odd):
    for name in ("m0", "k0"):  # k0 replaces m0 under the same id: a working avatar stays working
        r = server.http.put("/v1/avatars/odd", content=odd[name].read_bytes())
        assert r.status_code == 201, r.text
        r = server.http.post("/v1/render", json={"avatarId": "odd", "width": 32, "height": 32, "codec": "CODEC_PNG"})
        assert r.status_code == 200 and r.content.startswith(b"\x89PNG"), r.text
    info = server.http.get("/v1/avatars/odd").json()
    assert info["expression_names"] == [] and info["loaded"] is True


# ---------------------------------------------------------------------------------------------- sizes first
def test_a_declared_512_mib_render_body_is_refused_with_413_before_it_is_read(server):
    rss = server.rss()
    t0 = time.monotonic()
    s = _raw(server.http_port, b"POST /v1/render HTTP/1.1\r\nHost: x\r\n" + server.auth
             + b"Content-Type: application/json\r\n"
             + f"Content-Length: {512 << 20}\r\n\r\n".encode(), b"{" * 4096)
    with s:
        answer = _read_all(s)  # the server answers and closes: it never waits for the other 512 MiB
    head, _, body = answer.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 413") and b"connection: close" in head.lower(), answer[:300]
    error = json.loads(body)["error"]
    assert error["field"] == "body" and str(512 << 20) in error["message"]
    assert time.monotonic() - t0 < 5 and server.rss() - rss < 16 << 20


def test_a_bundle_larger_than_the_cache_is_refused_before_it_is_read_and_rss_stays_flat(server, odd):
    assert server.http.put("/v1/avatars/a-big", content=odd["a-big"].read_bytes()).status_code == 201
    size = odd["a-big"].stat().st_size
    before = server.rss()
    for _ in range(25):
        r = server.http.post("/v1/avatars/a-big/load")
        assert r.status_code == 429, r.text
    error = r.json()["error"]
    assert error["code"] == "RESOURCE_EXHAUSTED" and error["field"] == "avatar_id"
    assert "'a-big'" in error["message"] and f"{size / 1e6:.1f} MB" in error["message"]
    assert f"{CACHE_BYTES / 1e6:.1f} MB" in error["message"]
    assert server.rss() - before < 8 << 20  # 25 refusals of an 8 MB bundle allocated nothing for it
    r = server.http.post("/v1/render", json={"avatarId": "a-big", "width": 32, "height": 32})
    assert r.status_code == 429 and "'a-big'" in r.json()["error"]["message"]
    assert server.http.post("/v1/render", json={"avatarId": "demo", "width": 32, "height": 32}).status_code == 200


def test_the_cache_checks_the_file_size_against_its_budget_before_reading(tmp_path, odd, monkeypatch):
    """The general property, in process: a bundle whose file cannot fit is refused without the reader being called
    (today's code read, hashed and packed it first), and the loads in progress count against the budget."""
    import service.cache as cache_module

    store = BundleStore(tmp_path / "bundles")
    store.ensure()
    for name in ("a-big", "m0", "k0"):
        store.path(name).write_bytes(odd[name].read_bytes())
    reads = []
    real = cache_module.read_bundle_and_manifest
    monkeypatch.setattr(cache_module, "read_bundle_and_manifest", lambda *a, **k: (reads.append(a), real(*a, **k))[1])
    size = store.path("a-big").stat().st_size
    cache = cache_module.AvatarCache(store, size - 1, Metrics())
    with pytest.raises(ResourceExhausted, match=rf"'a-big'.*{size / 1e6:.1f} MB.*{(size - 1) / 1e6:.1f} MB"):
        asyncio.run(cache.load("a-big"))
    assert reads == [] and cache.loaded_ids() == []

    small = store.path("m0").stat().st_size

    async def concurrent():
        room = cache_module.AvatarCache(store, small + store.path("k0").stat().st_size - 1, Metrics())
        results = await asyncio.gather(room.load("m0"), room.load("k0"), return_exceptions=True)
        return room, results

    room, (_, second) = asyncio.run(concurrent())  # k0 is admitted while m0's load is in progress
    assert isinstance(second, ResourceExhausted) and "loads in progress" in str(second), second
    assert room.used <= room.budget


# ------------------------------------------------------------------------------------------ no plain 500
@pytest.mark.parametrize("body", [b"\xff\xfe\x00garbage", b"{", b"[]", b'"text"', b"1e999", b'{"width": "x"}',
                                  b'{"frame": []}', b"[" * 100_000, b'{"a":' * 50_000, b"\x00" * 100])
def test_a_malformed_render_body_is_a_named_4xx_json_error(server, body):
    r = server.http.post("/v1/render", content=body, headers={"Content-Type": "application/json"})
    assert 400 <= r.status_code < 500, (r.status_code, r.text[:300])
    error = r.json()["error"]
    assert set(error) >= {"code", "message", "field"} and error["field"], error
    assert len(error["message"]) < 1000


def test_unknown_routes_and_methods_answer_the_error_shape(server):
    r = server.http.get("/v1/no-such-route")
    assert r.status_code == 404 and r.json()["error"]["code"] == "NOT_FOUND"
    r = server.http.delete("/v1/render")
    assert r.status_code == 405 and r.json()["error"]["code"] == "INVALID_ARGUMENT"


def test_an_unexpected_exception_is_a_typed_500_with_a_logged_error_id(live_server, monkeypatch, caplog):
    async def broken(request):
        raise ZeroDivisionError("secret internals")

    monkeypatch.setattr(live_server.engine, "render_once", broken)
    with caplog.at_level(logging.ERROR, logger="service.errors"):
        r = httpx.post(live_server.http_url + "/v1/render", json={"avatarId": "demo"}, timeout=30)
    assert r.status_code == 500 and r.headers["content-type"] == "application/json"
    error = r.json()["error"]
    assert error["code"] == "INTERNAL" and "secret" not in r.text and "Traceback" not in r.text
    assert error["errorId"] in error["message"]
    logged = [rec for rec in caplog.records if error["errorId"] in rec.getMessage()]
    assert logged and logged[0].exc_info and "POST /v1/render" in logged[0].getMessage()


# ------------------------------------------------------------------------------------------------ uploads
def test_a_stalled_upload_times_out_with_408_and_leaves_no_temp_file(server):
    store = server.data / "bundles"
    t0 = time.monotonic()
    s = _raw(server.http_port, b"PUT /v1/avatars/stalled HTTP/1.1\r\nHost: x\r\n" + server.auth + b""
             b"Content-Type: application/octet-stream\r\nContent-Length: 1000000\r\n\r\n", b"\x00" * 5000)
    with s:
        time.sleep(0.3)
        assert any(n.startswith(".upload-") for n in _staged(store))  # the upload is being received
        answer = _read_all(s)  # then the server answers and closes
    assert answer.startswith(b"HTTP/1.1 408"), answer[:300]
    assert json.loads(answer.partition(b"\r\n\r\n")[2])["error"]["field"] == "body"
    assert BODY_TIMEOUT <= time.monotonic() - t0 < BODY_TIMEOUT + 4
    assert _staged(store) == [] and "stalled" not in [a["id"] for a in server.http.get("/v1/avatars").json()["avatars"]]


def test_a_missing_store_is_not_recreated_and_keeps_the_replica_not_ready(server, odd):
    store = server.data / "bundles"
    away = store.with_name("bundles-away")
    store.rename(away)
    try:
        r = server.http.put("/v1/avatars/m0", content=odd["m0"].read_bytes())
        assert r.status_code == 503 and r.json()["error"]["field"] == "bundle_store", r.text
        message = r.json()["error"]["message"]  # the folder named relative to the data folder: no server path
        assert "folder bundles is missing" in message and str(store) not in message
        assert not store.exists()  # not silently recreated
        for _ in range(2):
            r = server.http.get("/readyz")
            assert r.status_code == 503 and r.json()["checks"]["bundle_store"] is False
            reason = r.json()["reasons"]["bundle_store"]
            assert "bundles" in reason and str(store) not in reason and "missing" in reason
        assert server.http.get("/v1/avatars").status_code == 503
        assert server.http.post("/v1/avatars/m0/load").status_code == 503
        assert not store.exists()
    finally:
        away.rename(store)
    assert server.http.get("/readyz").status_code == 200


def test_store_creates_its_folder_only_when_it_never_existed(tmp_path):
    fresh = BundleStore(tmp_path / "fresh" / "bundles")
    fd, staged = fresh.staging()  # first use on an empty data dir (a worker, bench load): created
    os.close(fd)
    assert staged.parent.is_dir()
    gone = BundleStore(tmp_path / "gone")
    gone.ensure()
    gone.root.rmdir()
    for call in (gone.staging, gone.ensure, gone.ids, lambda: gone.existing("x")):
        with pytest.raises(Unavailable, match="missing"):
            call()
    assert not gone.root.exists() and not gone.reachable() and "missing" in gone.problem()


def test_stale_temp_files_are_removed_and_fresh_ones_kept(tmp_path):
    store = BundleStore(tmp_path)
    store.ensure()
    old = [tmp_path / ".upload-abc.tmp", tmp_path / ".demo.bundle.0123abcd.tmp"]
    fresh, bundle = tmp_path / ".upload-new.tmp", tmp_path / "x.bundle"
    for p in (*old, fresh, bundle):
        p.write_bytes(b"x")
    for p in old:
        os.utime(p, (time.time() - 120, time.time() - 120))
    assert sorted(store.clean_stale(older_than=60)) == sorted(p.name for p in old)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([fresh.name, bundle.name])


# --------------------------------------------------------------------------------------- bundle mapping
def test_bundle_validate_of_a_huge_sparse_file_names_enomem(tmp_path):
    """A bundle whose layout says 8 GB of data (a sparse file), validated under a 4 GB address-space limit: a clear
    error naming ENOMEM, not a bare ``[Errno 12]``."""
    path = tmp_path / "huge.bundle"
    _huge_sparse_bundle(path, gaussians=14_000_000)
    assert path.stat().st_size > 8e9 and path.stat().st_blocks * 512 < 1e6

    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))

    out = subprocess.run([sys.executable, "-m", "render_core.tools.cli", "bundle", "validate", str(path)],
                         capture_output=True, text=True, preexec_fn=limit, timeout=120)
    assert out.returncode == 1, out.stderr[-2000:]
    report = json.loads(out.stdout)
    assert report["valid"] is False and report["field"] == "path"
    assert "ENOMEM" in report["error"] and "[Errno" not in report["error"] and str(path.stat().st_size) in report[
        "error"]


def test_a_bundle_the_os_cannot_map_is_resource_exhausted_in_the_service(tmp_path, odd, monkeypatch):
    """ENOMEM while mapping (the machine's limit, not the file's fault): RESOURCE_EXHAUSTED naming the avatar and
    the cause, for a load and for an upload, never an untyped error."""
    import errno

    from render_core import bundle as bundle_module
    from service.cache import AvatarCache

    store = BundleStore(tmp_path / "bundles")
    store.ensure()
    store.path("m0").write_bytes(odd["m0"].read_bytes())

    def refuse(*args, **kwargs):
        raise OSError(errno.ENOMEM, "Cannot allocate memory")

    monkeypatch.setattr(bundle_module.mmap, "mmap", refuse)  # the mmap module itself: undone after the test
    with pytest.raises(ResourceExhausted, match=r"'m0'.*ENOMEM"):
        asyncio.run(AvatarCache(store, 1 << 40, Metrics()).load("m0"))
    fd, staged = store.staging()
    with os.fdopen(fd, "wb") as f:
        f.write(odd["k0"].read_bytes())
    with pytest.raises(ResourceExhausted, match="ENOMEM"):
        store.commit(staged, "k0")
    assert _staged(store.root) == [] and store.ids() == ["m0"]


def _huge_sparse_bundle(path: Path, gaussians: int) -> None:
    """A valid small bundle's header rewritten for ``gaussians`` face Gaussians, the data a hole (never read: the
    reader fails at the mapping)."""
    itemsize = {"F32": 4, "F16": 2, "I32": 4, "I64": 8, "U16": 2}
    write_bundle(synth_avatar(gaussians=50, blendshapes=2, seed=1), path)
    with open(path, "rb") as f:
        header = json.loads(f.read(int.from_bytes(f.read(8), "little")))
    meta = header.pop("__metadata__")
    manifest = json.loads(meta["blendsplat.manifest"])
    manifest["counts"]["gaussians"] = gaussians
    per_gaussian = {50: gaussians, 51: gaussians + 1, 56: gaussians + 6}  # N, N + 1 (row pointers), N + M
    offset = 0
    for name, entry in sorted(header.items(), key=lambda item: item[1]["data_offsets"][0]):
        if name not in ("joint_positions", "mouth_group") and not name.endswith((".col", ".values")):
            entry["shape"][0] = per_gaussian[entry["shape"][0]]
        manifest["tensors"][name]["shape"] = entry["shape"]
        size = itemsize[entry["dtype"]]
        for d in entry["shape"]:
            size *= d
        entry["data_offsets"] = [offset, offset + size]
        offset += size
    header["__metadata__"] = {**meta, "blendsplat.manifest": json.dumps(manifest)}
    raw = json.dumps(header).encode()
    with open(path, "wb") as f:
        f.write(len(raw).to_bytes(8, "little") + raw)
        f.truncate(8 + len(raw) + offset)


# ------------------------------------------------------------------------------------------- lifecycle
def test_an_upload_in_flight_at_sigterm_gets_503_and_the_drain_keeps_its_time(server):
    """Last test of ``server``: it stops it."""
    store = server.data / "bundles"
    s = _raw(server.http_port, b"PUT /v1/avatars/inflight HTTP/1.1\r\nHost: x\r\n" + server.auth + b""
             b"Content-Type: application/octet-stream\r\nContent-Length: 8000000\r\n\r\n", b"\x00" * 65536)
    with s:
        time.sleep(0.3)
        assert any(n.startswith(".upload-") for n in _staged(store))
        t0 = time.monotonic()
        server.proc.send_signal(signal.SIGTERM)
        answer = _read_all(s)
        answered = time.monotonic() - t0
    code = server.proc.wait(DELAY + DRAIN + MARGIN + 10)
    exited = time.monotonic() - t0
    assert answer.startswith(b"HTTP/1.1 503"), answer[:300]
    assert json.loads(answer.partition(b"\r\n\r\n")[2])["error"]["code"] == "UNAVAILABLE"
    assert answered < DELAY + 1.0, answered
    assert code == 0 and exited < DELAY + DRAIN + MARGIN, (exited, server.output()[-1500:])
    assert _staged(store) == []


def test_restart_with_odd_bundles_and_no_demo_comes_up_and_a_killed_servers_temp_files_are_cleaned(tmp_path, odd):
    """The store holds no demo avatar, and its first bundle is larger than the cache: the warm-up falls back to the
    built-in avatar (logged), the replica is ready, the odd avatars render, the big one is a named 429. A server
    killed mid-upload leaves its temp file; the next start removes it. A warm-up that fails altogether (a backend
    this machine lacks) leaves the process up and not ready, with the reason in /readyz and the log."""
    data = tmp_path / "data"
    store = BundleStore(data / "bundles")
    store.ensure()
    for name, path in odd.items():  # as uploads commit them
        fd, staged = store.staging()
        with os.fdopen(fd, "wb") as f:
            f.write(path.read_bytes())
        store.commit(staged, name)
    assert store.ids()[0] == "a-big"
    b = Serve(data, BLENDSPLAT_DEMO_AVATAR="none")
    try:
        assert "warm-up: avatar 'a-big' cannot be loaded" in b.output()
        for avatar_id in ("k0", "m0"):
            r = b.http.post("/v1/render", json={"avatarId": avatar_id, "width": 32, "height": 32})
            assert r.status_code == 200 and r.content, r.text
        assert b.http.post("/v1/avatars/a-big/load").status_code == 429
        s = _raw(b.http_port, b"PUT /v1/avatars/killed HTTP/1.1\r\nHost: x\r\n" + b.auth + b""
                 b"Content-Length: 1000000\r\n\r\n", b"\x00" * 5000)
        time.sleep(0.3)
        b.proc.kill()
        b.proc.wait()
        s.close()
    finally:
        b.stop()
    left = [n for n in _staged(data / "bundles") if n.startswith(".upload-")]
    assert len(left) == 1
    if __import__("torch").cuda.is_available():
        pytest.skip("the failing warm-up needs a machine without CUDA")
    c = Serve(data, wait_ready=False, BLENDSPLAT_DEMO_AVATAR="none", BLENDSPLAT_BACKEND="cuda",
              BLENDSPLAT_BODY_TIMEOUT_SECONDS="0.2")
    try:
        assert _staged(data / "bundles") == []  # older than twice the body timeout: a dead server's
        r = c.http.get("/readyz")
        assert r.status_code == 503 and r.json()["checks"]["warm_up"] is False
        assert "cuda" in r.json()["reasons"]["warm_up"] and "cuda" in c.output().split("not ready:")[1]
        assert c.proc.poll() is None
    finally:
        c.stop()
    assert c.proc.returncode == 0
