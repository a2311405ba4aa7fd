"""Safe inspection and extraction of uploaded archives (``.tar``, ``.tar.gz``, ``.zip``), standard library only.

An upload is hostile until proven otherwise. The kind is read from the content (magic bytes), never from the file
name. Every member is checked **before anything is written**:

- names: valid UTF-8, no control characters, no backslashes, not absolute (``/x``, ``C:x``), no ``..`` component,
  bounded length and depth, no duplicates (after dropping ``.`` components), no file that is also a folder;
- types: regular files and folders only (symbolic and hard links, devices, FIFOs, sparse files, encrypted zip
  members are refused);
- sizes: member count, each member's size, the total, and the compression ratio (total uncompressed bytes over the
  archive's bytes; for zip also per member) under :class:`ArchiveLimits`; the extraction ratio (what the members
  would take on disk, each file rounded up to whole blocks, over the archive's bytes: ``max_extraction_ratio``), so
  that neither a stream of zeros nor a swarm of tiny files can turn a small archive into a large extraction;
- integrity: a corrupt or truncated archive is refused with the reason (a gzip stream is decompressed to its end,
  so its CRC is checked and data hidden after the tar's end-of-archive marker counts; zip CRCs are checked as
  members are written).

Extraction writes regular files and folders only (``O_EXCL | O_NOFOLLOW``, modes 0644 / 0755; archive modes, owners
and times are ignored), counts the bytes really written and stops at the limits, whatever the headers declared.
On any failure the destination folder is removed: nothing is left behind.

The dataset may sit at the archive's root (``dataset.json`` at the top) or inside exactly one top-level folder;
:func:`extract_archive` returns that dataset root. A ``__MACOSX/`` folder (macOS Finder's resource forks) is checked
like everything else but neither extracted nor counted as a top-level folder.

Every refusal is one :class:`ArchiveError` (an ``InvalidArgument``: HTTP 422 / gRPC INVALID_ARGUMENT, ``field``
``"file"``) whose message names the problem and the offending member, and whose ``reason`` is a short code. The
checks and the extraction are here; reading the three formats (bounded, streamed) is
:mod:`service.jobs.archive_readers`.
"""


from __future__ import annotations

import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path

from ..usage import BLOCK, estimate
from .archive_readers import CHUNK, REASONS, ArchiveError, ArchiveLimits, detect_kind, open_reader

__all__ = ["REASONS", "ArchiveError", "ArchiveInfo", "ArchiveLimits", "Member", "detect_kind", "extract_archive",
           "inspect_archive"]

KINDS = ("tar", "tar.gz", "zip")
MANIFEST = "dataset.json"  # what marks the dataset root (docs/tracked-video-format.md)
IGNORED_TOP = "__MACOSX"

_MAX_COMPONENT_BYTES = 255  # NAME_MAX of common file systems
_DRIVE = re.compile(r"^[A-Za-z]:")
_LIMITS = ArchiveLimits()  # the defaults


@dataclass(frozen=True)
class Member:
    """One checked member: its normalised relative path (``/``-separated, no ``.`` components, no trailing ``/``),
    whether it is a folder, and its declared size in bytes (0 for folders)."""

    name: str
    is_dir: bool
    size: int


@dataclass(frozen=True)
class ArchiveInfo:
    """The result of :func:`inspect_archive`: the kind (``"tar"``, ``"tar.gz"`` or ``"zip"``), every member in
    archive order (``__MACOSX/`` ones included), the members' total declared size, the archive's own size, and the
    dataset root inside it (``""`` for the archive's root, else the one top-level folder's name)."""

    kind: str
    members: tuple[Member, ...]
    total_bytes: int
    archive_bytes: int
    root: str


# ------------------------------------------------------------------------------------------------------ public API
def inspect_archive(path: str | os.PathLike, limits: ArchiveLimits = _LIMITS) -> ArchiveInfo:
    """Check every member of the archive at ``path`` against ``limits`` without extracting anything, and find the
    dataset root. Raises :class:`ArchiveError` naming the first problem."""
    with open_reader(path, limits) as reader:
        return _check(reader, limits)[0]


def extract_archive(path: str | os.PathLike, dest: str | os.PathLike,
                    limits: ArchiveLimits = _LIMITS) -> Path:
    """Check the archive at ``path`` (as :func:`inspect_archive`), then extract it into the new folder ``dest``
    (its parent must exist, ``dest`` must not) and return the dataset root (``dest`` or ``dest/<top folder>``).

    The bytes written are counted against the limits as they are written. On any error ``dest`` is removed and
    :class:`ArchiveError` raised (``OSError`` for a problem of the destination, e.g. a full disk)."""
    dest = Path(dest)
    with open_reader(path, limits) as reader:
        info, plan = _check(reader, limits)
        os.mkdir(dest, 0o755)
        try:
            _write(reader, plan, dest, limits)
        except BaseException:
            shutil.rmtree(dest, ignore_errors=True)
            raise
    return dest / info.root if info.root else dest


# --------------------------------------------------------------------------------------------------------- checks
def _name_parts(raw: str, limits: ArchiveLimits) -> tuple[str, ...]:
    """The checked, normalised components of a member name (``()`` for the root folder itself)."""
    try:
        raw.encode("utf-8")
    except UnicodeEncodeError:
        raise ArchiveError("the member name is not valid UTF-8", reason="name", member=raw) from None
    if any(ord(c) < 32 or 127 <= ord(c) < 160 for c in raw):
        raise ArchiveError("the member name contains control characters", reason="name", member=raw)
    if "\\" in raw:
        raise ArchiveError("the member name contains a backslash (Windows path separator)", reason="name",
                           member=raw)
    if raw.startswith("/") or _DRIVE.match(raw):
        raise ArchiveError("absolute paths are refused", reason="absolute", member=raw)
    if len(raw) > limits.max_path_chars:
        raise ArchiveError(f"the member name is longer than {limits.max_path_chars} characters", reason="name",
                           member=raw)
    parts = tuple(p for p in raw.split("/") if p not in ("", "."))
    if ".." in parts:
        raise ArchiveError("path traversal ('..' component) is refused", reason="traversal", member=raw)
    if len(parts) > limits.max_depth:
        raise ArchiveError(f"the member is nested deeper than {limits.max_depth} folders", reason="name", member=raw)
    if any(len(p.encode("utf-8")) > _MAX_COMPONENT_BYTES for p in parts):
        raise ArchiveError(f"a path component is longer than {_MAX_COMPONENT_BYTES} bytes", reason="name",
                           member=raw)
    return parts


def _check(reader, limits: ArchiveLimits) -> tuple[ArchiveInfo, list[tuple[Member, tuple[str, ...], object]]]:
    """Run every check over the reader's members (streamed: a tar is never read past a refused member) and plan
    the extraction: (member, path parts, reader handle) for everything to extract."""
    members: list[Member] = []
    plan: list[tuple[Member, tuple[str, ...], object]] = []
    files: set[tuple[str, ...]] = set()
    dirs: set[tuple[str, ...]] = set()
    explicit_dirs: set[tuple[str, ...]] = set()
    total = stored = 0  # the members' bytes; what they would take on disk (whole blocks: service/usage.py)
    bomb_at = max(limits.ratio_grace_bytes, limits.max_ratio * reader.archive_bytes)
    stored_at = max(limits.ratio_grace_bytes, limits.max_extraction_ratio * reader.archive_bytes)
    for count, e in enumerate(reader.entries(), 1):
        if count > limits.max_members:
            raise ArchiveError(f"the archive holds more than {limits.max_members} members", reason="too_many",
                               member=e.raw)
        parts = _name_parts(e.raw, limits)
        if e.refusal is not None:
            raise ArchiveError(e.refusal[1], reason=e.refusal[0], member=e.raw)
        if e.size < 0:
            raise ArchiveError("a negative member size", reason="corrupt", member=e.raw)
        if e.kind == "dir":
            if e.size:
                raise ArchiveError("a folder entry that holds data", reason="corrupt", member=e.raw)
            if not parts:
                continue  # the archive's root itself ("./")
            if parts in explicit_dirs:
                raise ArchiveError("duplicate member name", reason="duplicate", member=e.raw)
            if parts in files:
                raise ArchiveError("a folder with the name of a file", reason="duplicate", member=e.raw)
            explicit_dirs.add(parts)
        else:
            if not parts:
                raise ArchiveError("a file without a name", reason="name", member=e.raw)
            if parts in files:
                raise ArchiveError("duplicate member name", reason="duplicate", member=e.raw)
            if parts in dirs:
                raise ArchiveError("a file with the name of a folder", reason="duplicate", member=e.raw)
            if e.size > limits.max_member_bytes:
                raise ArchiveError(f"the member is larger than {limits.max_member_bytes} bytes ({e.size})",
                                   reason="too_large", member=e.raw)
            if (e.compressed is not None and e.size > limits.ratio_grace_bytes
                    and e.size > limits.max_ratio * max(e.compressed, 1)):
                raise ArchiveError(f"a decompression bomb: {e.size} bytes compressed to {e.compressed} (more than "
                                   f"{limits.max_ratio:g} times)", reason="bomb", member=e.raw)
            total += e.size
            if total > limits.max_total_bytes:
                raise ArchiveError(f"the archive holds more than {limits.max_total_bytes} bytes uncompressed",
                                   reason="too_large", member=e.raw)
            if total > bomb_at:
                raise ArchiveError(f"a decompression bomb: more than {limits.max_ratio:g} uncompressed bytes per "
                                   f"archive byte ({total} from {reader.archive_bytes})", reason="bomb",
                                   member=e.raw)
            files.add(parts)
        stored += estimate(e.size) if e.kind != "dir" else BLOCK
        if stored > stored_at:
            raise ArchiveError(f"a decompression bomb: its files would take more than {limits.max_extraction_ratio:g} "
                               f"bytes on disk per archive byte ({stored} from {reader.archive_bytes}; "
                               "max_extraction_ratio)", reason="bomb", member=e.raw)
        for i in range(1, len(parts)):
            if parts[:i] in files:
                raise ArchiveError("a member inside a path that is a file", reason="duplicate", member=e.raw)
            dirs.add(parts[:i])
        if e.kind == "dir":
            dirs.add(parts)
        member = Member("/".join(parts), e.kind == "dir", e.size)
        members.append(member)
        if parts[0] != IGNORED_TOP:
            plan.append((member, parts, e.handle))
    info = ArchiveInfo(reader.kind, tuple(members), total, reader.archive_bytes, _root(plan))
    return info, plan


def _root(plan) -> str:
    """The dataset root: ``""`` when dataset.json is at the top, else the one top-level folder holding it."""
    if not plan:
        raise ArchiveError("the archive is empty", reason="layout")
    tops = sorted({parts[0] for _, parts, _ in plan})
    top_files = {parts[0] for m, parts, _ in plan if len(parts) == 1 and not m.is_dir}
    if MANIFEST in top_files:
        return ""
    if len(tops) == 1 and tops[0] not in top_files:
        if any(parts == (tops[0], MANIFEST) and not m.is_dir for m, parts, _ in plan):
            return tops[0]
        raise ArchiveError(f"no {MANIFEST} in the archive's one top-level folder {tops[0]!r}", reason="layout")
    listed = ", ".join(repr(t) for t in tops[:10]) + (", ..." if len(tops) > 10 else "")
    raise ArchiveError(f"the dataset ({MANIFEST}) must be at the archive's root or inside exactly one top-level "
                       f"folder; the top level holds {listed}", reason="layout")


def _write(reader, plan, dest: Path, limits: ArchiveLimits) -> None:
    """Write the planned members under ``dest``, counting the real bytes against the limits."""
    total = 0
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    for member, parts, handle in plan:
        target = dest.joinpath(*parts)
        if member.is_dir:
            target.mkdir(mode=0o755, parents=True, exist_ok=True)
            continue
        target.parent.mkdir(mode=0o755, parents=True, exist_ok=True)
        written = 0
        with reader.open(handle) as src, os.fdopen(os.open(target, flags, 0o644), "wb") as out:
            while True:
                chunk = reader.read(src, CHUNK, member.name)
                if not chunk:
                    break
                written += len(chunk)
                total += len(chunk)
                if written > member.size:
                    raise ArchiveError(f"the member holds more data than its declared {member.size} bytes",
                                       reason="corrupt", member=member.name)
                if total > limits.max_total_bytes:
                    raise ArchiveError(f"the archive holds more than {limits.max_total_bytes} bytes uncompressed",
                                       reason="too_large", member=member.name)
                out.write(chunk)
        if written != member.size:
            raise ArchiveError(f"truncated member: {written} of its {member.size} bytes", reason="corrupt",
                               member=member.name)
