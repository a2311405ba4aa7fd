"""The bundle store's integrity record: verified once when a bundle enters, trusted while the file is unchanged,
and a bundle replaced behind the store's back noticed at the next load."""

from __future__ import annotations

import asyncio
import json
import os

import pytest

from render_core import bundle as bundle_module
from render_core.bundle import write_bundle
from render_core.tools.synth import synth_avatar
from service.cache import AvatarCache
from service.errors import FailedPrecondition, InvalidArgument
from service.metrics import Metrics
from service.store import RECORD, BundleStore


def _stage(store: BundleStore, data: bytes):
    fd, staged = store.staging()
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    return staged


@pytest.fixture
def store(tmp_path):
    s = BundleStore(tmp_path / "bundles")
    s.ensure()
    return s


@pytest.fixture(scope="module")
def bundles(tmp_path_factory):
    root = tmp_path_factory.mktemp("store-bundles")
    paths = []
    for seed in (1, 2):
        path = root / f"{seed}.bundle"
        write_bundle(synth_avatar(gaussians=300, blendshapes=3, seed=seed), path)
        paths.append(path)
    return paths


def _count_digest_checks(monkeypatch) -> list:
    calls = []
    real = bundle_module._verify_digest
    monkeypatch.setattr(bundle_module, "_verify_digest", lambda *a: (calls.append(1), real(*a))[1])
    return calls


def test_commit_records_the_verification_and_loads_trust_it(store, bundles, monkeypatch):
    manifest = store.commit(_stage(store, bundles[0].read_bytes()), "a")
    path = store.path("a")
    record = json.loads(path.with_name(path.name + RECORD).read_text())
    assert record["digest"] == manifest["digest"] and record["size"] == path.stat().st_size
    assert store.verified(path) and store.ids() == ["a"]  # the record is never taken for an avatar
    calls = _count_digest_checks(monkeypatch)
    entry = asyncio.run(AvatarCache(store, 1 << 40, Metrics()).load("a"))
    assert entry.avatar.num_gaussians == 300 and calls == []  # trusted: no second pass over the data


def test_a_tampered_upload_is_refused_and_leaves_the_store_as_it_was(store, bundles):
    store.commit(_stage(store, bundles[0].read_bytes()), "a")
    before = store.path("a").read_bytes()
    raw = bytearray(bundles[1].read_bytes())
    raw[-10] ^= 0xFF  # a flipped data byte: the digest no longer matches
    with pytest.raises(InvalidArgument, match="digest"):
        store.commit(_stage(store, bytes(raw)), "a")
    assert store.path("a").read_bytes() == before and store.verified(store.path("a"))
    assert sorted(p.name for p in store.root.iterdir()) == ["a.bundle", "a.bundle" + RECORD]  # no staged file left


def test_a_bundle_replaced_behind_the_stores_back_is_verified_and_reloaded(store, bundles, monkeypatch):
    store.commit(_stage(store, bundles[0].read_bytes()), "a")
    cache = AvatarCache(store, 1 << 40, Metrics())
    first = asyncio.run(cache.load("a"))
    # Another writer replaces the file without the store (no new record): a different header and size.
    other = synth_avatar(gaussians=310, blendshapes=3, seed=9)
    write_bundle(other, store.path("a"))
    assert not store.verified(store.path("a"))
    calls = _count_digest_checks(monkeypatch)
    second = asyncio.run(cache.load("a"))
    assert second is not first and second.avatar.num_gaussians == 310 and calls == [1]  # fully verified
    # A corrupt replacement is refused at its next load, not served.
    raw = bytearray(store.path("a").read_bytes())
    raw[-10] ^= 0xFF
    store.path("a").write_bytes(bytes(raw))
    with pytest.raises(FailedPrecondition, match="broken bundle"):
        asyncio.run(cache.load("a"))
    assert "a" not in cache.loaded_ids()


def test_an_upload_through_the_store_replaces_the_cached_avatar(store, bundles):
    store.commit(_stage(store, bundles[0].read_bytes()), "a")
    cache = AvatarCache(store, 1 << 40, Metrics())  # another replica's cache: nobody tells it of the upload
    first = asyncio.run(cache.load("a"))
    store.commit(_stage(store, bundles[1].read_bytes()), "a")
    second = asyncio.run(cache.load("a"))
    assert second is not first and second.digest != first.digest and store.verified(store.path("a"))
    assert asyncio.run(cache.load("a")) is second  # unchanged since: a cache hit


def test_warm_up_without_any_avatar_renders_a_built_in_one(tmp_path):
    """An empty store and no demo avatar: readiness still comes, from a tiny built-in avatar (no file)."""
    from service.engine import Engine
    from service.settings import Settings

    async def scenario():
        engine = Engine(Settings(data_dir=tmp_path, warmup_size=32))
        await engine.start()
        try:
            await engine.warm_up(None)
            return engine.ready
        finally:
            await engine.close()

    assert asyncio.run(scenario())
