"""The upload store (service.jobs.uploads): an archive streamed in, checked, extracted, validated and published by one
rename; every refusal (too large, hostile archive, invalid dataset, client gone, cancelled) leaves nothing; real
deletion, retention and start-up cleaning."""

from __future__ import annotations

import asyncio
import hashlib
import json
import threading
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from test_archive import HOSTILE, make_dataset, tar_archive, zip_archive

from render_core.data import validate_dataset
from service.errors import BodyTooLarge, InvalidArgument, NotFound
from service.jobs import uploads as uploads_module
from service.jobs.archive import ArchiveError, ArchiveLimits
from service.jobs.uploads import ID_PATTERN, InvalidDataset, UploadStore


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> dict[str, bytes]:
    root = make_dataset(tmp_path_factory.mktemp("dataset") / "ds")
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture
def archive(tmp_path, dataset) -> Path:
    """A valid upload: a .tar.gz with the dataset inside one folder."""
    return tar_archive(tmp_path / "upload.tar.gz", dataset, prefix="my-take/", gz=True)


@pytest.fixture
def store(tmp_path) -> UploadStore:
    return UploadStore(tmp_path / "data" / "uploads")


async def chunks_of(data: bytes, size: int = 4096, pulled: list | None = None, fail_at: int | None = None):
    """The body as a client sends it, in pieces; ``pulled`` counts the pieces read; ``fail_at`` drops the
    connection at that offset."""
    for start in range(0, len(data), size):
        if fail_at is not None and start >= fail_at:
            raise ConnectionResetError("the client went away")
        if pulled is not None:
            pulled.append(start)
        yield data[start:start + size]
        await asyncio.sleep(0)


def receive(store: UploadStore, data: bytes, *, max_bytes: int = 1 << 30, **kw):
    return asyncio.run(store.receive(chunks_of(data, **kw), max_bytes=max_bytes, filename="C:\\takes\\my-take.tgz"))


def leftovers(store: UploadStore) -> list[str]:
    return sorted(p.name for p in store.root.iterdir()) if store.root.exists() else []


# ---------------------------------------------------------------------------------------------------------- happy
@pytest.mark.parametrize("kind", ["tar.gz", "zip"])
def test_an_upload_is_published_with_its_record_and_no_archive(store, tmp_path, dataset, kind):
    path = (tar_archive(tmp_path / "a", dataset, prefix="take/", gz=True) if kind == "tar.gz"
            else zip_archive(tmp_path / "a", dataset))
    raw = path.read_bytes()
    upload = receive(store, raw)
    assert ID_PATTERN.match(upload.id)
    assert (upload.size, upload.sha256) == (len(raw), hashlib.sha256(raw).hexdigest())
    assert (upload.frames, upload.width, upload.height, upload.face_model) == (4, 32, 32, "flame")
    assert upload.filename == "my-take.tgz" and upload.archive == kind
    assert abs(upload.created_at - datetime.now(UTC)) < timedelta(minutes=1)
    # one folder, holding the dataset and the record: the archive is gone, nothing else is left
    assert leftovers(store) == [upload.id]
    assert sorted(p.name for p in (store.root / upload.id).iterdir()) == ["dataset", "upload.json"]
    folder = store.path(upload.id)
    assert folder == store.root / upload.id / "dataset" and validate_dataset(folder) == []
    assert {p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()} == dataset
    record = json.loads((store.root / upload.id / "upload.json").read_text())
    assert set(record) == {"id", "created_at", "size", "sha256", "frames", "width", "height", "face_model",
                           "filename", "archive", "tenant",  # tenant: the owner (service/access/auth.py)
                           "stored_bytes", "files"}  # what it takes on disk, as extracted (the tenant's quota)
    assert record["files"] == len(list((store.root / upload.id).rglob("*"))) + 1  # its entries and its folder
    assert record["stored_bytes"] >= sum(len(b) for b in dataset.values())
    assert record["id"] == upload.id and record["created_at"].endswith("Z")
    assert store.get(upload.id) == upload and store.list() == [upload]


def test_uploads_are_listed_oldest_first(store, archive):
    first = receive(store, archive.read_bytes())
    second = receive(store, archive.read_bytes())
    assert first.id != second.id
    assert {u.id for u in store.list()} == {first.id, second.id}
    assert store.list() == sorted(store.list(), key=lambda u: (u.created_at, u.id))


# ------------------------------------------------------------------------------------------------------- refusals
@pytest.mark.parametrize("name", ["traversal", "absolute", "symlink", "hard link", "fifo", "bomb tar.gz",
                                  "bomb after the end", "too many files", "corrupt tar.gz", "truncated zip",
                                  "zip bad crc", "duplicate", "not an archive", "empty file"])
def test_a_hostile_archive_is_refused_and_leaves_nothing(tmp_path, dataset, name):
    build, limits, reason, _ = HOSTILE[name]
    store = UploadStore(tmp_path / "uploads", limits=limits)
    raw = build(tmp_path / "upload", dataset).read_bytes()
    with pytest.raises(ArchiveError) as caught:
        receive(store, raw)
    assert caught.value.reason == reason and caught.value.field == "file"
    assert leftovers(store) == []


def test_too_large_is_refused_without_reading_the_rest(store, archive):
    raw = archive.read_bytes()
    pulled: list[int] = []
    with pytest.raises(BodyTooLarge, match="larger than 1000 bytes") as caught:
        receive(store, raw, max_bytes=1000, size=100, pulled=pulled)
    assert isinstance(caught.value, InvalidArgument) and caught.value.field == "file"
    assert len(pulled) == 11 < len(raw) // 100
    assert leftovers(store) == []


def test_a_client_that_goes_away_leaves_nothing(store, archive):
    with pytest.raises(ConnectionResetError):
        receive(store, archive.read_bytes(), size=256, fail_at=1024)
    assert leftovers(store) == []


def test_an_invalid_dataset_is_refused_naming_every_problem(store, tmp_path, dataset):
    broken = dict(dataset)
    broken["frames/00001.png"] = dataset["frames/00001.png"][:40]  # truncated PNG
    del broken["masks/00002.png"]
    manifest = json.loads(dataset["dataset.json"])
    manifest["fps"] = -1
    broken["dataset.json"] = json.dumps(manifest).encode()
    raw = zip_archive(tmp_path / "bad.zip", broken, prefix="take/").read_bytes()
    with pytest.raises(InvalidDataset) as caught:
        receive(store, raw)
    e = caught.value
    assert e.field == "file" and isinstance(e, InvalidArgument)
    assert e.count == len(e.problems) >= 3
    for needle in ("frames/00001.png", "masks/00002.png", "fps"):
        assert needle in str(e), str(e)
    assert leftovers(store) == []


def test_invalid_dataset_message_is_bounded():
    e = InvalidDataset([f"frames/{i:05d}.png: " + "x" * 1000 for i in range(500)])
    assert e.count == 500 and len(e.problems) == 50 and all(len(p) <= 300 for p in e.problems)
    assert len(str(e)) < 4200 and "500 problems" in str(e) and "more" in str(e)


def test_cancelled_while_validating_leaves_nothing(store, archive, monkeypatch):
    """The client goes away while the worker thread validates: the thread finishes but never publishes."""
    entered, release = threading.Event(), threading.Event()
    real = uploads_module.validate_dataset

    def slow_validate(path):
        entered.set()
        release.wait(10)
        return real(path)

    monkeypatch.setattr(uploads_module, "validate_dataset", slow_validate)

    async def scenario():
        task = asyncio.create_task(store.receive(chunks_of(archive.read_bytes()), max_bytes=1 << 30))
        while not entered.is_set():
            await asyncio.sleep(0.005)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        release.set()
        for _ in range(400):  # the thread cleans its staging folder up
            if not leftovers(store):
                return
            await asyncio.sleep(0.005)

    asyncio.run(scenario())
    assert leftovers(store) == []


# --------------------------------------------------------------------------------------- deletion and retention
def test_delete_removes_the_files(store, archive):
    upload = receive(store, archive.read_bytes())
    keep = receive(store, archive.read_bytes())
    store.delete(upload.id)  # a small upload's files are gone when it returns (a large one's soon after)
    assert leftovers(store) == [keep.id]
    for call in (store.get, store.path, store.delete):
        with pytest.raises(NotFound):
            call(upload.id)


@pytest.mark.parametrize("bad", ["../uploads", "upl_../../../etc/passwd", "", "upl_short", "x" * 30,
                                 "upl_" + "a" * 20 + "/..", ".staging-abc"])
def test_ids_are_validated(store, bad):
    for call in (store.get, store.path, store.delete):
        with pytest.raises(InvalidArgument, match="not an upload id"):
            call(bad)


def test_sweep_deletes_uploads_past_retention(store, archive):
    old = receive(store, archive.read_bytes())
    new = receive(store, archive.read_bytes())
    record = store.root / old.id / "upload.json"
    data = json.loads(record.read_text())
    data["created_at"] = "2020-01-01T00:00:00Z"
    record.write_text(json.dumps(data))
    assert store.sweep(timedelta(days=30)) == [old.id]
    assert leftovers(store) == [new.id]
    assert store.sweep(timedelta(days=30)) == []
    assert store.sweep(timedelta(days=30), now=new.created_at + timedelta(days=31)) == [new.id]
    assert leftovers(store) == []


def test_clean_stale_removes_what_a_killed_process_left(store, archive):
    upload = receive(store, archive.read_bytes())
    (store.root / ".incoming-0123.tmp").write_bytes(b"half an archive")
    (store.root / ".staging-4567" / "extract").mkdir(parents=True)
    (store.root / ".staging-4567" / "extract" / "dataset.json").write_text("{}")
    (store.root / ".deleting-upl_x-89").mkdir()
    assert store.clean_stale(older_than=timedelta(hours=1)) == 0  # fresh: maybe another process's upload
    assert store.clean_stale() == 3
    assert leftovers(store) == [upload.id]
    assert store.get(upload.id) == upload


def test_an_empty_store(tmp_path):
    store = UploadStore(tmp_path / "nothing-yet")
    assert store.list() == [] and store.sweep(timedelta(0)) == [] and store.clean_stale() == 0
    with pytest.raises(NotFound):
        store.get("upl_" + "a" * 22)
    assert isinstance(UploadStore(tmp_path).limits, ArchiveLimits)
