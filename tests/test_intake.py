"""service.intake: the one upload intake (declared length, admission before, spooling off the event loop, the
quota after the body) and that a refused body leaves nothing behind."""

import asyncio
import hashlib
import threading

import pytest

from service import intake
from service.errors import InvalidArgument, ResourceExhausted
from service.intake import BodyTooLarge, UploadIntake, declared_length


class Quota:
    """The two checks the intake asks of Access, with a tenant quota of ``quota`` bytes over ``used``."""

    def __init__(self, quota: int, used: int = 0):
        self.quota, self.used, self.calls = quota, used, []

    def admit_upload(self, principal, incoming: int) -> None:
        self.calls.append(("admit", incoming))
        self.check_quota(principal, incoming, record=False)

    def check_quota(self, principal, incoming: int, record: bool = True) -> None:
        if record:
            self.calls.append(("quota", incoming))
        if self.used + incoming > self.quota:
            raise ResourceExhausted(f"with {incoming} more bytes the tenant would pass its quota of {self.quota}",
                                    field="authorization")


async def _body(*parts: bytes):
    for p in parts:
        await asyncio.sleep(0)
        yield p


def test_declared_length_is_parsed_once_and_strictly():
    assert declared_length({}) is None
    assert declared_length({"content-length": "123"}) == 123
    for bad in ("-1", "1e3", "12 34", "０", "9" * 30):
        with pytest.raises(InvalidArgument, match="Content-Length"):
            declared_length({"content-length": bad})


def test_a_chunked_body_over_the_quota_is_refused_after_it_arrived_and_nothing_is_kept(tmp_path):
    access = Quota(quota=1000, used=400)
    path = tmp_path / "body"
    # declared nothing (chunked): admitted on 0 bytes, then refused on the 700 that arrived
    with pytest.raises(ResourceExhausted, match="quota"):
        asyncio.run(UploadIntake(access).receive(None, _body(b"a" * 300, b"b" * 400), path, limit=10_000,
                                                 field="file"))
    assert access.calls == [("admit", 0), ("quota", 700)]
    assert not path.exists()
    # under the quota: kept, with its size and digest
    got = asyncio.run(UploadIntake(access).receive(None, _body(b"a" * 300, b"b" * 200), path, limit=10_000,
                                                   field="file"))
    assert got.size == 500 and got.sha256 == hashlib.sha256(b"a" * 300 + b"b" * 200).hexdigest()
    assert path.read_bytes() == b"a" * 300 + b"b" * 200 and (path.stat().st_mode & 0o777) == 0o600


def test_the_limit_is_enforced_on_the_declared_and_the_received_size(tmp_path):
    access = Quota(quota=10**9)
    with pytest.raises(BodyTooLarge, match="larger than 10 bytes"):
        asyncio.run(UploadIntake(access).receive(None, _body(b"x"), tmp_path / "a", limit=10, field="bundle",
                                                 declared=11))
    assert access.calls == [] and not (tmp_path / "a").exists()  # refused before admission and before a byte
    with pytest.raises(BodyTooLarge) as e:
        asyncio.run(UploadIntake(access).receive(None, _body(b"x" * 8, b"y" * 8), tmp_path / "b", limit=10,
                                                 field="bundle", declared=5))
    assert e.value.field == "bundle" and not (tmp_path / "b").exists()


@pytest.fixture
def writers(monkeypatch) -> list[int]:
    """The threads the intake's disk writes ran on (batches of 1000 bytes)."""
    seen: list[int] = []
    real = intake._write

    def spy(out, data):
        seen.append(threading.get_ident())
        real(out, data)

    monkeypatch.setattr(intake, "_write", spy)
    monkeypatch.setattr(intake, "WRITE_BATCH", 1000)
    return seen


def test_the_body_is_never_written_on_the_event_loop(tmp_path, writers):
    async def main():
        loop_thread = threading.get_ident()
        await UploadIntake(Quota(10**9)).receive(None, _body(*[b"z" * 600] * 5), tmp_path / "c", limit=10**6,
                                                 field="file")
        return loop_thread

    loop_thread = asyncio.run(main())
    assert len(writers) >= 3 and loop_thread not in writers
    assert (tmp_path / "c").stat().st_size == 3000


def test_a_client_that_goes_away_leaves_nothing(tmp_path):
    async def endless():
        yield b"x" * 100
        await asyncio.sleep(3600)
        yield b"never"

    async def main():
        task = asyncio.create_task(UploadIntake(Quota(10**9)).receive(None, endless(), tmp_path / "d", limit=10**6,
                                                                       field="file"))
        await asyncio.sleep(0.05)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    asyncio.run(main())
    assert not (tmp_path / "d").exists()


def test_the_avatar_put_spools_its_body_off_the_event_loop(tmp_path, writers):
    """Engine.replace (the avatar PUT) goes through the intake: no byte of the bundle is written on the loop."""
    from render_core.bundle import write_bundle
    from render_core.facemodel.synthetic import synth_avatar
    from service.engine import Engine
    from service.settings import Settings

    write_bundle(synth_avatar(gaussians=200, blendshapes=3, seed=2), tmp_path / "a.bundle", precision="fp16")
    data = (tmp_path / "a.bundle").read_bytes()
    engine = Engine(Settings(data_dir=tmp_path / "data", warmup_size=32))

    async def main():
        info = await engine.replace("spooled", _body(*[data[i:i + 1000] for i in range(0, len(data), 1000)]),
                                    len(data))
        return threading.get_ident(), info

    loop_thread, info = asyncio.run(main())
    assert info.id == "spooled" and writers and loop_thread not in writers
    assert sum(1 for p in (tmp_path / "data").rglob("*.tmp")) == 0  # the spool became the bundle
