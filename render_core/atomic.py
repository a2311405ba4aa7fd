"""Atomic file replacement: a reader sees the old file or the whole new one, never a torn write.

Every file the library and the service publish (bundles, face models, reports, checkpoints, uploads) goes through
:func:`atomic_path` (write to a temporary file in the same folder, then rename) or :func:`publish` (rename a file
that is already written); :func:`create_once` writes a file only when there is none (a generated secret that
processes starting together must agree on). A process killed while writing leaves its temporary file
(``.<name>.<16 hex>.tmp``): :func:`remove_stale` removes them from a folder whose writer is known to be gone (a
resumed training run's).
"""

from __future__ import annotations

import os
import re
import secrets
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

TEMP_NAME = re.compile(r"^\..+\.[0-9a-f]{16}\.tmp$")  # what atomic_path writes to: .<name>.<16 hex>.tmp


def publish(tmp: str | os.PathLike, path: str | os.PathLike, *, mode: int = 0o644) -> Path:
    """Make the written file ``tmp`` readable with ``mode``, flush it to disk and rename it onto ``path`` (same
    file system). The rename is then made durable where the platform can open a folder."""
    tmp, path = Path(tmp), Path(path)
    with open(tmp, "rb+") as f:
        os.fchmod(f.fileno(), mode)  # some writers (safetensors, mkstemp) create 0600 files; published ones are shared
        os.fsync(f.fileno())
    os.replace(tmp, path)
    with suppress(OSError):  # not every platform can open a directory
        fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    return path


def create_once(path: str | os.PathLike, text: str, *, mode: int = 0o600) -> bool:
    """Publish ``text`` as ``path`` (with ``mode``, whole or not at all) unless ``path`` exists; True when this call
    created it. Processes racing on the same ``path`` agree: exactly one creates it (a hard link never replaces),
    the others find theirs refused and read the winner's."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.{secrets.token_hex(8)}.tmp"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as out:
            out.write(text)
        try:
            os.link(tmp, path)
        except FileExistsError:
            return False
        return True
    finally:
        tmp.unlink(missing_ok=True)


@contextmanager
def atomic_path(path: str | os.PathLike, *, mode: int = 0o644) -> Iterator[Path]:
    """Yield a fresh temporary path beside ``path`` to write to; on a normal exit publish it as ``path``
    (:func:`publish`), on an exception remove it and leave ``path`` as it was.

    Example::

        with atomic_path("head.bundle") as tmp:
            safetensors.numpy.save_file(arrays, str(tmp))
    """
    path = Path(path)
    tmp = path.parent / f".{path.name}.{secrets.token_hex(8)}.tmp"
    # O_EXCL: never clobber someone else's file; the umask applies as for any new file until publish sets the mode
    os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
    try:
        yield tmp
        publish(tmp, path, mode=mode)
    except BaseException:
        with suppress(OSError):
            os.unlink(tmp)
        raise


def remove_stale(folder: str | os.PathLike) -> list[str]:
    """Remove the temporary files :func:`atomic_path` left in ``folder`` (not below it) when its process was killed
    mid-write; the names removed. Only for a folder no live process writes to (the caller knows: e.g. a training
    run resuming in its own work folder)."""
    removed = []
    try:
        entries = list(os.scandir(folder))
    except FileNotFoundError:
        return removed
    for entry in entries:
        if TEMP_NAME.match(entry.name) and entry.is_file(follow_symlinks=False):
            with suppress(FileNotFoundError):
                os.unlink(entry.path)
                removed.append(entry.name)
    return removed
