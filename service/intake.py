"""The one upload intake: every request body the service keeps (an avatar bundle, a dataset archive or a video, an
adapter's model) comes in here, whatever the transport or the resource.

1. The declared length (``Content-Length``, parsed once, by :func:`declared_length`) is refused at once when it is
   over the limit, before a byte is read.
2. Admission before the body: the key's uploads per hour and the tenant's storage quota with the declared size
   (``Access.admit_upload``; a chunked body declares nothing, so this counts 0 bytes).
3. The body is spooled to a private file (created exclusively, mode 0600) in batches written by a worker thread,
   never on the event loop, and refused as soon as it passes the limit; its size and SHA-256 come out.
4. Admission after the body: the tenant's quota with the bytes that really arrived (``Access.check_quota``), so
   a chunked or understated body cannot pass the quota.

Whatever fails (a limit, the quota, the client going away), the spooled file is removed: nothing is kept.
"""

from __future__ import annotations

import asyncio
import hashlib
import os
from collections.abc import AsyncIterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from .errors import BodyTooLarge, InvalidArgument

if TYPE_CHECKING:
    from .access.auth import Access, Principal

WRITE_BATCH = 1 << 20  # received bytes are written to disk in batches of this size, off the event loop


@dataclass(frozen=True)
class Spooled:
    """A body received whole: where it is, its size and its SHA-256 (hex)."""

    path: Path
    size: int
    sha256: str


def declared_length(headers: Mapping[str, str], field: str = "content-length") -> int | None:
    """The body size a request announces (None when it announces none, e.g. chunked); InvalidArgument naming
    ``field`` when the header is not a decimal number of bytes."""
    raw = headers.get("content-length")
    if raw is None:
        return None
    raw = raw.strip()
    if not (raw.isascii() and raw.isdigit()) or len(raw) > 19:
        raise InvalidArgument(f"Content-Length must be a decimal byte count, got {raw[:40]!r}", field=field)
    return int(raw)


def _write(out, data: bytes) -> None:
    """(Worker thread.) One batch to disk."""
    out.write(data)


async def spool(chunks: AsyncIterable[bytes], path: Path, limit: int, field: str) -> tuple[int, str]:
    """Write ``chunks`` to ``path`` (created exclusively, mode 0600) in batches off the event loop, refusing the
    body (BodyTooLarge naming ``field``) once it passes ``limit`` bytes; its size and SHA-256. The caller removes
    ``path`` on failure (:meth:`UploadIntake.receive` does)."""
    digest = hashlib.sha256()
    size = 0
    pending: list[bytes] = []
    pending_bytes = 0
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o600)
    with os.fdopen(fd, "wb") as out:
        async for chunk in chunks:
            if not chunk:
                continue
            size += len(chunk)
            if size > limit:
                raise BodyTooLarge(f"the upload is larger than {limit} bytes", field=field)
            digest.update(chunk)
            pending.append(bytes(chunk))
            pending_bytes += len(chunk)
            if pending_bytes >= WRITE_BATCH:
                await asyncio.to_thread(_write, out, b"".join(pending))
                pending, pending_bytes = [], 0
        if pending:
            await asyncio.to_thread(_write, out, b"".join(pending))
    return size, digest.hexdigest()


class UploadIntake:
    """Admission, spooling and the quota after the body (module docstring), for one :class:`Access`."""

    def __init__(self, access: Access):
        self.access = access

    def check_declared(self, declared: int | None, limit: int, field: str) -> None:
        """BodyTooLarge naming ``field`` when the announced size is already over ``limit``."""
        if declared is not None and declared > limit:
            raise BodyTooLarge(f"the upload is {declared} bytes, larger than {limit} bytes", field=field)

    async def admit(self, principal: Principal, declared: int | None) -> None:
        """Admission before the body: the key's upload count and the tenant's quota with the declared size."""
        await asyncio.to_thread(self.access.admit_upload, principal, declared or 0)

    async def receive(self, principal: Principal, chunks: AsyncIterable[bytes], path: Path, *, limit: int,
                      field: str, declared: int | None = None, admitted: bool = False) -> Spooled:
        """Steps 1 to 4 of the module docstring (``admitted``: the caller already ran :meth:`admit`, e.g. before
        parsing a multipart body whose file part this is). On any failure ``path`` is removed."""
        if not admitted:
            self.check_declared(declared, limit, field)
            await self.admit(principal, declared)
        try:
            size, sha256 = await spool(chunks, path, limit, field)
            await asyncio.to_thread(self.access.check_quota, principal, size)
        except BaseException:
            path.unlink(missing_ok=True)
            raise
        return Spooled(path, size, sha256)
