"""Uploaded archives (service.jobs.archive): the kinds accepted, where the dataset may sit, and every hostile archive
refused with its reason before anything is written, leaving nothing behind."""

from __future__ import annotations

import dataclasses
import gzip
import io
import stat
import tarfile
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from render_core.data import Tracking, validate_dataset, write_dataset
from service.errors import InvalidArgument
from service.jobs.archive import ArchiveError, ArchiveLimits, detect_kind, extract_archive, inspect_archive

N, H, W = 4, 32, 32


def make_dataset(out: Path) -> Path:
    """A valid portable dataset: 4 PNG frames of 32x32, masks, tracking (13 files and folders)."""
    tracking = Tracking(
        face_model="flame", expression_names=["exp_00", "exp_01"], joint_names=["root", "jaw"],
        expression=np.zeros((N, 2), np.float32), joint_rotations=np.zeros((N, 2, 3), np.float32),
        eyelids=np.zeros((N, 2), np.float32),
        K=np.tile(np.array([[30, 0, 16], [0, 30, 16], [0, 0, 1]], np.float32), (N, 1, 1)),
        R=np.tile(np.eye(3, dtype=np.float32), (N, 1, 1)), t=np.tile(np.array([0, 0, 1], np.float32), (N, 1)),
        shape=np.zeros(0, np.float32), train=np.arange(N - 1), test=np.array([N - 1]), width=W, height=H)
    frames = [np.full((H, W, 3), 40 * i, np.uint8) for i in range(N)]
    masks = [np.full((H, W), 255, np.uint8) for _ in range(N)]
    return write_dataset(out, frames, masks, tracking)


@pytest.fixture(scope="session")
def dataset(tmp_path_factory) -> dict[str, bytes]:
    """The valid dataset's files, by relative path."""
    root = make_dataset(tmp_path_factory.mktemp("dataset") / "ds")
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def tar_member(name: str, data: bytes = b"", type=tarfile.REGTYPE, linkname: str = "", size: int | None = None):
    info = tarfile.TarInfo(name)
    info.type, info.linkname = type, linkname
    info.size = len(data) if size is None else size
    info.mode = 0o755 if type == tarfile.DIRTYPE else 0o644
    return info, data


def tar_archive(path: Path, files: dict[str, bytes], *, prefix: str = "", gz: bool = False, extra=(),
                fmt: int = tarfile.PAX_FORMAT) -> Path:
    """A tar (gzip-compressed with ``gz``) of ``files`` under ``prefix``, then the hand-made ``extra`` members."""
    with tarfile.open(path, "w:gz" if gz else "w", format=fmt, encoding="utf-8", errors="surrogateescape") as tf:
        if prefix.strip("./"):
            tf.addfile(tar_member(prefix.rstrip("/"), type=tarfile.DIRTYPE)[0])
        for name, data in files.items():
            info, data = tar_member(prefix + name, data)
            tf.addfile(info, io.BytesIO(data))
        for info, data in extra:
            tf.addfile(info, io.BytesIO(data) if data else None)
    return path


def zip_archive(path: Path, files: dict[str, bytes], *, prefix: str = "", extra=(),
                method: int = zipfile.ZIP_DEFLATED) -> Path:
    """A zip of ``files`` under ``prefix``, then ``extra`` (ZipInfo or name, bytes) members."""
    with warnings.catch_warnings(), zipfile.ZipFile(path, "w", method) as zf:
        warnings.simplefilter("ignore")  # duplicate names are written on purpose
        for name, data in files.items():
            zf.writestr(prefix + name, data)
        for info, data in extra:
            zf.writestr(info, data)
    return path


def zip_link(name: str, target: str) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name)
    info.create_system = 3
    info.external_attr = (stat.S_IFLNK | 0o777) << 16
    return info, target.encode()


# ---------------------------------------------------------------------------------------------------------- happy
@pytest.mark.parametrize("prefix", ["", "./", "upload-7/"])
@pytest.mark.parametrize("kind", ["tar", "tar.gz", "zip"])
def test_extracts_the_dataset_at_the_root_or_in_one_folder(tmp_path, dataset, kind, prefix):
    path = tmp_path / "upload.bin"  # the kind comes from the content, not the name
    if kind == "zip":
        zip_archive(path, dataset, prefix=prefix)
    else:
        tar_archive(path, dataset, prefix=prefix, gz=kind == "tar.gz")
    assert detect_kind(path) == kind
    info = inspect_archive(path)
    assert info.kind == kind and info.root == prefix.strip("./")
    assert info.total_bytes == sum(len(d) for d in dataset.values())
    root = extract_archive(path, tmp_path / "out")
    assert root == tmp_path / "out" / prefix.strip("./")
    assert {p.relative_to(root).as_posix(): p.read_bytes() for p in root.rglob("*") if p.is_file()} == dataset
    assert all(stat.S_IMODE(p.stat().st_mode) == 0o644 for p in root.rglob("*") if p.is_file())
    assert validate_dataset(root) == []


def test_kind_comes_from_the_content_not_the_name(tmp_path, dataset):
    assert detect_kind(tar_archive(tmp_path / "a.zip", dataset, gz=True)) == "tar.gz"
    assert detect_kind(zip_archive(tmp_path / "b.tar.gz", dataset)) == "zip"
    assert detect_kind(tar_archive(tmp_path / "c.tgz", dataset, fmt=tarfile.GNU_FORMAT)) == "tar"


def test_limits_are_a_frozen_dataclass_that_validates():
    limits = ArchiveLimits()
    assert limits.max_members == 100_000 and limits.max_total_bytes == 20 << 30 and limits.max_ratio == 200
    with pytest.raises(dataclasses.FrozenInstanceError):
        limits.max_members = 1
    with pytest.raises(ValueError, match="max_members"):
        ArchiveLimits(max_members=0)
    assert dataclasses.replace(limits, max_members=10).max_members == 10


def test_macos_resource_forks_are_not_a_second_top_level_folder(tmp_path, dataset):
    path = zip_archive(tmp_path / "mac.zip", dataset, prefix="ds/", extra=[("__MACOSX/ds/._dataset.json", b"x")])
    root = extract_archive(path, tmp_path / "out")
    assert root == tmp_path / "out" / "ds" and not (tmp_path / "out" / "__MACOSX").exists()


# ---------------------------------------------------------------------------------------------------- hostile ones
Build = Callable[[Path, dict], Path]


def _gz(raw: bytes) -> bytes:
    return gzip.compress(raw, compresslevel=1, mtime=0)


def _tar_body(files) -> bytes:
    """The members of a tar, without the end-of-archive marker (to append hand-made blocks to)."""
    buf = io.BytesIO()
    tf = tarfile.open(fileobj=buf, mode="w", format=tarfile.GNU_FORMAT)
    for name, data in files.items():
        info, data = tar_member(name, data)
        tf.addfile(info, io.BytesIO(data))
    body = buf.getvalue()[: tf.offset]
    tf.close()
    return body


def _write(path: Path, raw: bytes) -> Path:
    path.write_bytes(raw)
    return path


def _damaged(build: Build, damage: Callable[[bytes], bytes]) -> Build:
    return lambda p, ds: _write(p, damage(build(p, ds).read_bytes()))


def _flip_middle(raw: bytes) -> bytes:
    mid = len(raw) // 2
    return raw[:mid] + bytes(b ^ 0x5A for b in raw[mid:mid + 64]) + raw[mid + 64:]


def _zip_bad_crc(p: Path, ds) -> Path:
    """Flip a byte inside the last member's stored data: the central directory is intact, the CRC is not."""
    zip_archive(p, ds, prefix="ds/", method=zipfile.ZIP_STORED)
    with zipfile.ZipFile(p) as zf:
        info = zf.getinfo("ds/tracking.npz")
    raw = bytearray(p.read_bytes())
    raw[info.header_offset + 30 + len(info.filename) + 10] ^= 0xFF
    return _write(p, bytes(raw))


def _zip_bad_utf8(p: Path, ds) -> Path:
    raw = zip_archive(p, ds, extra=[("caf\u00e9", b"x")]).read_bytes()
    return _write(p, raw.replace("caf\u00e9".encode(), b"caf\xff\xfe"))


def _zip_encrypted(p: Path, ds) -> Path:
    """A member flagged as encrypted (zipfile cannot write one: the flag is set by hand, local and central)."""
    raw = bytearray(zip_archive(p, ds, extra=[("secret.bin", b"x")]).read_bytes())
    with zipfile.ZipFile(p) as zf:
        raw[zf.getinfo("secret.bin").header_offset + 6] |= 0x1
    central = raw.rfind(b"PK\x01\x02", 0, raw.rfind(b"secret.bin"))
    raw[central + 8] |= 0x1
    return _write(p, bytes(raw))


def _pax_bomb(p: Path, ds) -> Path:
    """A pax extended header declaring 64 MiB: tarfile would buffer it whole; refused before the read."""
    header = tar_member("ds/evil", size=64 << 20, type=tarfile.XHDTYPE)[0].tobuf(tarfile.GNU_FORMAT)
    return _write(p, _gz(_tar_body(ds) + header + bytes(64 << 10)))


def _pax_sparse(p: Path, ds) -> Path:
    """GNU sparse format 1.0: a pax header announcing a sparse map that tarfile would read from the data."""
    info, _ = tar_member("holes", b"1\n" * 4096)
    info.pax_headers = {"GNU.sparse.major": "1", "GNU.sparse.minor": "0", "GNU.sparse.realsize": "1000000"}
    return tar_archive(p, ds, extra=[(info, b"1\n" * 4096)])


SMALL_RATIO = ArchiveLimits(ratio_grace_bytes=64 << 10)
ANY = "<any member>"

HOSTILE: dict[str, tuple[Build, ArchiveLimits | None, str, str | None]] = {
    # id: (build(path, dataset) -> archive, limits, reason, offending member (None: the archive as a whole))
    "traversal": (lambda p, ds: tar_archive(p, ds, extra=[tar_member("../evil", b"x")]), None, "traversal",
                  "../evil"),
    "traversal deep": (lambda p, ds: tar_archive(p, ds, prefix="ds/", gz=True,
                                                 extra=[tar_member("ds/frames/../../../evil", b"x")]),
                       None, "traversal", "ds/frames/../../../evil"),
    "zip traversal": (lambda p, ds: zip_archive(p, ds, extra=[("../../evil", b"x")]), None, "traversal",
                      "../../evil"),
    "absolute": (lambda p, ds: tar_archive(p, ds, extra=[tar_member("/etc/evil", b"x")]), None, "absolute",
                 "/etc/evil"),
    "drive letter": (lambda p, ds: zip_archive(p, ds, extra=[("C:/evil", b"x")]), None, "absolute", "C:/evil"),
    "backslash": (lambda p, ds: zip_archive(p, ds, extra=[("..\\..\\evil", b"x")]), None, "name",
                  "..\\..\\evil"),
    "symlink": (lambda p, ds: tar_archive(p, ds, extra=[tar_member("frames/link", type=tarfile.SYMTYPE,
                                                                    linkname="/etc/passwd")]),
                None, "link", "frames/link"),
    "zip symlink": (lambda p, ds: zip_archive(p, ds, extra=[zip_link("masks/link", "../../etc")]), None, "link",
                    "masks/link"),
    "hard link": (lambda p, ds: tar_archive(p, ds, gz=True, extra=[tar_member("hard", type=tarfile.LNKTYPE,
                                                                               linkname="dataset.json")]),
                  None, "link", "hard"),
    "char device": (lambda p, ds: tar_archive(p, ds, extra=[tar_member("dev", type=tarfile.CHRTYPE)]), None,
                    "special", "dev"),
    "block device": (lambda p, ds: tar_archive(p, ds, extra=[tar_member("blk", type=tarfile.BLKTYPE)]), None,
                     "special", "blk"),
    "fifo": (lambda p, ds: tar_archive(p, ds, extra=[tar_member("fifo", type=tarfile.FIFOTYPE)]), None,
             "special", "fifo"),
    "sparse": (lambda p, ds: tar_archive(p, ds, fmt=tarfile.GNU_FORMAT,
                                         extra=[tar_member("holes", type=tarfile.GNUTYPE_SPARSE)]),
               None, "special", "holes"),
    "pax sparse": (_pax_sparse, None, "special", None),
    "bomb tar.gz": (lambda p, ds: tar_archive(p, ds, gz=True, extra=[tar_member("zeros", bytes(4 << 20))]),
                    SMALL_RATIO, "bomb", "zeros"),
    "bomb zip member": (lambda p, ds: zip_archive(p, ds, extra=[("zeros", bytes(4 << 20))]), SMALL_RATIO, "bomb",
                        "zeros"),
    "bomb after the end": (lambda p, ds: _write(p, _gz(_tar_body(ds) + bytes(4 << 20))), SMALL_RATIO, "bomb",
                           None),
    "forged pax header": (_pax_bomb, None, "corrupt", None),
    "too many files": (lambda p, ds: tar_archive(p, ds), ArchiveLimits(max_members=5), "too_many",
                       "masks/00000.png"),
    "zip too many files": (lambda p, ds: zip_archive(p, ds), ArchiveLimits(max_members=5), "too_many", None),
    "too large": (lambda p, ds: tar_archive(p, ds, gz=True), ArchiveLimits(max_total_bytes=1000), "too_large",
                  ANY),
    "member too large": (lambda p, ds: zip_archive(p, ds), ArchiveLimits(max_member_bytes=1000), "too_large",
                         "tracking.npz"),
    "corrupt tar.gz": (_damaged(lambda p, ds: tar_archive(p, ds, gz=True), _flip_middle), None, "corrupt", None),
    "truncated tar.gz": (_damaged(lambda p, ds: tar_archive(p, ds, gz=True), lambda r: r[: len(r) // 2]), None,
                         "corrupt", None),
    "truncated tar": (_damaged(lambda p, ds: tar_archive(p, ds), lambda r: r[: len(r) // 2]), None, "corrupt",
                      None),
    "tar without its end": (lambda p, ds: _write(p, _tar_body(ds)), None, "corrupt", None),
    "garbage after the end": (_damaged(lambda p, ds: tar_archive(p, ds), lambda r: r + b"garbage" * 100), None,
                              "corrupt", None),
    "truncated zip": (_damaged(lambda p, ds: zip_archive(p, ds), lambda r: r[: len(r) // 2]), None, "corrupt",
                      None),
    "zip bad crc": (_zip_bad_crc, None, "corrupt", "ds/tracking.npz"),
    "not an archive": (lambda p, ds: _write(p, b"hello, this is a text file\n" * 40), None, "kind", None),
    "empty file": (lambda p, ds: _write(p, b""), None, "kind", None),
    "bzip2": (lambda p, ds: _write(p, b"BZh91AY&SY" + bytes(600)), None, "kind", None),
    "gzip without a tar": (lambda p, ds: _write(p, _gz(b"just text\n" * 100)), None, "kind", None),
    "duplicate": (lambda p, ds: tar_archive(p, ds, extra=[tar_member("dataset.json", b"{}")]), None, "duplicate",
                  "dataset.json"),
    "duplicate after ./": (lambda p, ds: tar_archive(p, ds, extra=[tar_member("./frames//00000.png", b"x")]), None,
                           "duplicate", "./frames//00000.png"),
    "zip duplicate": (lambda p, ds: zip_archive(p, ds, extra=[("tracking.npz", b"x")]), None, "duplicate",
                      "tracking.npz"),
    "file over a folder": (lambda p, ds: tar_archive(p, ds, extra=[tar_member("frames", b"x")]), None,
                           "duplicate", "frames"),
    "not utf-8": (lambda p, ds: tar_archive(p, ds, fmt=tarfile.GNU_FORMAT, extra=[tar_member("caf\udce9", b"x")]),
                  None, "name", "caf\udce9"),
    "zip not utf-8": (_zip_bad_utf8, None, "name", "caf\udcff\udcfe"),
    "control character": (lambda p, ds: tar_archive(p, ds, extra=[tar_member("frames/a\nb.png", b"x")]), None,
                          "name", "frames/a\nb.png"),
    "zip encrypted": (_zip_encrypted, None, "unsupported", "secret.bin"),
    "two top-level folders": (lambda p, ds: tar_archive(p, ds, prefix="a/", extra=[tar_member("b/x", b"x")]), None,
                              "layout", None),
    "no dataset.json": (lambda p, ds: zip_archive(p, {k: v for k, v in ds.items() if k != "dataset.json"},
                                                  prefix="ds/"), None, "layout", None),
}


@pytest.mark.parametrize("name", list(HOSTILE))
def test_hostile_archive_is_refused_and_leaves_nothing(tmp_path, dataset, name):
    build, limits, reason, member = HOSTILE[name]
    (tmp_path / "in").mkdir()
    (tmp_path / "out").mkdir()
    path = build(tmp_path / "in" / "upload", dataset)
    limits = limits or ArchiveLimits()
    with pytest.raises(ArchiveError) as caught:
        extract_archive(path, tmp_path / "out" / "x", limits)
    e = caught.value
    assert isinstance(e, InvalidArgument) and e.field == "file"
    assert e.reason == reason, str(e)
    assert e.member == member or (member is ANY and e.member), str(e)
    if member not in (None, ANY):
        assert repr(member)[1:-1] in str(e) or repr(member.encode("utf-8", "surrogateescape")) in str(e)
    assert list((tmp_path / "out").iterdir()) == []
    assert [p.name for p in (tmp_path / "in").iterdir()] == ["upload"]
    if name != "zip bad crc":  # zip CRCs are checked as members are written, after other files were
        with pytest.raises(ArchiveError):  # inspection refuses it the same way, without a destination
            inspect_archive(path, limits)


def test_refusal_messages_name_the_problem(tmp_path, dataset):
    path = tar_archive(tmp_path / "t", dataset, extra=[tar_member("x", type=tarfile.SYMTYPE, linkname="/etc")])
    with pytest.raises(ArchiveError, match=r"symbolic links are refused \(-> '/etc'\) \(member 'x'\)"):
        extract_archive(path, tmp_path / "out")
    path = tar_archive(tmp_path / "b", dataset, gz=True, extra=[tar_member("zeros", bytes(4 << 20))])
    with pytest.raises(ArchiveError, match="decompression bomb"):
        inspect_archive(path, SMALL_RATIO)
    assert not (tmp_path / "out").exists()


def test_a_bomb_is_refused_before_it_is_decompressed(tmp_path, dataset):
    """A member declaring more than the limits is refused at its header: tarfile never seeks over its data."""
    zeros = tar_member("zeros", size=1 << 40)[0].tobuf(tarfile.GNU_FORMAT)
    path = _write(tmp_path / "b", _gz(_tar_body(dataset) + zeros + bytes(1 << 20)))
    with pytest.raises(ArchiveError, match="larger than") as caught:
        inspect_archive(path)
    assert caught.value.reason == "too_large" and caught.value.member == "zeros"
