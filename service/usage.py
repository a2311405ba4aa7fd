"""What a tenant's files take on disk: the one measure the storage quota counts (issue 28).

The quota charges bytes **stored**, not bytes received: an archive's extraction (tiny files each take a whole block
and an inode), a job's work folder, a bundle. A file counts ``max(st_size, st_blocks * 512)``: what it allocates,
never less than its length (a sparse or compressed file system does not make it free). A folder counts its own
blocks too. Trees are measured once, when they are written (an upload at ingest, a work folder at the worker's
checkpoints and stage ends), and the numbers recorded; quota checks sum the records, they never walk the disk.

:data:`BLOCK` is the block size an archive's members are charged before anything is extracted
(:mod:`service.jobs.archive`): each file at least one block, its length rounded up to whole blocks.
"""

from __future__ import annotations

import os
import stat
from dataclasses import dataclass
from pathlib import Path

BLOCK = 4096  # the file-system block an estimate rounds each file up to (ext4, XFS, most NFS exports)


@dataclass(frozen=True)
class Usage:
    """A tree's bytes on disk and its entries (files and folders, the tree's own root included)."""

    bytes: int = 0
    files: int = 0

    def __add__(self, other: Usage) -> Usage:
        return Usage(self.bytes + other.bytes, self.files + other.files)


def disk_bytes(st: os.stat_result) -> int:
    """What one entry takes: its allocated blocks, never less than its length."""
    return max(st.st_size, getattr(st, "st_blocks", 0) * 512)


def estimate(size: int) -> int:
    """The bytes a file of ``size`` bytes is charged before it is written: whole :data:`BLOCK` s, at least one."""
    return max(1, -(-size // BLOCK)) * BLOCK


def tree_usage(path: str | os.PathLike) -> Usage:
    """The bytes on disk and the entries of the tree at ``path`` (symbolic links count as themselves, never
    followed); ``Usage()`` when it is not there. Entries removed while it walks are skipped."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return Usage()
    total, count = disk_bytes(st), 1
    if not stat.S_ISDIR(st.st_mode):
        return Usage(total, count)
    stack = [Path(path)]
    while stack:
        folder = stack.pop()
        try:
            entries = list(os.scandir(folder))
        except (FileNotFoundError, NotADirectoryError):
            continue
        for entry in entries:
            try:
                st = entry.stat(follow_symlinks=False)
            except FileNotFoundError:
                continue
            total += disk_bytes(st)
            count += 1
            if stat.S_ISDIR(st.st_mode):
                stack.append(Path(entry.path))
    return Usage(total, count)
