"""Reading uploaded archives for the checks of :mod:`service.jobs.archive`: what an archive may hold
(:class:`ArchiveLimits`), how one is refused (:class:`ArchiveError`), its kind from its content
(:func:`detect_kind`), and bounded readers of tar, gzip-compressed tar and zip that yield each member (an
:class:`Entry`) and open it for extraction. A reader never trusts a header: a tar stream is read through a guard
(position and read-size caps, sparse headers refused), a zip's central directory is bounded before it is parsed.
"""

from __future__ import annotations

import gzip
import io
import os
import re
import stat
import struct
import tarfile
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass

from ..errors import InvalidArgument

REASONS = ("kind", "corrupt", "name", "traversal", "absolute", "link", "special", "unsupported", "duplicate",
           "too_many", "too_large", "bomb", "layout")
CHUNK = 256 << 10  # extraction copies (and a tar's tail is read) in chunks of this size
_MAX_READ = 1 << 20  # the largest single read a tar header (pax, GNU long name) may ask for
_MAX_TAIL = 16 << 20  # bytes allowed after a tar's end-of-archive marker (record padding)
_HEADER_ALLOWANCE = 1536  # tar stream bytes per member beyond its data (header, padding, long names)
_CD_BYTES_PER_MEMBER = 2048  # central-directory bytes a zip may spend per allowed member
_PAX_SPARSE = re.compile(rb"(?:^|\n)[0-9]+ GNU\.sparse\.")  # a pax record of GNU's sparse formats 0.0 to 1.0
_ZIP_METHODS = (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED, zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA)
_TAR_FILE_TYPES = (tarfile.REGTYPE, tarfile.AREGTYPE, tarfile.CONTTYPE)
_TAR_REFUSED = {
    tarfile.SYMTYPE: ("link", "symbolic links are refused"),
    tarfile.LNKTYPE: ("link", "hard links are refused"),
    tarfile.CHRTYPE: ("special", "device files are refused (character device)"),
    tarfile.BLKTYPE: ("special", "device files are refused (block device)"),
    tarfile.FIFOTYPE: ("special", "FIFOs are refused"),
}
_OTHER_MAGIC = ((b"BZh", "a bzip2 stream"), (b"\xfd7zXZ\x00", "an xz stream"), (b"\x28\xb5\x2f\xfd", "a zstd stream"),
                (b"7z\xbc\xaf\x27\x1c", "a 7-Zip archive"), (b"Rar!", "a RAR archive"))


class ArchiveError(InvalidArgument):
    """An uploaded archive was refused. ``reason`` is one of :data:`REASONS`; ``member`` the offending member's name
    as the archive spells it (None when the problem is the archive as a whole); ``field`` is ``"file"``."""

    def __init__(self, problem: str, *, reason: str, member: str | None = None):
        self.problem, self.reason, self.member = problem, reason, member
        super().__init__(f"{problem} (member {_show(member)})" if member is not None else problem, field="file")


@dataclass(frozen=True)
class ArchiveLimits:
    """What an archive may hold. The defaults fit the largest datasets the format allows; tighten them with
    ``dataclasses.replace(ArchiveLimits(), max_total_bytes=...)``."""

    max_members: int = 100_000
    max_total_bytes: int = 20 << 30  # all members' data, uncompressed
    max_member_bytes: int = 4 << 30  # one member's data, uncompressed
    max_ratio: float = 200.0  # uncompressed bytes per archive byte (whole archive; per member for zip)
    max_extraction_ratio: float = 50.0  # bytes on disk (whole blocks per file: service/usage.py) per archive byte
    ratio_grace_bytes: int = 16 << 20  # the ratio is not enforced while the uncompressed bytes stay below this
    max_path_chars: int = 1024
    max_depth: int = 32  # path components

    def __post_init__(self):
        for name in ("max_members", "max_total_bytes", "max_member_bytes", "max_path_chars", "max_depth"):
            if not isinstance(getattr(self, name), int) or getattr(self, name) < 1:
                raise ValueError(f"ArchiveLimits.{name} must be a positive integer, got {getattr(self, name)!r}")
        for name in ("max_ratio", "max_extraction_ratio"):
            if not getattr(self, name) >= 1:
                raise ValueError(f"ArchiveLimits.{name} must be at least 1, got {getattr(self, name)!r}")
        if not isinstance(self.ratio_grace_bytes, int) or self.ratio_grace_bytes < 0:
            raise ValueError(f"ArchiveLimits.ratio_grace_bytes must be >= 0, got {self.ratio_grace_bytes!r}")


def _show(name: str | None) -> str:
    """A member name for a message: repr (control characters escaped), raw bytes if not valid UTF-8, bounded."""
    try:
        name.encode("utf-8")
        text = repr(name)
    except UnicodeEncodeError:
        text = repr(name.encode("utf-8", "surrogateescape"))
    return text if len(text) <= 200 else text[:197] + "..."


def _why(e: BaseException) -> str:
    text = str(e) or type(e).__name__
    return text if len(text) <= 200 else text[:197] + "..."


def _is_tar_block(block: bytes) -> bool:
    """Whether a 512-byte block is a tar header: the ustar magic, or (old V7 archives) a valid header checksum."""
    if len(block) < 512:
        return False
    if block[257:262] == b"ustar":
        return True
    try:
        return tarfile.nti(block[148:156]) in tarfile.calc_chksums(block) and any(block[:100])
    except (ValueError, tarfile.HeaderError):
        return False


@dataclass
class Entry:
    """One member as a reader sees it, before checks: ``kind`` is "file" or "dir", or ``refusal`` says why not."""

    raw: str
    kind: str | None
    size: int
    handle: object
    refusal: tuple[str, str] | None = None  # (reason, problem)
    compressed: int | None = None  # zip: the member's compressed size


def detect_kind(path: str | os.PathLike) -> str:
    """The archive's kind from its first bytes: ``"tar"``, ``"tar.gz"`` (a gzip stream holding a tar) or ``"zip"``.
    Raises :class:`ArchiveError` (reason ``kind``, or ``corrupt`` for an unreadable gzip stream) for anything else."""
    with open(path, "rb") as f:
        head = f.read(512)
        if not head:
            raise ArchiveError("the upload is empty", reason="kind")
        if head.startswith(b"\x1f\x8b"):
            f.seek(0)
            try:
                with gzip.GzipFile(fileobj=f, mode="rb") as gz:
                    inner = gz.read(512)
            except Exception as e:  # OSError, EOFError, zlib.error: hostile bytes
                raise ArchiveError(f"corrupt gzip stream ({_why(e)})", reason="corrupt") from None
            if not _is_tar_block(inner):
                raise ArchiveError("a gzip stream that does not hold a tar archive; upload a .tar.gz, .tar or .zip",
                                   reason="kind")
            return "tar.gz"
    if head.startswith(b"PK\x03\x04"):
        return "zip"
    if head.startswith(b"PK\x05\x06"):
        raise ArchiveError("the zip archive is empty", reason="layout")
    if _is_tar_block(head):
        return "tar"
    for magic, what in _OTHER_MAGIC:
        if head.startswith(magic):
            raise ArchiveError(f"{what} is not accepted; upload a .tar.gz, .tar or .zip, or a video", reason="kind")
    raise ArchiveError("not a .tar, .tar.gz or .zip archive, nor a video (MP4, MOV, WebM, MKV): unrecognised "
                       "content", reason="kind")


# ---------------------------------------------------------------------------------------------------------- readers
def open_reader(path, limits: ArchiveLimits):
    kind = detect_kind(path)
    return _ZipReader(path, limits) if kind == "zip" else _TarReader(path, kind, limits)


class _Guard:
    """The file object tarfile reads through: tracks the position in the (decompressed) stream, refuses a seek or
    read past ``cap`` (a gzip stream expanding too far) and a single read larger than ``_MAX_READ`` (a forged
    header asking tarfile to buffer gigabytes), and remembers the last read (the block that ended the archive).
    While ``sniff`` is set (the checking pass), a GNU sparse header (old GNU type ``S``, or a pax header with
    ``GNU.sparse.*`` records) is refused when read, before tarfile collects its unbounded sparse map."""

    def __init__(self, f, *, total_cap: int, bomb_cap: float, archive_bytes: int):
        self._f = f
        self._pos = 0
        self._total_cap, self._bomb_cap, self._archive_bytes = total_cap, bomb_cap, archive_bytes
        self.last: tuple[int, bytes] = (0, b"")
        self.sniff = True

    def _check(self, pos: int) -> None:
        if pos > self._bomb_cap:
            raise ArchiveError(f"a decompression bomb: the gzip stream expands to more than {int(self._bomb_cap)} "
                               f"bytes from {self._archive_bytes}", reason="bomb")
        if pos > self._total_cap:
            raise ArchiveError(f"the archive's stream is larger than {self._total_cap} bytes", reason="too_large")

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._pos

    def seek(self, pos: int, whence: int = io.SEEK_SET) -> int:
        if whence == io.SEEK_CUR:
            pos += self._pos
        elif whence != io.SEEK_SET:
            raise io.UnsupportedOperation("seek from the end")
        self._check(pos)
        self._pos = self._f.seek(pos)
        return self._pos

    def read(self, n: int = -1) -> bytes:
        if n is None or n < 0 or n > _MAX_READ:
            raise ArchiveError(f"a forged or corrupt tar header of {n} bytes (more than {_MAX_READ})", reason="corrupt")
        start = self._pos
        data = self._f.read(n)
        self._pos += len(data)
        self._check(self._pos)
        self.last = (start, data)
        if self.sniff:
            if n == tarfile.BLOCKSIZE and data[156:157] == tarfile.GNUTYPE_SPARSE and _is_tar_block(data):
                raise ArchiveError("sparse files are refused", reason="special",
                                   member=tarfile.nts(data[:100], "utf-8", "surrogateescape"))
            if _PAX_SPARSE.search(data):
                raise ArchiveError("sparse files are refused (a pax header with GNU.sparse records)",
                                   reason="special")
        return data


class _TarReader:
    """A tar or gzip-compressed tar, read through a :class:`_Guard` in random-access mode: the checking pass walks
    the headers (seeking over data), the extraction pass reads each checked member."""

    def __init__(self, path, kind: str, limits: ArchiveLimits):
        self.kind = kind
        self._raw = open(path, "rb")
        try:
            self.archive_bytes = os.fstat(self._raw.fileno()).st_size
            stream = gzip.GzipFile(fileobj=self._raw, mode="rb") if kind == "tar.gz" else self._raw
            total_cap = limits.max_total_bytes + limits.max_members * _HEADER_ALLOWANCE + _MAX_TAIL
            bomb_cap = (max(limits.ratio_grace_bytes, limits.max_ratio * self.archive_bytes) if kind == "tar.gz"
                        else float("inf"))
            self._guard = _Guard(stream, total_cap=total_cap, bomb_cap=bomb_cap, archive_bytes=self.archive_bytes)
            self._tar = self._call(lambda: tarfile.open(fileobj=self._guard, mode="r:", encoding="utf-8",
                                                        errors="surrogateescape"))
        except BaseException:
            self._raw.close()
            raise

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self._raw.close()

    def _call(self, fn, member: str | None = None):
        try:
            return fn()
        except ArchiveError:
            raise
        except Exception as e:  # any parser failure on untrusted bytes is a corrupt archive
            what = "tar.gz" if self.kind == "tar.gz" else "tar"
            raise ArchiveError(f"corrupt or truncated {what} archive ({_why(e)})", reason="corrupt",
                               member=member) from None

    def entries(self) -> Iterator[Entry]:
        while True:
            ti = self._call(self._tar.next)
            if ti is None:
                break
            yield self._entry(ti)
        self._check_end()
        self._guard.sniff = False

    @staticmethod
    def _entry(ti: tarfile.TarInfo) -> Entry:
        if ti.sparse is not None:
            return Entry(ti.name, None, ti.size, ti, ("special", "sparse files are refused"))
        if ti.type in _TAR_FILE_TYPES:
            return Entry(ti.name, "file", ti.size, ti)
        if ti.type == tarfile.DIRTYPE:
            return Entry(ti.name, "dir", ti.size, ti)
        reason, problem = _TAR_REFUSED.get(ti.type, ("special", f"member type {ti.type!r} is neither a regular file "
                                                                f"nor a folder"))
        if reason == "link":
            problem += f" (-> {_show(ti.linkname)})"
        return Entry(ti.name, None, ti.size, ti, (reason, problem))

    def _check_end(self) -> None:
        """After the last member: the block that ended the archive must be the zero end-of-archive marker, and
        what follows it zeros (record padding, bounded); a gzip stream is read to its end (CRC checked)."""
        start, block = self._guard.last
        if start != self._tar.offset or not block:
            raise ArchiveError("truncated archive: it ends without the end-of-archive marker", reason="corrupt")
        if len(block) < tarfile.BLOCKSIZE:
            raise ArchiveError("truncated archive: a partial header block at its end", reason="corrupt")
        if any(block):
            raise ArchiveError(f"corrupt archive: an unreadable header at byte {start}", reason="corrupt")
        tail = 0
        while True:
            data = self._call(lambda: self._guard.read(CHUNK))
            if not data:
                return
            tail += len(data)
            if tail > _MAX_TAIL:
                raise ArchiveError(f"more than {_MAX_TAIL} bytes after the end-of-archive marker", reason="bomb")
            if any(data):
                raise ArchiveError("corrupt archive: data after the end-of-archive marker", reason="corrupt")

    def open(self, handle: tarfile.TarInfo):
        return self._call(lambda: self._tar.extractfile(handle), handle.name)

    def read(self, src, n: int, name: str) -> bytes:
        return self._call(lambda: src.read(n), name)


class _ZipReader:
    """A zip archive. Its central directory is walked first (count and size bounded) so that ``zipfile`` never
    builds more entries than the limits allow; member CRCs are checked as they are extracted."""

    kind = "zip"

    def __init__(self, path, limits: ArchiveLimits):
        self._path = path
        with open(path, "rb") as f:
            self.archive_bytes = os.fstat(f.fileno()).st_size
            _precheck_zip(f, self.archive_bytes, limits)
        try:
            self._zip = zipfile.ZipFile(path, metadata_encoding="utf-8")
        except UnicodeDecodeError as e:
            raise ArchiveError(f"a member name is not valid UTF-8: {_why(e)}", reason="name",
                               member=e.object.decode("utf-8", "surrogateescape")
                               if isinstance(e.object, bytes) else None) from None
        except Exception as e:  # any parser failure on untrusted bytes is a corrupt archive
            raise ArchiveError(f"corrupt or truncated zip archive ({_why(e)})", reason="corrupt") from None

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self._zip.close()

    def entries(self) -> Iterator[Entry]:
        for zi in self._zip.infolist():
            raw = zi.orig_filename  # before zipfile cuts the name at a NUL
            mode = zi.external_attr >> 16
            ftype = stat.S_IFMT(mode)
            is_dir = zi.is_dir()
            refusal = None
            if ftype == stat.S_IFLNK:
                refusal = ("link", "symbolic links are refused")
            elif ftype not in (0, stat.S_IFREG, stat.S_IFDIR):
                refusal = ("special", "device files, FIFOs and sockets are refused")
            elif zi.flag_bits & 0x1:
                refusal = ("unsupported", "encrypted members are refused")
            elif zi.compress_type not in _ZIP_METHODS:
                refusal = ("unsupported", f"compression method {zi.compress_type} is not supported")
            yield Entry(raw, "dir" if is_dir else "file", zi.file_size, zi, refusal,
                         compressed=None if is_dir else zi.compress_size)

    def open(self, handle: zipfile.ZipInfo):
        try:
            return self._zip.open(handle)
        except Exception as e:
            raise ArchiveError(f"corrupt zip member ({_why(e)})", reason="corrupt",
                               member=handle.orig_filename) from None

    def read(self, src, n: int, name: str) -> bytes:
        try:
            return src.read(n)
        except Exception as e:  # bad CRC, bad deflate data, truncation
            raise ArchiveError(f"corrupt zip member ({_why(e)})", reason="corrupt", member=name) from None


def _precheck_zip(f, size: int, limits: ArchiveLimits) -> None:
    """Find the end-of-central-directory record (zip64 too) and walk the central directory's entries, refusing
    more than ``limits.max_members`` before ``zipfile`` parses them into objects."""
    tail_len = min(size, 22 + 65535)
    f.seek(size - tail_len)
    tail = f.read(tail_len)
    i = tail.rfind(b"PK\x05\x06")
    if i < 0 or len(tail) - i < 22:
        raise ArchiveError("corrupt or truncated zip archive: no end-of-central-directory record", reason="corrupt")
    eocd_at = size - tail_len + i
    _, disk, cd_disk, _, entries, cd_size, cd_offset, _ = struct.unpack("<4s4H2LH", tail[i:i + 22])
    if 0xFFFF in (entries, disk) or 0xFFFFFFFF in (cd_size, cd_offset):
        f.seek(max(eocd_at - 20, 0))
        loc = f.read(20)
        if len(loc) == 20 and loc[:4] == b"PK\x06\x07":
            f.seek(struct.unpack("<Q", loc[8:16])[0])
            rec = f.read(56)
            if len(rec) == 56 and rec[:4] == b"PK\x06\x06":
                disk, cd_disk, _, entries, cd_size, cd_offset = struct.unpack("<2L4Q", rec[16:56])
    if disk or cd_disk:
        raise ArchiveError("multi-part (spanned) zip archives are not supported", reason="unsupported")
    if entries > limits.max_members:
        raise ArchiveError(f"the archive holds more than {limits.max_members} members ({entries})",
                           reason="too_many")
    if cd_size > limits.max_members * _CD_BYTES_PER_MEMBER or cd_offset + cd_size > size:
        raise ArchiveError(f"corrupt zip archive: a central directory of {cd_size} bytes at {cd_offset}",
                           reason="corrupt")
    f.seek(cd_offset)
    cd = f.read(cd_size)
    pos = count = 0
    while pos < len(cd):
        if cd[pos:pos + 4] != b"PK\x01\x02" or pos + 46 > len(cd):
            raise ArchiveError(f"corrupt zip archive: a bad central-directory entry at byte {cd_offset + pos}",
                               reason="corrupt")
        n, m, k = struct.unpack_from("<3H", cd, pos + 28)
        pos += 46 + n + m + k
        count += 1
        if count > limits.max_members:
            raise ArchiveError(f"the archive holds more than {limits.max_members} members", reason="too_many")
