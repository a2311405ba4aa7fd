"""Avatar bundles: one self-contained, memory-mappable file per avatar (docs/architecture.md, "Avatar bundle").

A bundle is a standard safetensors file::

    [8 bytes: u64 little-endian header length H] [H bytes: UTF-8 JSON header] [data region: raw tensors]

The header maps each tensor name to ``{"dtype", "shape", "data_offsets": [begin, end]}`` (offsets relative to
the data region, little-endian, C order) and holds
``__metadata__ = {"blendsplat.manifest": <manifest JSON>}``.

Schema 2 (what :func:`write_bundle` writes) stores the packed layout of :mod:`render_core.packed`, which the
native renderer reads as it is, so a load is a memory map: N face Gaussians, K blendshapes, J joints, M mouth
Gaussians, C = (sh_degree+1)^2, R = 16 + ceil16(3C), Pg and Pc stored geometry and colour pairs::

    gaussians [N + M, R] F32                       face then mouth Gaussian rows (packed.py)
    deltas.geometry.row_ptr [N + 1] I32            deltas.color.row_ptr [N + 1] I32
    deltas.geometry.col [Pg] U16                   deltas.color.col [Pc] U16
    deltas.geometry.values [Pg * 11 + 5]           deltas.color.values [Pc * 3C + ceil16(3C) - 3C]
    mouth_group [M] I64   lbs_weights [N, J] F32   joint_positions [J, 3] F32
    pose_correctives [N, 3, ceil16(9 (J-1))]       eyelid_offsets [N, 2, 3] F32   (both optional)

and, with precision int8 only (the scales of the quantised values and the positions' second byte, packed.py)::

    deltas.geometry.scale [K, 16] F32              deltas.color.scale [K, ceil16(3C)] F32
    deltas.geometry.position_residual [Pg * 3 + 13] I8

The manifest's ``precision`` names the storage of the pair values: F32 ("fp32"), F16 ("fp16", the default) or I8
("int8": symmetric int8 times float32 scales, finite and not negative; schema 2 only). The pose correctives are
stored in the same precision, F16 for int8. Pairs are sorted by Gaussian, then blendshape, with no duplicates.
Schema 1 stored every pair densely::

    neutral.means [N, 3]  neutral.quats [N, 4] (wxyz)  neutral.log_scales [N, 3]  neutral.opacity_logits [N]
    neutral.sh [N, C, 3]                 deltas.<same five> [K, N, ...]       mouth.<same five> [M, ...]
    mouth_group [M] I64                  lbs_weights [N, J] F32               joint_positions [J, 3] F32
    pose_correctives [9 (J-1), N, 3]     eyelid_offsets [2, N, 3]             (both optional)

with the delta, corrective and eyelid tensors in the bundle's precision; it still loads (as dense deltas), and
``blendsplat bundle convert`` rewrites it as schema 2.

The manifest is a JSON object: ``format`` ("blendsplat-avatar"), ``schema_version``, ``face_model``,
``expression_names`` (in order), ``joint_names``, ``joint_parents``, ``mouth_joint_names`` (upper, lower),
``sh_degree``, ``counts`` {gaussians, blendshapes, joints, mouth}, ``precision``, ``raster_mode``,
``default_camera`` {width, height, K 3x3, R 3x3, t 3}, ``provenance``, ``tensors`` {name: {dtype, shape}} and
``digest``.

Digest: ``"sha256:" + hex(SHA-256(DOMAIN || u64le(len(canon)) || canon || bytes of every tensor in ascending
name order))`` where DOMAIN is ``b"blendsplat-avatar-digest-v1\\n"`` and ``canon`` is the manifest as stored,
without ``digest``, as JSON with sorted keys, no whitespace and ASCII escapes. The reader requires the tensors
to tile the data region exactly, so every data byte is covered, and hashing by name (not file order) also
detects tensors whose offsets were swapped. Any edit of the manifest is detected too.

Schema versions: :data:`UPGRADERS` maps a version v to a function turning a v manifest into a v+1 manifest;
on load :func:`upgrade_manifest` applies the chain up to :data:`CURRENT_SCHEMA_VERSION`. The digest always
refers to the manifest as stored (before upgrading), and the tensors are read in the layout of the stored version
(the manifest keys of schemas 1 and 2 are the same; the ``tensors`` table describes the file as stored).
"""

from __future__ import annotations

import copy
import errno
import hashlib
import importlib.metadata
import json
import math
import mmap
import os
import sys
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

import numpy as np
import safetensors.numpy
import torch
from torch import Tensor

from . import packed
from .atomic import atomic_path
from .avatar import RASTER_MODES, Avatar, Gaussians
from .camera import calibration_problem
from .errors import BlendsplatError, BundleError

CURRENT_SCHEMA_VERSION = 2
FORMAT = "blendsplat-avatar"
MANIFEST_KEY = "blendsplat.manifest"
PRECISIONS: tuple[str, ...] = ("fp32", "fp16", "int8")
UPGRADERS: dict[int, Callable[[dict[str, Any]], dict[str, Any]]] = {
    1: dict,  # 1 -> 2 changed the tensor layout only (read by the stored version), not the manifest's keys
}
"""Schema upgraders: ``UPGRADERS[v]`` turns a version-v manifest into a version-(v+1) one.
:func:`upgrade_manifest` sets ``schema_version`` after each step."""

_DIGEST_DOMAIN = b"blendsplat-avatar-digest-v1\n"
_MAX_HEADER_BYTES = 100 * 1024 * 1024
_HASH_CHUNK_BYTES = 64 * 1024 * 1024
_FINITE_CHUNK = 1 << 24  # elements per isfinite() pass
_GAUSSIAN_KEYS = ("means", "quats", "log_scales", "opacity_logits", "sh")
_GAUSSIAN_TAILS: dict[str, tuple[str, ...]] = {
    "means": ("3",), "quats": ("4",), "log_scales": ("3",), "opacity_logits": (), "sh": ("C", "3"),
}
_GROUP_LEADS = {"neutral": ("N",), "deltas": ("K", "N"), "mouth": ("M",)}
_OPTIONAL = ("pose_correctives", "eyelid_offsets")
_DTYPES: dict[str, torch.dtype] = {"F32": torch.float32, "F16": torch.float16, "I64": torch.int64,
                                   "I32": torch.int32, "U16": torch.uint16, "I8": torch.int8}
_DTYPE_NAMES = {v: k for k, v in _DTYPES.items()}
_ITEMSIZE = {"F32": 4, "F16": 2, "I64": 8, "I32": 4, "U16": 2, "I8": 1}
_PRECISION_DTYPE = {"fp32": "F32", "fp16": "F16", "int8": "I8"}  # the pair values
_SIDE_DTYPE = {"fp32": "F32", "fp16": "F16", "int8": "F16"}  # pose correctives (schema 1: eyelids too)
_SCALES = ("scale", "position_residual")  # the tensors of an int8 table besides row_ptr, col and values
# Symbolic shape of every tensor a schema-1 bundle may hold (N, K, J, M, C and literals).
_SHAPES_V1: dict[str, tuple[str, ...]] = {
    **{f"{group}.{key}": (*lead, *_GAUSSIAN_TAILS[key]) for group, lead in _GROUP_LEADS.items()
       for key in _GAUSSIAN_KEYS},
    "mouth_group": ("M",),
    "lbs_weights": ("N", "J"),
    "joint_positions": ("J", "3"),
    "pose_correctives": ("9(J-1)", "N", "3"),
    "eyelid_offsets": ("2", "N", "3"),
}


# ---------------------------------------------------------------------------------------------------- writing


def write_bundle(
    avatar: Avatar, path: str | os.PathLike, precision: Literal["fp32", "fp16", "int8"] = "fp16", *,
    schema_version: int = CURRENT_SCHEMA_VERSION,
) -> dict[str, Any]:
    """Write ``avatar`` to ``path`` as one bundle file and return its manifest.

    ``precision`` is the storage of the blendshape data (delta pairs, pose correctives; schema 1 also eyelid
    offsets): float16 by default, float32, or (schema 2 only) int8 pair values with float32 scales
    (:meth:`render_core.packed.Pairs.quantize`) and float16 pose correctives; the neutral and mouth Gaussians,
    ``lbs_weights`` and ``joint_positions`` stay float32. Only the (Gaussian, blendshape) pairs with a non-zero
    value (after the cast) are stored. ``schema_version`` 1 writes the old dense layout (for tools that read only
    that; loading it costs a repack). ``provenance`` gains ``created_at`` (ISO 8601, UTC) and
    ``blendsplat_version`` where absent.

    The write is atomic: the file is written to a temporary name in the same folder, fsynced and renamed over
    ``path``, so a crash leaves either the old file or the new one. An invalid avatar (bad shapes, non-finite
    values, values that overflow float16, a malformed default camera) raises :class:`BundleError` before
    anything is written. I/O failures raise ``OSError``.

    Example::

        manifest = write_bundle(synth_avatar(), "head.bsplat", precision="fp16")
    """
    if precision not in PRECISIONS:
        raise BundleError(f"must be one of {PRECISIONS}, got {precision!r}", field="precision")
    if schema_version not in (1, 2):
        raise BundleError(f"writes schema 1 or 2, got {schema_version!r}", field="schema_version")
    _check_precision(precision, schema_version)
    _validate_avatar(avatar)
    tensors = (_tensors_v1 if schema_version == 1 else _tensors_v2)(avatar, precision)
    manifest = _build_manifest(avatar, precision, tensors, schema_version)
    _check_manifest(manifest)
    _check_tensor_table(manifest, {n: (_DTYPE_NAMES[t.dtype], tuple(t.shape)) for n, t in tensors.items()},
                        schema_version)
    arrays = {name: t.numpy() for name, t in tensors.items()}
    manifest["digest"] = _content_digest(manifest, (_as_bytes(arrays[name]) for name in sorted(arrays)))
    with atomic_path(path) as tmp:
        _serialize(arrays, str(tmp), {MANIFEST_KEY: json.dumps(manifest, separators=(",", ":"))})
    return manifest


def _tensors_v2(avatar: Avatar, precision: str) -> dict[str, Tensor]:
    """The schema-2 tensors (the packed layout), contiguous on the CPU; refuses non-finite values."""
    store, side = _DTYPES[_PRECISION_DTYPE[precision]], _DTYPES[_SIDE_DTYPE[precision]]
    for group in ("neutral", "mouth"):
        for key, t in getattr(avatar, group).tensors().items():
            _cast_finite(f"{group}.{key}", t, torch.float32)
    out = {"gaussians": packed.pack_rows(avatar.neutral, avatar.mouth).contiguous()}
    dense = avatar.deltas if isinstance(avatar.deltas, Gaussians) else None
    sources = dense.tensors() if dense is not None else avatar.deltas.tensors()
    for key, t in sources.items():
        if t.is_floating_point() and _count_nonfinite(t.detach()):
            raise BundleError(f"{_count_nonfinite(t.detach())} non-finite values (NaN/Inf); refusing to write the "
                              "bundle", field=f"deltas.{key}")
    deltas = avatar.sparse_deltas(store)
    for key, t in deltas.tensors().items():
        bad = _count_nonfinite(t) if t.is_floating_point() else 0
        if bad:  # finite before the cast: values beyond the storage's range; name the dense tensor where known
            field = next((f"deltas.{k}" for k, d in (dense.tensors().items() if dense is not None else ())
                          if _count_nonfinite(d.detach().to(store))), f"deltas.{key}")
            raise BundleError(f"{bad} values overflow {t.dtype} (|x| > {torch.finfo(t.dtype).max:g}); write with "
                              "precision='fp32'", field=field)
        out[f"deltas.{key}"] = t.contiguous()
    if avatar.pose_correctives is not None:
        pc = _cast_finite("pose_correctives", avatar.pose_correctives, side)
        out["pose_correctives"] = packed.pack_correctives(pc, side)
    if avatar.eyelid_offsets is not None:
        out["eyelid_offsets"] = packed.pack_eyelids(_cast_finite("eyelid_offsets", avatar.eyelid_offsets,
                                                                  torch.float32))
    _add_skinning(avatar, out)
    return out


def _add_skinning(avatar: Avatar, out: dict[str, Tensor]) -> None:
    """LBS weights and joint positions (float32) and the mouth groups (int64), as both schemas store them."""
    out["lbs_weights"] = _cast_finite("lbs_weights", avatar.lbs_weights, torch.float32)
    out["joint_positions"] = _cast_finite("joint_positions", avatar.joint_positions, torch.float32)
    if avatar.mouth_group.is_floating_point() or avatar.mouth_group.dtype == torch.bool:
        raise BundleError(f"expected an integer tensor, got {avatar.mouth_group.dtype}", field="mouth_group")
    out["mouth_group"] = avatar.mouth_group.detach().to("cpu", torch.int64).contiguous()


def _tensors_v1(avatar: Avatar, precision: str) -> dict[str, Tensor]:
    """The schema-1 tensors (dense deltas), contiguous on the CPU in their stored dtypes; refuses non-finite
    values."""
    source: dict[str, Tensor] = {}
    for group in _GROUP_LEADS:
        g = avatar.dense_deltas() if group == "deltas" else getattr(avatar, group)
        for key, t in g.tensors().items():
            source[f"{group}.{key}"] = t
    for name in _OPTIONAL:
        if getattr(avatar, name) is not None:
            source[name] = getattr(avatar, name)
    out: dict[str, Tensor] = {}
    for name, t in source.items():
        if not t.is_floating_point():
            raise BundleError(f"expected a floating-point tensor, got {t.dtype}", field=name)
        out[name] = _cast_finite(name, t, _DTYPES[_stored_dtype(name, precision)])
    _add_skinning(avatar, out)
    return out


def _cast_finite(name: str, t: Tensor, dtype: torch.dtype) -> Tensor:
    bad = _count_nonfinite(t.detach())
    if bad:
        raise BundleError(f"{bad} non-finite values (NaN/Inf); refusing to write the bundle", field=name)
    out = t.detach().to("cpu", dtype).contiguous()
    bad = _count_nonfinite(out)
    if bad:
        raise BundleError(
            f"{bad} values overflow {dtype} (|x| > {torch.finfo(dtype).max:g}); write with precision='fp32'",
            field=name,
        )
    return out


def _build_manifest(avatar: Avatar, precision: str, tensors: Mapping[str, Tensor], version: int) -> dict[str, Any]:
    provenance = dict(avatar.provenance)
    provenance.setdefault("created_at", datetime.now(UTC).isoformat(timespec="seconds"))
    provenance.setdefault("blendsplat_version", _package_version())
    manifest: dict[str, Any] = {
        "format": FORMAT,
        "schema_version": version,
        "face_model": avatar.face_model,
        "expression_names": list(avatar.expression_names),
        "joint_names": list(avatar.joint_names),
        "joint_parents": [int(p) for p in avatar.joint_parents],
        "mouth_joint_names": list(avatar.mouth_joint_names),
        "sh_degree": avatar.sh_degree,
        "counts": {
            "gaussians": avatar.num_gaussians,
            "blendshapes": avatar.num_expressions,
            "joints": avatar.num_joints,
            "mouth": avatar.num_mouth,
        },
        "precision": precision,
        "raster_mode": avatar.raster_mode,
        "default_camera": avatar.default_camera,
        "provenance": provenance,
        "tensors": {
            name: {"dtype": _DTYPE_NAMES[t.dtype], "shape": list(t.shape)}
            for name, t in sorted(tensors.items())
        },
    }
    for key, value in manifest.items():
        try:
            json.dumps(value, allow_nan=False)
        except (TypeError, ValueError) as e:
            raise BundleError(f"not JSON-serialisable ({e})", field=key) from None
    # Round-trip through JSON so the returned manifest (and the digest) is exactly what a reader sees.
    return json.loads(json.dumps(manifest))


def _package_version() -> str:
    try:
        return importlib.metadata.version("blendsplat")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def _serialize(arrays: Mapping[str, np.ndarray], path: str, metadata: dict[str, str]) -> None:
    """Write a safetensors file: the one call of the serializer (tests replace it to simulate a crash)."""
    safetensors.numpy.save_file(dict(arrays), path, metadata=metadata)


# ---------------------------------------------------------------------------------------------------- reading


def read_bundle(
    path: str | os.PathLike, *, verify: bool = True, device: torch.device | str | None = None
) -> Avatar:
    """Load the avatar stored at ``path``.

    Tensors are zero-copy views of a private (copy-on-write) memory map of the file: nothing is read into RAM
    until used, and writing to a loaded tensor never changes the file. fp16 bundles load as fp16 tensors.
    ``device`` other than the CPU copies the tensors there.

    With ``verify`` (the default) the content digest is checked (the file was not modified or corrupted) and
    every float tensor must be finite; the layout, manifest and shapes are always checked. Older schema
    versions are upgraded through :data:`UPGRADERS`. Every problem raises :class:`BundleError` whose ``field``
    names the offending tensor or manifest key.

    Bundles are immutable once written (:func:`write_bundle` replaces a file atomically, so a loaded avatar keeps
    its own inode); truncating a bundle in place under a process that has it mapped would fault that process.

    Example::

        avatar = read_bundle("head.bsplat")            # fp16 or fp32 tensors, memory-mapped
        avatar = read_bundle("head.bsplat", device="cuda")
    """
    return _load(path, verify=verify, device=device)[0]


def read_bundle_and_manifest(
    path: str | os.PathLike, *, verify: bool = True, device: torch.device | str | None = None
) -> tuple[Avatar, dict]:
    """:func:`read_bundle` and the (upgraded) manifest of the same file, from one read of its header (a store
    that replaces bundles atomically cannot pair an avatar with a newer file's manifest)."""
    return _load(path, verify=verify, device=device)


def read_manifest(path: str | os.PathLike) -> dict:
    """The (upgraded) manifest of the bundle at ``path``, reading only the header.

    Checks the layout, format, schema version, manifest fields and tensor shapes like :func:`read_bundle`, but
    neither maps nor hashes the tensor data. Raises :class:`BundleError`.
    """
    with _open(path) as f:
        return _parse(f)[1]


def stored_schema_version(path: str | os.PathLike) -> int:
    """The schema version the bundle at ``path`` was written with (before upgrading; reads only the header)."""
    with _open(path) as f:
        return _parse(f)[0].stored_manifest["schema_version"]


def validate_bundle(path: str | os.PathLike) -> dict:
    """Fully check the bundle at ``path`` (layout, manifest, shapes, digest, finiteness, avatar invariants).

    Returns the (upgraded) manifest; raises :class:`BundleError` naming the first problem.
    """
    return _load(path, verify=True, device=None)[1]


def upgrade_manifest(manifest: dict) -> dict:
    """A copy of ``manifest`` upgraded to :data:`CURRENT_SCHEMA_VERSION` through :data:`UPGRADERS`.

    Raises :class:`BundleError` (field ``schema_version``) for a version newer than this build reads, or an
    older one with no chain of upgraders to the current version.
    """
    version = manifest.get("schema_version")
    if version is None:
        raise BundleError("missing", field="schema_version")
    if not _is_int(version) or version < 1:
        raise BundleError(f"must be a positive integer, got {version!r}", field="schema_version")
    current = CURRENT_SCHEMA_VERSION
    if version > current:
        raise BundleError(
            f"schema_version {version} is newer than this build reads ({_readable_versions()}); "
            "upgrade blendsplat",
            field="schema_version",
        )
    out = copy.deepcopy(manifest)
    for v in range(version, current):
        upgrader = UPGRADERS.get(v)
        if upgrader is None:
            raise BundleError(
                f"schema_version {version} cannot be read: no upgrader from {v} to {v + 1} "
                f"(this build reads {_readable_versions()})",
                field="schema_version",
            )
        try:
            out = upgrader(out)
        except BlendsplatError:
            raise
        except Exception as e:
            raise BundleError(f"upgrading from {v} to {v + 1} failed: {type(e).__name__}: {e}",
                              field="schema_version") from e
        if not isinstance(out, dict):
            raise BundleError(f"the upgrader from {v} returned {type(out).__name__}, not a dict",
                              field="schema_version")
        out["schema_version"] = v + 1
    return out


def _readable_versions() -> str:
    """The schema versions this build can read, as text ("1" or "1, 2, 3")."""
    current = CURRENT_SCHEMA_VERSION
    ok = [current]
    for v in range(current - 1, 0, -1):
        if v not in UPGRADERS:
            break
        ok.append(v)
    return ", ".join(str(v) for v in sorted(ok))


@dataclass(frozen=True)
class _Entry:
    """One tensor of the safetensors header: dtype name, shape and byte range in the data region."""

    dtype: str
    shape: tuple[int, ...]
    begin: int
    end: int


@dataclass(frozen=True)
class _Layout:
    file_size: int
    data_start: int
    entries: dict[str, _Entry]
    stored_manifest: dict[str, Any]  # as stored (the digest refers to it), before upgrading


def _open(path: str | os.PathLike):
    p = Path(path)
    if not p.exists():
        raise BundleError(f"no such file: {p}", field="path")
    if not p.is_file():
        raise BundleError(f"not a file: {p}", field="path")
    try:
        return open(p, "rb")
    except OSError as e:
        raise BundleError(f"cannot open {p}: {e.strerror}", field="path") from None


def _parse(f) -> tuple[_Layout, dict[str, Any]]:
    """Layout and upgraded, checked manifest of the open bundle ``f``."""
    layout = _read_layout(f)
    manifest = upgrade_manifest(layout.stored_manifest)
    _check_manifest(manifest)
    _check_tensor_table(manifest, {name: (e.dtype, e.shape) for name, e in layout.entries.items()},
                        layout.stored_manifest["schema_version"])
    return layout, manifest


class BundleMappingError(BundleError):
    """The bundle's file could not be memory-mapped: a limit of this machine or process (``errno``: ENOMEM when
    there is not enough memory or address space for a private map of the whole file), not a fault of its content.
    The service answers RESOURCE_EXHAUSTED for it."""

    def __init__(self, message: str, *, os_errno: int, field: str | None = "path"):
        self.errno = os_errno
        super().__init__(message, field=field)


def _map(f, size: int) -> mmap.mmap:
    """A private (copy-on-write) map of the whole open file; an OS refusal as a :class:`BundleMappingError`
    naming the cause (never a bare ``[Errno 12]``)."""
    try:
        return mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_COPY)
    except (OSError, ValueError, OverflowError) as e:
        code = getattr(e, "errno", None) or errno.EINVAL
        name = errno.errorcode.get(code, str(code))
        why = getattr(e, "strerror", None) or str(e)
        hint = (": not enough memory or address space for a private map of the whole file (the process's memory "
                "limit, or the system's overcommit policy)" if code == errno.ENOMEM else "")
        raise BundleMappingError(f"cannot memory-map the {size}-byte file: {name} ({why}){hint}",
                                 os_errno=code) from None


def _load(path: str | os.PathLike, *, verify: bool, device: torch.device | str | None) -> tuple[Avatar, dict]:
    with _open(path) as f:
        layout, manifest = _parse(f)
        mapped = _map(f, layout.file_size)
    if len(mapped) != layout.file_size:
        raise BundleError(f"the file changed while loading ({layout.file_size} -> {len(mapped)} bytes)",
                          field="path")
    if verify:
        _verify_digest(layout, mapped)
    tensors = {name: _view(mapped, layout.data_start, e) for name, e in layout.entries.items()}
    if verify:
        for name, t in sorted(tensors.items()):
            bad = _count_nonfinite(t) if t.is_floating_point() else 0
            if bad:
                raise BundleError(f"{bad} of {t.numel()} values are non-finite (NaN/Inf)", field=name)
    version = layout.stored_manifest["schema_version"]
    avatar = (_avatar_from_v1 if version == 1 else _avatar_from_v2)(manifest, tensors)
    _validate_avatar(avatar)
    if device is not None:
        avatar = avatar.to(device=device)
    return avatar, manifest


def _read_layout(f) -> _Layout:
    """Parse and check the safetensors header of the open file ``f`` (no tensor data is read)."""
    size = os.fstat(f.fileno()).st_size
    if size < 8:
        what = "the file is empty" if size == 0 else f"the file has {size} bytes"
        raise BundleError(f"truncated: {what}; a bundle starts with an 8-byte header length", field="header")
    header_len = int.from_bytes(f.read(8), "little")
    if header_len > size - 8:
        raise BundleError(
            f"truncated or not a bundle: the header length says {header_len} bytes but the file has only "
            f"{size - 8} after the length prefix",
            field="header",
        )
    if header_len > _MAX_HEADER_BYTES:
        raise BundleError(
            f"header length {header_len} exceeds the {_MAX_HEADER_BYTES}-byte limit; not a bundle",
            field="header",
        )
    raw = f.read(header_len)
    if len(raw) != header_len:
        raise BundleError(f"truncated: expected a {header_len}-byte header, read {len(raw)}", field="header")
    header = _parse_json(raw, "header", "the safetensors header")
    meta = header.pop("__metadata__", None)
    if not isinstance(meta, dict):
        raise BundleError("the safetensors header has no __metadata__ (not a blendsplat bundle)",
                          field="manifest")
    text = meta.get(MANIFEST_KEY)
    if not isinstance(text, str):
        raise BundleError(f"__metadata__ has no {MANIFEST_KEY!r} string (not a blendsplat bundle)",
                          field="manifest")
    manifest = _parse_json(text.encode("utf-8", "surrogatepass"), "manifest", "the manifest")
    if manifest.get("format") != FORMAT:
        raise BundleError(f"expected {FORMAT!r}, got {manifest.get('format')!r}", field="format")

    data_start = 8 + header_len
    entries = {name: _parse_entry(name, spec) for name, spec in header.items()}
    end = 0
    previous = None
    for name, e in sorted(entries.items(), key=lambda item: (item[1].begin, item[1].end)):
        if e.begin < end:
            raise BundleError(f"data_offsets {[e.begin, e.end]} overlap {previous!r} (which ends at {end})",
                              field=name)
        if e.begin > end:
            raise BundleError(
                f"a gap of {e.begin - end} bytes precedes it; tensors must tile the data region", field=name
            )
        end, previous = e.end, name
    available = size - data_start
    if available < end:
        raise BundleError(f"truncated: expected {end} bytes of tensor data, file has {available}",
                          field="data")
    if available > end:
        raise BundleError(f"{available - end} unexpected bytes after the tensor data ({end} bytes)",
                          field="data")
    return _Layout(size, data_start, entries, manifest)


def _parse_json(raw: bytes, field: str, what: str) -> dict[str, Any]:
    def no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
        out = dict(pairs)
        if len(out) != len(pairs):
            seen: set[str] = set()
            dup = next(k for k, _ in pairs if k in seen or seen.add(k))
            raise ValueError(f"duplicate key {dup!r}")
        return out

    try:
        value = json.loads(raw.decode("utf-8"), object_pairs_hook=no_duplicates)
    except (UnicodeDecodeError, ValueError, RecursionError) as e:
        raise BundleError(f"{what} is not JSON ({type(e).__name__}: {str(e)[:200]})", field=field) from None
    if not isinstance(value, dict):
        raise BundleError(f"{what} must be a JSON object, got {type(value).__name__}", field=field)
    return value


def _parse_entry(name: str, spec: Any) -> _Entry:
    if not isinstance(spec, dict) or set(spec) != {"dtype", "shape", "data_offsets"}:
        raise BundleError(f"malformed header entry {spec!r:.200}; expected {{dtype, shape, data_offsets}}",
                          field=name)
    dtype, shape, offsets = spec["dtype"], spec["shape"], spec["data_offsets"]
    if dtype not in _DTYPES:
        raise BundleError(f"dtype {dtype!r} is not allowed; bundles store {', '.join(_DTYPES)}", field=name)
    if not isinstance(shape, list) or not all(_is_int(d) and d >= 0 for d in shape):
        raise BundleError(f"shape must be a list of non-negative integers, got {shape!r:.200}", field=name)
    if (not isinstance(offsets, list) or len(offsets) != 2 or not all(_is_int(o) for o in offsets)
            or not 0 <= offsets[0] <= offsets[1]):
        raise BundleError(f"data_offsets must be [begin, end] with 0 <= begin <= end, got {offsets!r:.200}",
                          field=name)
    need = math.prod(shape) * _ITEMSIZE[dtype]
    if offsets[1] - offsets[0] != need:
        raise BundleError(
            f"data_offsets {offsets} span {offsets[1] - offsets[0]} bytes but {dtype} {shape} needs {need}",
            field=name,
        )
    return _Entry(dtype, tuple(shape), offsets[0], offsets[1])


def _view(mapped: mmap.mmap, data_start: int, e: _Entry) -> Tensor:
    """A zero-copy tensor over the mapped bytes of one entry (a copy only for empty or misaligned tensors)."""
    dtype = _DTYPES[e.dtype]
    count = math.prod(e.shape)
    offset = data_start + e.begin
    if count == 0:
        return torch.empty(e.shape, dtype=dtype)
    t = torch.frombuffer(mapped, dtype=dtype, count=count, offset=offset).view(e.shape)
    if offset % _ITEMSIZE[e.dtype]:  # safetensors writers align tensors; a hand-made file may not
        t = t.clone()
    if sys.byteorder == "big":
        t = torch.from_numpy(t.numpy().byteswap())
    return t


def _verify_digest(layout: _Layout, mapped: mmap.mmap) -> None:
    stored = layout.stored_manifest.get("digest")
    if stored is None:
        raise BundleError("missing: cannot verify the content (load with verify=False to skip)",
                          field="digest")
    if not isinstance(stored, str) or not stored.startswith("sha256:"):
        raise BundleError(f"expected 'sha256:<hex>', got {stored!r:.100}", field="digest")
    view = memoryview(mapped)
    try:
        parts = [view[layout.data_start + e.begin : layout.data_start + e.end]
                 for _, e in sorted(layout.entries.items())]
        actual = _content_digest(layout.stored_manifest, parts)
        for part in parts:
            part.release()
    finally:
        view.release()
    if actual != stored:
        raise BundleError("content digest mismatch: the file was modified or corrupted", field="digest")


def _avatar_fields(manifest: dict[str, Any]) -> dict[str, Any]:
    """The avatar's non-tensor fields, from the manifest."""
    return dict(
        joint_names=list(manifest["joint_names"]),
        joint_parents=list(manifest["joint_parents"]),
        expression_names=list(manifest["expression_names"]),
        mouth_joint_names=tuple(manifest["mouth_joint_names"]),
        sh_degree=manifest["sh_degree"],
        face_model=manifest["face_model"],
        raster_mode=manifest["raster_mode"],
        default_camera=copy.deepcopy(manifest["default_camera"]),
        provenance=copy.deepcopy(manifest["provenance"]),
    )


def _avatar_from_v1(manifest: dict[str, Any], tensors: dict[str, Tensor]) -> Avatar:
    def group(name: str) -> Gaussians:
        return Gaussians(**{key: tensors[f"{name}.{key}"] for key in _GAUSSIAN_KEYS})

    return Avatar(
        neutral=group("neutral"),
        deltas=group("deltas"),
        lbs_weights=tensors["lbs_weights"],
        joint_positions=tensors["joint_positions"],
        mouth=group("mouth"),
        mouth_group=tensors["mouth_group"],
        pose_correctives=tensors.get("pose_correctives"),
        eyelid_offsets=tensors.get("eyelid_offsets"),
        **_avatar_fields(manifest),
    )


def _avatar_from_v2(manifest: dict[str, Any], tensors: dict[str, Tensor]) -> Avatar:
    """Views of the packed tensors (no copies): the native renderer finds its layout behind them."""
    counts, c = manifest["counts"], (manifest["sh_degree"] + 1) ** 2
    n, k, j = counts["gaussians"], counts["blendshapes"], counts["joints"]
    neutral, mouth = packed.unpack_rows(tensors["gaussians"], n, c)

    def pairs(part: str, length: int) -> packed.Pairs:
        return packed.Pairs(tensors[f"deltas.{part}.row_ptr"], tensors[f"deltas.{part}.col"],
                            tensors[f"deltas.{part}.values"], length,
                            *(tensors.get(f"deltas.{part}.{name}") for name in _SCALES))

    deltas = packed.SparseDeltas(pairs("geometry", packed.GEOMETRY_LENGTH), pairs("color", 3 * c), k, n, c)
    pc, eyelids = tensors.get("pose_correctives"), tensors.get("eyelid_offsets")
    return Avatar(
        neutral=neutral,
        deltas=deltas,
        lbs_weights=tensors["lbs_weights"],
        joint_positions=tensors["joint_positions"],
        mouth=mouth,
        mouth_group=tensors["mouth_group"],
        pose_correctives=packed.unpack_correctives(pc, j) if pc is not None else None,
        eyelid_offsets=packed.unpack_eyelids(eyelids) if eyelids is not None else None,
        **_avatar_fields(manifest),
    )


# ------------------------------------------------------------------------------------------- shared checks


def _validate_avatar(avatar: Avatar) -> None:
    """``avatar.validate()`` with its ShapeError/ValueError turned into BundleError (same field)."""
    try:
        avatar.validate()
    except BundleError:
        raise
    except BlendsplatError as e:
        message = str(e)
        if e.field and message.startswith(f"{e.field}: "):
            message = message[len(e.field) + 2 :]
        raise BundleError(message, field=e.field) from None
    except ValueError as e:
        raise BundleError(str(e), field="avatar") from None


def _check_manifest(m: dict[str, Any]) -> None:
    """Raise BundleError naming the first malformed manifest field (shapes are checked separately)."""
    if not isinstance(m.get("face_model"), str) or not m["face_model"]:
        raise BundleError(f"must be a non-empty string, got {m.get('face_model')!r}", field="face_model")
    counts = m.get("counts")
    if not isinstance(counts, dict):
        raise BundleError(f"must be an object {{gaussians, blendshapes, joints, mouth}}, got {counts!r:.100}",
                          field="counts")
    for key, low in (("gaussians", 1), ("blendshapes", 0), ("joints", 1), ("mouth", 0)):
        if not _is_int(counts.get(key)) or counts[key] < low:
            raise BundleError(f"must be an integer >= {low}, got {counts.get(key)!r}", field=f"counts.{key}")
    k, j = counts["blendshapes"], counts["joints"]

    expressions = _names(m, "expression_names")
    if len(expressions) != k:
        raise BundleError(f"{len(expressions)} names for {k} blendshapes (counts.blendshapes)",
                          field="expression_names")
    joints = _names(m, "joint_names")
    if len(joints) != j:
        raise BundleError(f"{len(joints)} names for {j} joints (counts.joints)", field="joint_names")

    parents = m.get("joint_parents")
    if not isinstance(parents, list) or not all(_is_int(p) for p in parents):
        raise BundleError(f"must be a list of integers, got {parents!r:.200}", field="joint_parents")
    if len(parents) != j:
        raise BundleError(f"{len(parents)} parents for {j} joints", field="joint_parents")
    for i, p in enumerate(parents):
        if (i == 0 and p != -1) or (i > 0 and not 0 <= p < i):
            raise BundleError(
                f"joint {joints[i]!r} has parent {p}; the first joint is the only root (-1) and every other "
                "joint's parent must precede it",
                field="joint_parents",
            )

    mouth_joints = m.get("mouth_joint_names")
    if not isinstance(mouth_joints, list) or len(mouth_joints) != 2:
        raise BundleError(f"expected [upper, lower] joint names, got {mouth_joints!r:.200}",
                          field="mouth_joint_names")
    for name in mouth_joints:
        if name not in joints:
            raise BundleError(f"{name!r} is not a joint ({', '.join(joints)})", field="mouth_joint_names")

    if not _is_int(m.get("sh_degree")) or not 0 <= m["sh_degree"] <= 3:
        raise BundleError(f"must be 0, 1, 2 or 3, got {m.get('sh_degree')!r}", field="sh_degree")
    if m.get("precision") not in PRECISIONS:
        raise BundleError(f"must be one of {PRECISIONS}, got {m.get('precision')!r}", field="precision")
    if m.get("raster_mode") not in RASTER_MODES:
        raise BundleError(f"must be one of {RASTER_MODES}, got {m.get('raster_mode')!r}", field="raster_mode")
    _check_camera(m.get("default_camera"))
    if not isinstance(m.get("provenance"), dict):
        raise BundleError(f"must be an object, got {m.get('provenance')!r:.100}", field="provenance")


def _names(m: dict[str, Any], key: str) -> list[str]:
    names = m.get(key)
    if not isinstance(names, list) or not all(isinstance(n, str) and n for n in names):
        raise BundleError(f"must be a list of non-empty strings, got {names!r:.200}", field=key)
    seen: set[str] = set()
    for n in names:
        if n in seen:
            raise BundleError(f"duplicate name {n!r}", field=key)
        seen.add(n)
    return names


def _check_camera(cam: Any) -> None:
    """A pinhole camera {width, height, K 3x3 (fx, fy > 0), R 3x3 rotation, t 3}, all finite."""
    field = "default_camera"
    if not isinstance(cam, dict):
        raise BundleError(f"expected {{width, height, K, R, t}}, got {cam!r:.100}", field=field)
    missing = [key for key in ("width", "height", "K", "R", "t") if key not in cam]
    if missing:
        raise BundleError(f"missing {', '.join(missing)}; expected {{width, height, K: 3x3, R: 3x3, t: 3}}",
                          field=field)
    for key in ("width", "height"):
        if not _is_int(cam[key]) or cam[key] < 1:
            raise BundleError(f"must be a positive integer, got {cam[key]!r}", field=f"{field}.{key}")
    mats = {key: _float_array(cam[key], shape, f"{field}.{key}")
            for key, shape in (("K", (3, 3)), ("R", (3, 3)), ("t", (3,)))}
    problem = calibration_problem(*(torch.from_numpy(mats[key]) for key in ("K", "R", "t")))
    if problem is not None:
        raise BundleError(problem[1], field=f"{field}.{problem[0]}")


def _float_array(value: Any, shape: tuple[int, ...], field: str) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise BundleError(f"expected numbers of shape {list(shape)}, got {value!r:.100}",
                          field=field) from None
    if a.shape != shape:
        raise BundleError(f"expected shape {list(shape)}, got {list(a.shape)}", field=field)
    if not np.isfinite(a).all():
        raise BundleError("must be finite", field=field)
    return a


def _resolve(symbols: tuple[str, ...], counts: dict[str, int], sh_degree: int) -> tuple[int, ...]:
    dims = {"N": counts["gaussians"], "K": counts["blendshapes"], "J": counts["joints"], "M": counts["mouth"],
            "C": (sh_degree + 1) ** 2, "9(J-1)": 9 * (counts["joints"] - 1)}
    return tuple(dims[s] if s in dims else int(s) for s in symbols)


def _check_precision(precision: str, version: int) -> None:
    """BundleError (field ``precision``) unless schema ``version`` stores ``precision``: int8 is schema 2's only."""
    if precision == "int8" and version < 2:
        raise BundleError(f"int8 blendshapes are stored by schema 2 and later only, not schema {version}; write "
                          "schema 2 or precision fp16", field="precision")


def _stored_dtype(name: str, precision: str) -> str:
    """Schema 1: blendshape data (deltas, correctives, eyelids) in the bundle's precision; everything else fixed."""
    if name == "mouth_group":
        return "I64"
    if name.startswith("deltas.") or name in _OPTIONAL:
        return _PRECISION_DTYPE[precision]
    return "F32"


def _expected_v1(m: dict[str, Any], table: Mapping[str, tuple[str, tuple[int, ...]]]):
    counts, sh_degree, precision = m["counts"], m["sh_degree"], m["precision"]
    return {name: (_stored_dtype(name, precision), _resolve(symbols, counts, sh_degree), "[" + ", ".join(symbols)
                   + "]") for name, symbols in _SHAPES_V1.items()}


def _expected_v2(m: dict[str, Any], table: Mapping[str, tuple[str, tuple[int, ...]]]):
    counts, c = m["counts"], (m["sh_degree"] + 1) ** 2
    n, j, mouth, k = counts["gaussians"], counts["joints"], counts["mouth"], counts["blendshapes"]
    value, quantized = _PRECISION_DTYPE[m["precision"]], m["precision"] == "int8"
    out = {
        "gaussians": ("F32", (n + mouth, packed.row_width(c)), "[N + M, 16 + ceil16(3C)]"),
        "mouth_group": ("I64", (mouth,), "[M]"),
        "lbs_weights": ("F32", (n, j), "[N, J]"),
        "joint_positions": ("F32", (j, 3), "[J, 3]"),
        "pose_correctives": (_SIDE_DTYPE[m["precision"]], (n, 3, packed.corrective_width(j)),
                             "[N, 3, ceil16(9(J-1))]"),
        "eyelid_offsets": ("F32", (n, 2, 3), "[N, 2, 3]"),
    }
    for part, length in (("geometry", packed.GEOMETRY_LENGTH), ("color", 3 * c)):
        col = table.get(f"deltas.{part}.col", ("U16", ()))[1]
        pairs = col[0] if len(col) == 1 else 0  # the pair count is the col tensor's (its own shape is checked)
        pad = packed.ceil16(length) - length
        out[f"deltas.{part}.row_ptr"] = ("I32", (n + 1,), "[N + 1]")
        out[f"deltas.{part}.col"] = ("U16", (pairs,), "[P]")
        out[f"deltas.{part}.values"] = (value, (pairs * length + pad,),
                                        f"[P * {length} + {pad}] with P = {pairs} pairs (the col tensor)")
        if quantized:
            out[f"deltas.{part}.scale"] = ("F32", (k, length + pad), f"[K, {length + pad}]")
            if part == "geometry":
                residual = pairs * packed.POSITION_COLUMNS + packed.RESIDUAL_PADDING
                out[f"deltas.{part}.position_residual"] = ("I8", (residual,),
                                                           f"[P * 3 + 13] with P = {pairs} pairs (the col tensor)")
    return out


_SCHEMAS = {1: _expected_v1, 2: _expected_v2}


def _check_tensor_table(m: dict[str, Any], table: dict[str, tuple[str, tuple[int, ...]]], version: int) -> None:
    """Check the tensors (name -> (dtype, shape)) against those of the schema ``version``, the precision, the
    counts and the manifest's ``tensors`` table."""
    precision = m["precision"]
    _check_precision(precision, version)
    expected = _SCHEMAS[version](m, table)
    for name in sorted(table):
        if name not in expected:
            raise BundleError(f"unexpected tensor; a schema-{version} bundle holds {', '.join(expected)}",
                              field=name)
    for name in expected:
        if name not in table and name not in _OPTIONAL:
            raise BundleError("missing tensor", field=name)
    for name in (n for n in expected if n in table):  # a fixed order: the Gaussians first, then deltas, ...
        dtype, shape = table[name]
        want_dtype, want, symbols = expected[name]
        if dtype != want_dtype:
            raise BundleError(f"dtype {dtype} does not match precision {precision!r} and schema {version}, which "
                              f"store {want_dtype}", field=name)
        if tuple(shape) != want:
            raise BundleError(f"expected shape {symbols} = {list(want)}, got {list(shape)}", field=name)
    listed = m.get("tensors")
    if not isinstance(listed, dict):
        raise BundleError(f"must be an object {{name: {{dtype, shape}}}}, got {listed!r:.100}",
                          field="tensors")
    actual = {name: {"dtype": dtype, "shape": list(shape)} for name, (dtype, shape) in table.items()}
    for name in sorted(set(listed) | set(actual)):
        if listed.get(name) != actual.get(name):
            raise BundleError(f"the manifest lists {name!r} as {listed.get(name)} but the file holds "
                              f"{actual.get(name)}", field="tensors")


# ---------------------------------------------------------------------------------------------- primitives


def _canonical(manifest: Mapping[str, Any]) -> bytes:
    body = {k: v for k, v in manifest.items() if k != "digest"}
    try:
        return json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=True,
                          allow_nan=False).encode("ascii")
    except ValueError as e:
        raise BundleError(f"cannot be canonicalised ({e})", field="manifest") from None


def _content_digest(manifest: Mapping[str, Any], parts: Iterable[Any]) -> str:
    """``"sha256:<hex>"`` over the domain tag, the canonical manifest and ``parts`` (buffers) in order."""
    canon = _canonical(manifest)
    h = hashlib.sha256(_DIGEST_DOMAIN)
    h.update(len(canon).to_bytes(8, "little"))
    h.update(canon)
    for part in parts:
        buf = memoryview(part).cast("B") if not isinstance(part, memoryview) else part
        for i in range(0, len(buf), _HASH_CHUNK_BYTES):
            h.update(buf[i : i + _HASH_CHUNK_BYTES])
    return f"sha256:{h.hexdigest()}"


def _as_bytes(a: np.ndarray) -> memoryview:
    """The raw little-endian bytes of a C-contiguous array, without copying."""
    a = np.ascontiguousarray(a)
    if a.dtype.byteorder == ">" or (a.dtype.byteorder == "=" and sys.byteorder == "big"):
        a = a.byteswap().view(a.dtype.newbyteorder("<"))
    return memoryview(a.reshape(-1).view(np.uint8))


def _count_nonfinite(t: Tensor) -> int:
    """How many NaN/Inf values ``t`` holds, in chunks so a huge memory-mapped tensor needs no huge mask.

    CPU tensors are scanned through numpy (no copy: ``Tensor.numpy()`` shares memory), whose isfinite is much
    faster than torch's on CPU; other devices use torch.
    """
    if not t.is_floating_point() or t.numel() == 0:
        return 0
    flat = t.detach().reshape(-1)
    use_numpy = flat.device.type == "cpu" and flat.dtype in (torch.float32, torch.float16, torch.float64)
    bad = 0
    for i in range(0, flat.numel(), _FINITE_CHUNK):
        chunk = flat[i : i + _FINITE_CHUNK]
        if use_numpy:
            finite = np.isfinite(chunk.numpy())
            if not finite.all():
                bad += int(finite.size - np.count_nonzero(finite))
        else:
            finite_t = torch.isfinite(chunk)
            if not bool(finite_t.all()):
                bad += int(chunk.numel() - finite_t.sum())
    return bad


def _is_int(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)
