"""A warning when the SQLite job database sits on a network filesystem.

SQLite (WAL mode: shared memory and POSIX locks) is for one machine; on NFS, SMB, CephFS and the like its locks are
unreliable and concurrent writers from several machines corrupt the file. A deployment with workers on several
machines (a ReadWriteMany volume) puts the job database on PostgreSQL (``BLENDSPLAT_JOBS_URL``).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

from sqlalchemy.engine import make_url

log = logging.getLogger(__name__)

NETWORK_FILESYSTEMS = frozenset({
    "nfs", "nfs4", "cifs", "smb3", "smbfs", "ncpfs", "afs", "9p", "ceph", "glusterfs", "lustre", "gpfs", "beegfs",
    "ocfs2", "gfs2", "fuse.sshfs", "fuse.glusterfs", "fuse.cephfs", "fuse.s3fs", "fuse.gcsfuse", "fuse.juicefs",
    "fuse.rclone", "fuse.goofys", "fuse.mountpoint-s3", "fuse.azureblob", "fuse.blobfuse2", "efs",
})


def _unescape(field: str) -> str:
    """/proc/mounts escapes space, tab, newline and backslash as octal (``\\040``)."""
    return field.replace("\\040", " ").replace("\\011", "\t").replace("\\012", "\n").replace("\\134", "\\")


def filesystem_type(path: str | os.PathLike, mounts: str | os.PathLike = "/proc/mounts") -> str | None:
    """The type of the filesystem holding ``path`` (the longest mount point above it), or None when unknown."""
    target = Path(path).absolute()
    while not target.exists() and target != target.parent:
        target = target.parent  # the file (or its folder) may not exist yet
    target = target.resolve()
    try:
        lines = Path(mounts).read_text().splitlines()
    except OSError:
        return None
    best, best_type = -1, None
    for line in lines:
        fields = line.split()
        if len(fields) < 3:
            continue
        point = Path(_unescape(fields[1]))
        if (target == point or point in target.parents) and len(point.parts) >= best:
            best, best_type = len(point.parts), fields[2]
    return best_type


def warn_if_sqlite_on_network_filesystem(url: str, mounts: str | os.PathLike = "/proc/mounts") -> str | None:
    """Log a warning when ``url`` is a SQLite file on a network filesystem; the filesystem type, else None."""
    parsed = make_url(url)
    if parsed.get_backend_name() != "sqlite" or not parsed.database or parsed.database == ":memory:":
        return None
    fstype = filesystem_type(parsed.database, mounts)
    if fstype is None or fstype.lower() not in NETWORK_FILESYSTEMS:
        return None
    log.warning("the job database %s is a SQLite file on a network filesystem (%s): SQLite is for one machine, "
                "its locks are unreliable there and several machines writing it corrupt it; use PostgreSQL "
                "(BLENDSPLAT_JOBS_URL=postgresql+psycopg://...) for workers on several machines",
                parsed.database, fstype)
    return fstype
