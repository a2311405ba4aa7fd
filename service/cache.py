"""Loaded avatars, shared by every session of this process: LRU under a memory budget.

An entry is a bundle read from the store and packed for the renderer; it counts as the file's bytes plus
:attr:`~render_core.renderer.AvatarRenderer.nbytes` (the native packing, or the cuda backend's GPU copy). Sessions
pin the entries they use; only unpinned entries are evicted. Concurrent requests for one avatar share a single
load.

The budget is checked twice: before anything is mapped or read, against the bundle file's size (header and data:
a lower bound of what the entry will count; room is made then, and the bytes are reserved while the load runs, so
concurrent loads cannot overshoot together), and after the renderer is built, against what the entry really
holds. A bundle that cannot fit is refused with RESOURCE_EXHAUSTED naming the avatar and the sizes, having
allocated nothing for it.

A bundle the store recorded as verified loads without the digest and finiteness pass. Each load of a cached
avatar checks that its file is still the one that was read (inode, size, modification time): a bundle replaced in
the store, by an upload through another replica, is read again, so no replica keeps serving the old avatar to new
sessions.
"""

from __future__ import annotations

import asyncio
import logging
import os
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

from render_core.avatar import Avatar
from render_core.bundle import BundleMappingError, read_bundle_and_manifest
from render_core.errors import BundleError
from render_core.raster.native import Schedule
from render_core.renderer import AvatarRenderer

from .errors import FailedPrecondition, NotFound, ResourceExhausted
from .metrics import Metrics
from .store import BundleStore

log = logging.getLogger(__name__)


@dataclass(eq=False)
class Loaded:
    id: str
    avatar: Avatar
    renderer: AvatarRenderer
    digest: str
    file_bytes: int
    memory_bytes: int
    file_id: tuple[int, int, int] = (0, 0, 0)  # (inode, size, mtime ns) of the file read; none for a built-in one
    pins: int = 0
    loaded_at: float = field(default_factory=time.time)


class AvatarCache:
    def __init__(self, store: BundleStore, budget: int, metrics: Metrics, backend: str | None = None,
                 threads: int = 0, schedule: Schedule | None = None):
        self.store, self.budget, self.metrics = store, budget, metrics
        self.backend, self.threads, self.schedule = backend, threads, schedule
        self._entries: OrderedDict[str, Loaded] = OrderedDict()  # least recently used first
        self._loading: dict[str, asyncio.Future[Loaded]] = {}
        self._reserved: dict[str, int] = {}  # loads in progress: the bytes admitted for them before reading

    @property
    def used(self) -> int:
        return sum(e.memory_bytes for e in self._entries.values())

    def get(self, avatar_id: str) -> Loaded | None:
        return self._entries.get(avatar_id)

    def loaded_ids(self) -> list[str]:
        return list(self._entries)

    async def load(self, avatar_id: str) -> Loaded:
        """The avatar, loading it from the store if needed (NotFound, InvalidArgument for a broken bundle)."""
        entry = self._entries.get(avatar_id)
        if entry is not None and entry.file_id != _file_id(self.store.existing(avatar_id)):
            log.info("avatar %s was replaced in the store: reading it again", avatar_id)
            self.unload(avatar_id)  # sessions that hold the old one keep it until they end
            entry = None
        if entry is not None:
            self.metrics.cache_hits.inc()
            self._entries.move_to_end(avatar_id)
            return entry
        if avatar_id in self._loading:  # someone else is loading it: share that load
            self.metrics.cache_hits.inc()
            return await asyncio.shield(self._loading[avatar_id])
        path = self.store.existing(avatar_id)  # NotFound: a lookup of nothing is neither a hit nor a miss
        self.metrics.cache_misses.inc()
        # Before mapping or reading anything: the file's size (a lower bound of the entry) must fit.
        admitted = _file_bytes(path, avatar_id)
        self._make_room(admitted, avatar_id, before_reading=True)
        future: asyncio.Future[Loaded] = asyncio.get_running_loop().create_future()
        self._loading[avatar_id] = future
        self._reserved[avatar_id] = admitted
        try:
            entry = await asyncio.to_thread(self._read, avatar_id, path)
            del self._reserved[avatar_id]
            self._make_room(entry.memory_bytes, avatar_id)
            self._entries[avatar_id] = entry
            self._update_gauges()
            future.set_result(entry)
            log.info("loaded avatar %s (%d Gaussians, %.0f MB)", avatar_id, entry.avatar.num_gaussians
                     + entry.avatar.num_mouth, entry.memory_bytes / 1e6)
            return entry
        except BaseException as e:
            future.set_exception(e)
            future.exception()  # retrieved: waiters re-raise it, nobody else has to
            raise
        finally:
            del self._loading[avatar_id]
            self._reserved.pop(avatar_id, None)

    async def acquire(self, avatar_id: str) -> Loaded:
        entry = await self.load(avatar_id)
        entry.pins += 1
        return entry

    def release(self, entry: Loaded) -> None:
        entry.pins -= 1

    def unload(self, avatar_id: str) -> bool:
        """Drop an avatar from memory (sessions using it keep their reference until they end)."""
        entry = self._entries.pop(avatar_id, None)
        self._update_gauges()
        return entry is not None

    def _read(self, avatar_id: str, path: Path) -> Loaded:
        return read_entry(avatar_id, path, self.backend, self.threads, verify=not self.store.verified(path),
                          schedule=self.schedule)

    def _make_room(self, need: int, for_id: str, *, before_reading: bool = False) -> None:
        """Evict unpinned avatars, least recently used first, until ``need`` more bytes fit beside the loaded
        avatars and the loads in progress; ResourceExhausted naming the avatar and the sizes when they cannot."""
        what = f"its bundle file is {_mb(need)}" if before_reading else f"it needs {_mb(need)}"
        if need > self.budget:
            raise ResourceExhausted(f"avatar {for_id!r} does not fit in this replica's cache: {what}, more than the "
                                    f"cache budget of {_mb(self.budget)}", field="avatar_id")
        reserved = sum(n for k, n in self._reserved.items() if k != for_id)
        for victim in [k for k, e in self._entries.items() if e.pins == 0]:
            if self.used + reserved + need <= self.budget:
                break
            log.info("evicting avatar %s (least recently used)", victim)
            del self._entries[victim]
            self._update_gauges()
        if self.used + reserved + need > self.budget:
            loading = f" and {_mb(reserved)} by loads in progress" if reserved else ""
            raise ResourceExhausted(f"no room for avatar {for_id!r} ({what}): {_mb(self.used)} of the "
                                    f"{_mb(self.budget)} budget are held by avatars in use{loading}",
                                    field="avatar_id")

    def _update_gauges(self) -> None:
        self.metrics.cache_bytes.set(self.used)
        self.metrics.cache_avatars.set(len(self._entries))


def _mb(n: int) -> str:
    return f"{n / 1e6:.1f} MB"


def _file_bytes(path: Path, avatar_id: str) -> int:
    try:
        return path.stat().st_size
    except FileNotFoundError:
        raise NotFound(f"avatar {avatar_id!r} was removed from the bundle store", field="avatar_id") from None


def _file_id(path: Path) -> tuple[int, int, int]:
    st = os.stat(path)
    return st.st_ino, st.st_size, st.st_mtime_ns


def read_entry(avatar_id: str, path: Path, backend: str | None = None, threads: int = 0, *, verify: bool = True,
               seconds: dict[str, float] | None = None, schedule: Schedule | None = None) -> Loaded:
    """Read a bundle of the store and pack it for ``backend``: what a cache miss costs (``blendsplat bench load``
    times it). ``verify``: the digest and finiteness pass (skipped for a bundle the store recorded as verified;
    the layout, manifest and shapes are always checked). ``seconds`` gets the stages ``read`` and ``renderer``.
    ``schedule``: the native renderer's (default: every switch on)."""
    file_id = _file_id(path)  # before reading: a file replaced during the read is noticed at the next load
    t0 = time.perf_counter()
    try:
        avatar, manifest = read_bundle_and_manifest(path, verify=verify)
    except BundleMappingError as e:  # this machine's limit, not the file's fault
        raise ResourceExhausted(f"avatar {avatar_id!r} cannot be loaded: {e.detail}", field="avatar_id") from None
    except BundleError as e:
        raise FailedPrecondition(f"avatar {avatar_id!r} has a broken bundle in the store: {e}",
                                 field="avatar_id") from None
    t1 = time.perf_counter()
    renderer = AvatarRenderer(avatar, backend, threads=threads, schedule=schedule)
    if seconds is not None:
        seconds.update(read=t1 - t0, renderer=time.perf_counter() - t1)
    file_bytes = path.stat().st_size
    # The avatar as read (about the file's size) plus what the renderer holds for it, host or device.
    return Loaded(avatar_id, avatar, renderer, manifest.get("digest", ""), file_bytes, file_bytes + renderer.nbytes,
                  file_id)
