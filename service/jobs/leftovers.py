"""What the upload store's work in progress leaves in its folder, and how it goes (:mod:`service.jobs.uploads`).

**Uploads in progress** live under names that start with ``.`` (never an id), each carrying the upload's token
``T`` (20 hex digits)::

    .incoming-T.lock   held (an exclusive ``flock``) by the receiving process from the start of the upload to its end
    .incoming-T.tmp    the body being received
    .staging-T         its extraction and validation

:func:`clean_stale` (at start and at each retention sweep) removes an upload's entries when nobody holds its lock:
the process that received it is gone (SIGKILL, a crash, a lost node), whatever their age, so a restarted server
starts clean; an upload another process is still receiving (replicas share the folder) is never touched. Names
without a lock (an older version's: a 16-digit token, ``.deleting-*``) go by age, as before. Where the file system
cannot lock, everything goes by age.

**Deletion** is a rename into the trash, then the removal of the tree in a background thread (:class:`Trash`): a
deleted upload is gone for every reader at once, and a 100,000-file upload does not hold the caller for the
half-minute its files take to unlink. The trash is ``.deleting-<id>-<random>`` in the same folder (a rename never
crosses file systems); :meth:`Trash.empty` at start removes what a killed process left there.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import re
import secrets
import shutil
import threading
import time
from collections import deque
from datetime import timedelta
from pathlib import Path

log = logging.getLogger(__name__)

TEMP_PREFIXES = (".incoming-", ".staging-", ".deleting-")
TRASH_PREFIX = ".deleting-"
DELETE_WAIT_SECONDS = 0.5  # a deletion waits this long for its files to go, then leaves the rest to the trash
_LOCKED = re.compile(r"^\.(?:incoming|staging)-([0-9a-f]{20})(?:\.tmp|\.lock)?$")  # an upload's entries, by token


def lock_path(root: Path, token: str) -> Path:
    return root / f".incoming-{token}.lock"


class UploadLock:
    """The lock of one upload in progress: :meth:`acquire` picks a fresh token and holds its lock file (created
    exclusively, then locked, then checked to be the file still named so: a cleaner that took it between the two
    steps removed it, and another token is tried); :meth:`release` removes it. Without file locks (ENOLCK, EINVAL)
    the file is kept all the same and the upload's leftovers go by age."""

    def __init__(self, root: Path):
        self.root = root
        self.token = ""
        self._fd: int | None = None

    def acquire(self) -> str:
        for _ in range(100):
            token = secrets.token_hex(10)
            path = lock_path(self.root, token)
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o600)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:  # a cleaner holds it this instant: it will remove it
                os.close(fd)
                continue
            except OSError as e:
                if e.errno not in (errno.ENOLCK, errno.EINVAL, errno.EOPNOTSUPP):
                    os.close(fd)
                    raise
            if _same_file(fd, path):
                self.token, self._fd = token, fd
                return token
            os.close(fd)
        raise OSError(errno.EAGAIN, "could not take an upload lock")

    def release(self) -> None:
        if self._fd is None:
            return
        with contextlib.suppress(OSError):
            lock_path(self.root, self.token).unlink()
        os.close(self._fd)
        self._fd = None


def _same_file(fd: int, path: Path) -> bool:
    try:
        mine, named = os.fstat(fd), os.stat(path)
    except FileNotFoundError:
        return False
    return (mine.st_dev, mine.st_ino) == (named.st_dev, named.st_ino)


def _owner_gone(root: Path, token: str) -> bool | None:
    """True when nobody holds the upload's lock (its receiver is gone), False when someone does, None when the file
    system cannot tell."""
    try:
        fd = os.open(lock_path(root, token), os.O_RDWR | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        return True  # the lock goes last: its receiver finished or a cleaner removed it
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    except OSError:
        return None
    finally:
        os.close(fd)  # a dead receiver never comes back: the lock need not be held while its entries go
    return True


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        p.unlink(missing_ok=True)


def clean_stale(root: Path, older_than: timedelta = timedelta(0)) -> int:
    """Remove the entries of uploads whose receiving process is gone, and unlocked leftovers (an older version's,
    or where nothing can be locked) last modified more than ``older_than`` ago (module docstring); how many
    entries were removed (lock files not counted)."""
    if not root.is_dir():
        return 0
    cutoff = time.time() - older_than.total_seconds()
    by_token: dict[str, list[Path]] = {}
    aged: list[Path] = []
    for p in root.iterdir():
        if not p.name.startswith(TEMP_PREFIXES):
            continue
        match = _LOCKED.match(p.name)
        if match:
            by_token.setdefault(match.group(1), []).append(p)
        else:
            aged.append(p)
    count = 0
    for token, entries in by_token.items():
        gone = _owner_gone(root, token)
        if gone is None:
            aged.extend(entries)
        elif gone:
            for p in sorted(entries, key=lambda e: e.name.endswith(".lock")):  # the lock last
                _remove(p)
                count += not p.name.endswith(".lock")
    for p in aged:
        try:
            if older_than and p.lstat().st_mtime > cutoff:
                continue
        except FileNotFoundError:
            continue
        _remove(p)
        count += 1
    return count


class Trash:
    """Deleted trees renamed out of sight in ``root`` (``.deleting-<name>-<random>``) and removed by a background
    thread, one tree at a time (module docstring). ``wait``: how long a deletion waits for its files to go."""

    def __init__(self, root: Path, wait: float = DELETE_WAIT_SECONDS):
        self.root, self.wait = root, wait
        self._queue: deque[Path] = deque()
        self._busy = threading.Condition()
        self._worker: threading.Thread | None = None

    def discard(self, path: Path) -> bool:
        """Rename ``path`` into the trash (False when it is not there) and have it removed; wait up to ``wait``
        seconds for that (a small tree is gone from the disk when this returns, a large one soon after)."""
        doomed = self.root / f"{TRASH_PREFIX}{path.name}-{secrets.token_hex(4)}"
        try:
            os.rename(path, doomed)
        except FileNotFoundError:
            return False
        self._enqueue([doomed])
        deadline = time.monotonic() + self.wait
        with self._busy:
            while doomed.exists() and (left := deadline - time.monotonic()) > 0:
                self._busy.wait(min(left, 0.05))
        return True

    def empty(self) -> int:
        """Have everything in the trash removed (a killed process's deletions included); how many trees."""
        if not self.root.is_dir():
            return 0
        doomed = [p for p in self.root.iterdir() if p.name.startswith(TRASH_PREFIX)]
        self._enqueue(doomed)
        return len(doomed)

    def drain(self, timeout: float = 60.0) -> bool:
        """Wait until the trash thread has removed everything queued; whether it did within ``timeout``."""
        deadline = time.monotonic() + timeout
        with self._busy:
            while self._queue or self._worker is not None:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._busy.wait(min(left, 0.05))
        return True

    def _enqueue(self, paths: list[Path]) -> None:
        if not paths:
            return
        with self._busy:
            self._queue.extend(p for p in paths if p not in self._queue)
            if self._worker is None:
                self._worker = threading.Thread(target=self._work, name="upload-trash", daemon=True)
                self._worker.start()

    def _work(self) -> None:
        while True:
            with self._busy:
                if not self._queue:
                    self._worker = None
                    self._busy.notify_all()
                    return
                doomed = self._queue[0]
            try:
                _remove(doomed)  # errors ignored: a tree another process empties at the same time
            except OSError as e:
                log.warning("uploads: could not remove a deleted upload (%s); the next start tries again", e)
            with self._busy:
                self._queue.popleft()
                self._busy.notify_all()
