"""Avatar bundles: round trips, memory mapping, and every way a file can be bad (render_core.bundle).

The container (header, offsets, digest, manifest) is the same for both schemas: those tests run on a schema-1 and a
schema-2 file. Schema-2 structure (the CSR pair tables) and v1 -> v2 conversion: tests/test_bundle_v2.py.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import replace
from pathlib import Path

import pytest
import safetensors
import safetensors.torch
import torch

from render_core import bundle, packed
from render_core.avatar import Gaussians
from render_core.bundle import (
    CURRENT_SCHEMA_VERSION,
    read_bundle,
    read_bundle_and_manifest,
    read_manifest,
    stored_schema_version,
    upgrade_manifest,
    validate_bundle,
    write_bundle,
)
from render_core.errors import BundleError
from render_core.packed import SparseDeltas
from render_core.tools.synth import synth_avatar

_DTYPE = {torch.float32: "F32", torch.float16: "F16", torch.int64: "I64", torch.int32: "I32", torch.uint16: "U16"}
SCHEMAS = [1, 2]
# A float32 tensor (the Gaussians) and the SH deltas of each schema's layout.
GAUSSIANS = {1: "neutral.means", 2: "gaussians"}
SH_DELTAS = {1: "deltas.sh", 2: "deltas.color.values"}


def _tensors(avatar) -> dict[str, torch.Tensor]:
    """The avatar's content under its schema-1 bundle names, the deltas dense whatever form the avatar holds."""
    out = {}
    for group, gaussians in (("neutral", avatar.neutral), ("deltas", avatar.dense_deltas()), ("mouth", avatar.mouth)):
        for key, t in gaussians.tensors().items():
            out[f"{group}.{key}"] = t
    out.update(mouth_group=avatar.mouth_group, lbs_weights=avatar.lbs_weights,
               joint_positions=avatar.joint_positions)
    for name in ("pose_correctives", "eyelid_offsets"):
        if getattr(avatar, name) is not None:
            out[name] = getattr(avatar, name)
    return out


def _held_tensors(avatar) -> dict[str, torch.Tensor]:
    """Every tensor the avatar holds as it holds it (sparse deltas as their pair tables)."""
    out = {f"{group}.{key}": t for group in ("neutral", "mouth") for key, t in getattr(avatar, group).tensors().items()}
    out.update({f"deltas.{key}": t for key, t in avatar.deltas.tensors().items()})
    out.update(mouth_group=avatar.mouth_group, lbs_weights=avatar.lbs_weights,
               joint_positions=avatar.joint_positions)
    for name in ("pose_correctives", "eyelid_offsets"):
        if getattr(avatar, name) is not None:
            out[name] = getattr(avatar, name)
    return out


def _pair_masks(deltas: Gaussians) -> tuple[torch.Tensor, torch.Tensor]:
    """[K, N] masks of the (blendshape, Gaussian) pairs with a non-zero geometry / SH delta (computed here from
    the dense tensors, independently of packed.py)."""
    k, n = deltas.means.shape[:2]
    geometry = torch.cat([deltas.means, deltas.quats, deltas.log_scales, deltas.opacity_logits[..., None]], -1)
    return geometry.ne(0).any(-1), deltas.sh.reshape(k, n, -1).ne(0).any(-1)


def _digest(manifest: dict, tensors: dict[str, torch.Tensor]) -> str:
    """The content digest as bundle.py documents it, computed independently here so the format is pinned:
    sha256(domain tag, u64le length of the canonical manifest, canonical manifest, tensor bytes by name)."""
    body = {k: v for k, v in manifest.items() if k != "digest"}
    canon = json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=True).encode()
    h = hashlib.sha256(b"blendsplat-avatar-digest-v1\n" + len(canon).to_bytes(8, "little") + canon)
    for name in sorted(tensors):
        h.update(tensors[name].contiguous().numpy().tobytes())
    return "sha256:" + h.hexdigest()


def _read_raw(path: Path) -> tuple[dict[str, torch.Tensor], dict]:
    """Tensors and stored manifest of a bundle, read with the safetensors library (not bundle.py)."""
    tensors = {k: v.clone() for k, v in safetensors.torch.load_file(str(path)).items()}
    with safetensors.safe_open(str(path), framework="pt") as f:
        manifest = json.loads(f.metadata()["blendsplat.manifest"])
    return tensors, manifest


def _write_raw(path: Path, tensors: dict[str, torch.Tensor], manifest: dict) -> None:
    """A hand-made bundle that bypasses write_bundle's checks, with a tensor table and digest that match."""
    manifest = dict(manifest)
    manifest["tensors"] = {k: {"dtype": _DTYPE[v.dtype], "shape": list(v.shape)} for k, v in tensors.items()}
    manifest["digest"] = _digest(manifest, tensors)
    safetensors.torch.save_file({k: v.contiguous() for k, v in tensors.items()}, str(path),
                                metadata={"blendsplat.manifest": json.dumps(manifest)})


def _header(path: Path) -> dict:
    """The safetensors header JSON of a file."""
    raw = path.read_bytes()
    return json.loads(raw[8 : 8 + int.from_bytes(raw[:8], "little")])


def _header_end(path: Path) -> int:
    """Offset of the data region: 8 + the header length."""
    return 8 + int.from_bytes(path.read_bytes()[:8], "little")


def _rewrite_header(src: Path, dst: Path, edit) -> None:
    """Copy a bundle with its safetensors header JSON passed through ``edit`` (data region unchanged)."""
    raw = src.read_bytes()
    n = int.from_bytes(raw[:8], "little")
    header = json.loads(raw[8 : 8 + n])
    edit(header)
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)
    dst.write_bytes(len(text).to_bytes(8, "little") + text + raw[8 + n :])


def _error(path: Path, **kwargs) -> BundleError:
    with pytest.raises(BundleError) as info:
        read_bundle(path, **kwargs)
    return info.value


@pytest.fixture(params=SCHEMAS, ids=["v1", "v2"])
def schema(request) -> int:
    """The schema version a test's bundle is written with (tests about one layout parametrize it directly)."""
    return request.param


@pytest.fixture
def bundle_path(avatar, tmp_path, schema) -> Path:
    """The fixture avatar written with the default precision (fp16) in schema ``schema``."""
    path = tmp_path / "head.bsplat"
    write_bundle(avatar, path, schema_version=schema)
    return path


# ------------------------------------------------------------------------------------------------ round trips


@pytest.mark.parametrize("schema", SCHEMAS, ids=["v1", "v2"])
@pytest.mark.parametrize("variant", ["fixture", "sh1-antialiased-no-optionals"])
def test_fp32_round_trip_is_bit_exact(avatar, tmp_path, variant, schema):
    if variant != "fixture":
        avatar = synth_avatar(gaussians=40, blendshapes=3, seed=5, sh_degree=1, raster_mode="antialiased")
        avatar = replace(avatar, pose_correctives=None, eyelid_offsets=None)
    path = tmp_path / "a.bsplat"
    manifest = write_bundle(avatar, path, precision="fp32", schema_version=schema)
    loaded = read_bundle(path)
    assert isinstance(loaded.deltas, SparseDeltas if schema == 2 else Gaussians)

    original, back = _tensors(avatar), _tensors(loaded)
    assert back.keys() == original.keys()
    for name, t in original.items():
        assert back[name].dtype == t.dtype, name
        assert torch.equal(back[name], t), name
    if variant != "fixture":
        assert loaded.pose_correctives is None and loaded.eyelid_offsets is None

    assert loaded.expression_names == avatar.expression_names
    assert loaded.joint_names == avatar.joint_names
    assert loaded.joint_parents == avatar.joint_parents
    assert loaded.mouth_joint_names == tuple(avatar.mouth_joint_names)
    assert loaded.sh_degree == avatar.sh_degree
    assert loaded.raster_mode == avatar.raster_mode
    assert loaded.face_model == avatar.face_model
    assert loaded.default_camera == avatar.default_camera
    created = manifest["provenance"]
    assert loaded.provenance == {**avatar.provenance, "created_at": created["created_at"],
                                 "blendsplat_version": created["blendsplat_version"]}
    assert "T" in created["created_at"]  # ISO 8601

    assert manifest["format"] == "blendsplat-avatar"
    assert manifest["schema_version"] == schema and stored_schema_version(path) == schema
    assert manifest["precision"] == "fp32"
    n, k, m = avatar.num_gaussians, avatar.num_expressions, avatar.num_mouth
    assert manifest["counts"] == {"gaussians": n, "blendshapes": k, "joints": avatar.num_joints, "mouth": m}
    c = (avatar.sh_degree + 1) ** 2
    if schema == 1:
        assert manifest["tensors"]["deltas.sh"] == {"dtype": "F32", "shape": list(avatar.deltas.sh.shape)}
    else:
        geometry, color = _pair_masks(avatar.deltas)  # synth_avatar's deltas are dense: every pair is stored
        assert int(geometry.sum()) == int(color.sum()) == n * k
        assert manifest["tensors"]["gaussians"] == {"dtype": "F32", "shape": [n + m, 16 + -(-3 * c // 16) * 16]}
        assert manifest["tensors"]["deltas.color.values"] == {
            "dtype": "F32", "shape": [n * k * 3 * c + packed.ceil16(3 * c) - 3 * c]}
        assert manifest["tensors"]["deltas.geometry.col"] == {"dtype": "U16", "shape": [n * k]}
    # Both schemas read back to the current one's manifest (the same keys; schema 1 upgraded).
    upgraded = {**manifest, "schema_version": CURRENT_SCHEMA_VERSION}
    assert read_manifest(path) == upgraded
    assert validate_bundle(path) == upgraded
    # The documented digest definition, recomputed from what the safetensors library reads back.
    raw_tensors, stored = _read_raw(path)
    assert stored == manifest
    assert manifest["digest"] == _digest(stored, raw_tensors)

    # Writing a loaded (memory-mapped) avatar again keeps the provenance and the tensors: the same file content.
    again = tmp_path / "b.bsplat"
    rewritten = write_bundle(loaded, again, precision="fp32", schema_version=schema)
    assert rewritten["provenance"] == manifest["provenance"]
    assert rewritten["digest"] == manifest["digest"]
    assert torch.equal(read_bundle(again).dense_deltas().means, avatar.deltas.means)


@pytest.mark.parametrize("explicit", [True, False], ids=["precision=fp16", "default"])
def test_fp16_round_trip_stays_fp16_within_tolerance(avatar, tmp_path, schema, explicit):
    path = tmp_path / "half.bsplat"
    manifest = write_bundle(avatar, path, **({"precision": "fp16"} if explicit else {}), schema_version=schema)
    loaded = read_bundle(path)
    assert manifest["precision"] == "fp16"  # also the default
    assert manifest["counts"] == read_manifest(path)["counts"]
    assert (loaded.num_gaussians, loaded.num_expressions, loaded.num_joints, loaded.num_mouth) == (
        avatar.num_gaussians, avatar.num_expressions, avatar.num_joints, avatar.num_mouth)

    original, back = _tensors(avatar), _tensors(loaded)
    # Blendshape data in the precision: deltas and pose correctives; eyelid offsets too in schema 1 (schema 2
    # keeps them float32).
    blendshape_data = [n for n in original if n.startswith("deltas.") or n == "pose_correctives"
                       or (n == "eyelid_offsets" and schema == 1)]
    assert len(blendshape_data) == (7 if schema == 1 else 6)
    for name, t in original.items():
        if name not in blendshape_data:  # neutral and mouth Gaussians, weights, joints: exact in fp32
            assert back[name].dtype == original[name].dtype and torch.equal(back[name], t), name
            continue
        assert back[name].dtype == torch.float16, name
        # Exactly the fp16 cast of the original, zeros included (a pair not stored is a zero delta) ...
        assert torch.equal(back[name], t.half()), name
        # ... and fp16 keeps 11 significant bits: relative error <= 2^-11, absolute <= 3e-8 in the subnormal range.
        torch.testing.assert_close(back[name].float(), t, rtol=1e-3, atol=1e-6, msg=name)
    assert loaded.precision == "fp16" and avatar.precision == "fp32"


def test_bundle_and_manifest_read_together_equal_their_separate_reads(bundle_path):
    avatar, manifest = read_bundle_and_manifest(bundle_path)
    alone = read_bundle(bundle_path)
    assert manifest == read_manifest(bundle_path) and manifest["digest"].startswith("sha256:")
    assert torch.equal(avatar.neutral.means, alone.neutral.means)
    assert avatar.expression_names == alone.expression_names


def test_loaded_tensors_are_memory_mapped_views_of_the_file(bundle_path, schema):
    """Each tensor's memory must lie inside a mapping of the bundle file itself, as listed by the kernel in
    /proc/self/maps: this holds only for zero-copy views of an mmap, never for tensors read into RAM (a copy
    lives on the heap, an anonymous mapping). The mapping is private (copy-on-write), so writing to a loaded
    tensor must leave the file unchanged."""
    maps = Path("/proc/self/maps")
    if not maps.exists():
        pytest.skip("needs /proc/self/maps (Linux)")
    avatar = read_bundle(bundle_path)
    target = os.path.realpath(bundle_path)
    regions = []
    for line in maps.read_text().splitlines():
        fields = line.split(maxsplit=5)
        if len(fields) == 6 and fields[5] == target:
            start, end = (int(x, 16) for x in fields[0].split("-"))
            regions.append((start, end))
    assert regions, "the bundle file is not mapped"
    held = _held_tensors(avatar)
    assert len(held) == (20 if schema == 1 else 21)  # v2: 10 Gaussian views, 6 pair tensors, 5 more
    for name, t in held.items():
        assert t.numel() > 0, name
        lo, hi = t.data_ptr(), t.data_ptr() + t.numel() * t.element_size()
        assert any(start <= lo and hi <= end for start, end in regions), f"{name} is a copy, not a view"

    before = bundle_path.read_bytes()
    avatar.neutral.means.add_(1.0)
    assert bundle_path.read_bytes() == before
    torch.testing.assert_close(read_bundle(bundle_path).neutral.means, avatar.neutral.means - 1.0)


# ------------------------------------------------------------------------------------------- damaged files


@pytest.mark.parametrize(
    "cut", ["0", "4", "7", "8", "100", "header_end-1", "header_end", "mid_data", "size-1"]
)
def test_truncated_file_raises_clear_error(bundle_path, tmp_path, cut):
    raw = bundle_path.read_bytes()
    end = _header_end(bundle_path)
    at = {"header_end-1": end - 1, "header_end": end, "mid_data": (end + len(raw)) // 2,
          "size-1": len(raw) - 1}.get(cut) or int(cut)
    path = tmp_path / "cut.bsplat"
    path.write_bytes(raw[:at])
    error = _error(path)
    assert "truncated" in str(error)
    with pytest.raises(BundleError, match="truncated"):
        read_manifest(path)
    if at >= end:
        assert f"file has {at - end}" in str(error) and error.field == "data"


def test_flipped_data_byte_fails_the_digest(bundle_path, schema):
    """One bit of a float value (the middle of the SH deltas, so the value stays finite and the structure
    intact): only the digest can tell."""
    raw = bytearray(bundle_path.read_bytes())
    begin, end = _header(bundle_path)[SH_DELTAS[schema]]["data_offsets"]
    raw[_header_end(bundle_path) + (begin + end) // 2 // 2 * 2] ^= 0x01  # the low byte of an fp16 value
    bundle_path.write_bytes(bytes(raw))
    error = _error(bundle_path)
    assert error.field == "digest" and "digest mismatch" in str(error)
    read_bundle(bundle_path, verify=False)  # the check is what verify turns on


def test_edited_manifest_fails_the_digest(bundle_path):
    raw = bundle_path.read_bytes()
    end = _header_end(bundle_path)
    assert raw[:end].count(b"exp_02") == 1
    bundle_path.write_bytes(raw[:end].replace(b"exp_02", b"exp_2X") + raw[end:])  # same length, valid JSON
    assert "exp_2X" in read_manifest(bundle_path)["expression_names"]
    error = _error(bundle_path)
    assert error.field == "digest" and "modified or corrupted" in str(error)


def test_swapped_tensor_offsets_fail_the_digest(avatar, tmp_path, schema):
    """Two equal-sized tensors swapping places keep the data region's bytes but not their meaning. Schema 2: the
    two row_ptr tables, which differ once Gaussian 0 has no SH deltas."""
    if schema == 1:
        a, b = "neutral.means", "neutral.log_scales"
    else:
        a, b = "deltas.geometry.row_ptr", "deltas.color.row_ptr"
        sh = avatar.deltas.sh.clone()
        sh[:, 0] = 0.0
        avatar = replace(avatar, deltas=replace(avatar.deltas, sh=sh))
    src = tmp_path / "head.bsplat"
    write_bundle(avatar, src, schema_version=schema)
    tensors, _ = _read_raw(src)
    assert tensors[a].shape == tensors[b].shape and not torch.equal(tensors[a], tensors[b])

    def swap(header):
        header[a]["data_offsets"], header[b]["data_offsets"] = header[b]["data_offsets"], header[a]["data_offsets"]

    path = tmp_path / "swapped.bsplat"
    _rewrite_header(src, path, swap)
    assert _error(path).field == "digest"


def _shift_last_tensor(header, name):
    last = max((v for k, v in header.items() if k != "__metadata__"), key=lambda v: v["data_offsets"][1])
    last["data_offsets"] = [o + 8 for o in last["data_offsets"]]


def _overlap_first(header, name):
    """``name`` resized to 6 float32 values placed at offset 0, over the first tensor."""
    assert header[name]["dtype"] == "F32" and header[name]["data_offsets"][0] > 0
    header[name].update(shape=[2, 3], data_offsets=[0, 24])


@pytest.mark.parametrize(
    "edit, field, text",
    [
        (lambda h, name: h[name].update(dtype="F64"), "name", "not allowed"),
        (lambda h, name: h[name].update(data_offsets=[0, 4]), "name", "needs"),
        (_shift_last_tensor, None, "a gap of 8 bytes"),
        (_overlap_first, None, "overlap"),
        (lambda h, name: h[name].update(data_offsets=[8, 4]), "name", "begin <= end"),
        (lambda h, name: h.pop("__metadata__"), "manifest", "__metadata__"),
    ],
    ids=["dtype", "length", "gap", "overlap", "reversed", "no-metadata"],
)
def test_malformed_header_is_rejected(bundle_path, tmp_path, schema, edit, field, text):
    name = {1: "neutral.means", 2: "joint_positions"}[schema]  # a float32 tensor that does not start the data
    path = tmp_path / "bad.bsplat"
    _rewrite_header(bundle_path, path, lambda h: edit(h, name))
    error = _error(path)
    assert text in str(error)
    if field:
        assert error.field == (name if field == "name" else field)
    with pytest.raises(BundleError, match=text):
        read_manifest(path)


def test_trailing_bytes_are_rejected(bundle_path):
    bundle_path.write_bytes(bundle_path.read_bytes() + b"\0" * 16)
    error = _error(bundle_path)
    assert error.field == "data" and "16 unexpected bytes" in str(error)


@pytest.mark.parametrize("content", ["random", "json", "empty", "plain-safetensors", "directory", "missing"])
def test_not_a_bundle(tmp_path, content):
    path = tmp_path / "x.bsplat"
    if content == "random":
        path.write_bytes(torch.randint(0, 256, (4096,), dtype=torch.uint8).numpy().tobytes())
    elif content == "json":
        path.write_text(json.dumps({"format": "blendsplat-avatar", "schema_version": 1}))
    elif content == "empty":
        path.write_bytes(b"")
    elif content == "plain-safetensors":
        safetensors.torch.save_file({"x": torch.zeros(3)}, str(path))
    elif content == "directory":
        path.mkdir()
    error = _error(path)
    assert error.field in {"header", "manifest", "path"}
    expected = {"random": "not a bundle", "json": "not a bundle", "empty": "empty",
                "plain-safetensors": "__metadata__", "directory": "not a file", "missing": "no such file"}
    assert expected[content] in str(error)


def test_header_that_is_not_json(bundle_path):
    raw = bytearray(bundle_path.read_bytes())
    raw[8] = ord("[")  # '{' -> '[' : no longer a JSON document
    bundle_path.write_bytes(bytes(raw))
    error = _error(bundle_path)
    assert error.field == "header" and "not JSON" in str(error)


# ------------------------------------------------------------------------------------ content and manifest


def test_wrong_format_is_rejected(bundle_path, tmp_path):
    tensors, manifest = _read_raw(bundle_path)
    path = tmp_path / "other.bsplat"
    _write_raw(path, tensors, {**manifest, "format": "gaussian-splat"})
    error = _error(path)
    assert error.field == "format" and "gaussian-splat" in str(error)


@pytest.mark.parametrize("schema, name", [(1, "deltas.means"), (2, "gaussians"), (2, "deltas.geometry.values")])
def test_wrong_shape_names_the_tensor(avatar, bundle_path, tmp_path, schema, name):
    n, k, m, c = avatar.num_gaussians, avatar.num_expressions, avatar.num_mouth, (avatar.sh_degree + 1) ** 2
    tensors, manifest = _read_raw(bundle_path)
    cut = {"deltas.means": lambda t: t[..., :2], "gaussians": lambda t: t[:, :-16],
           "deltas.geometry.values": lambda t: t[:-1]}[name]
    tensors[name] = cut(tensors[name]).contiguous()
    path = tmp_path / "shape.bsplat"
    _write_raw(path, tensors, manifest)
    r = 16 + packed.ceil16(3 * c)
    expected = {
        "deltas.means": f"[K, N, 3] = [{k}, {n}, 3], got [{k}, {n}, 2]",
        "gaussians": f"[N + M, 16 + ceil16(3C)] = [{n + m}, {r}], got [{n + m}, {r - 16}]",
        "deltas.geometry.values": f"[P * 11 + 5] with P = {n * k} pairs (the col tensor) = [{n * k * 11 + 5}], "
                                  f"got [{n * k * 11 + 4}]",
    }[name]
    for call in (read_bundle, read_manifest):
        with pytest.raises(BundleError) as info:
            call(path)
        assert info.value.field == name
        assert expected in str(info.value)


_BAD_TENSORS_V1 = [
    ("missing", lambda t: t.pop("lbs_weights"), "lbs_weights"),
    ("unexpected", lambda t: t.update(extra=torch.zeros(3)), "extra"),
    ("v2-name", lambda t: t.update(gaussians=torch.zeros(3, 64)), "gaussians"),
    ("lbs-joints", lambda t: t.update(lbs_weights=t["lbs_weights"][:, :-1].contiguous()), "lbs_weights"),
    ("correctives", lambda t: t.update(pose_correctives=t["pose_correctives"][:9].contiguous()), "pose_correctives"),
    ("eyelids", lambda t: t.update(eyelid_offsets=t["eyelid_offsets"][:1].contiguous()), "eyelid_offsets"),
    ("int32", lambda t: t.update(mouth_group=t["mouth_group"].int()), "mouth_group"),
    ("sh-coeffs", lambda t: t.update({"neutral.sh": t["neutral.sh"][:, :4].contiguous()}), "neutral.sh"),
    ("mixed-precision", lambda t: t.update({"mouth.quats": t["mouth.quats"].half()}), "mouth.quats"),
    ("deltas-fp32", lambda t: t.update({"deltas.sh": t["deltas.sh"].float()}), "deltas.sh"),
    ("mouth-group-values", lambda t: t.update(mouth_group=t["mouth_group"] * 2), "mouth_group"),  # validate()
]
_BAD_TENSORS_V2 = [
    ("missing", lambda t: t.pop("lbs_weights"), "lbs_weights"),
    ("missing-gaussians", lambda t: t.pop("gaussians"), "gaussians"),
    ("missing-col", lambda t: t.pop("deltas.color.col"), "deltas.color.col"),
    ("unexpected", lambda t: t.update(extra=torch.zeros(3)), "extra"),
    ("v1-name", lambda t: t.update({"neutral.means": torch.zeros(600, 3)}), "neutral.means"),
    ("lbs-joints", lambda t: t.update(lbs_weights=t["lbs_weights"][:, :-1].contiguous()), "lbs_weights"),
    ("correctives", lambda t: t.update(pose_correctives=t["pose_correctives"][..., :32].contiguous()),
     "pose_correctives"),
    ("correctives-v1-layout", lambda t: t.update(pose_correctives=torch.zeros(36, 600, 3).half()),
     "pose_correctives"),
    ("eyelids", lambda t: t.update(eyelid_offsets=t["eyelid_offsets"][:, :1].contiguous()), "eyelid_offsets"),
    ("eyelids-fp16", lambda t: t.update(eyelid_offsets=t["eyelid_offsets"].half()), "eyelid_offsets"),
    ("int32", lambda t: t.update(mouth_group=t["mouth_group"].int()), "mouth_group"),
    ("sh-width", lambda t: t.update(gaussians=t["gaussians"][:, :32].contiguous()), "gaussians"),
    ("mixed-precision", lambda t: t.update(gaussians=t["gaussians"].half()), "gaussians"),
    ("values-fp32", lambda t: t.update({"deltas.color.values": t["deltas.color.values"].float()}),
     "deltas.color.values"),
    ("correctives-fp32", lambda t: t.update(pose_correctives=t["pose_correctives"].float()), "pose_correctives"),
    ("mouth-group-values", lambda t: t.update(mouth_group=t["mouth_group"] * 2), "mouth_group"),  # validate()
]


@pytest.mark.parametrize(
    "schema, change, field",
    [pytest.param(1, change, field, id=f"v1-{name}") for name, change, field in _BAD_TENSORS_V1]
    + [pytest.param(2, change, field, id=f"v2-{name}") for name, change, field in _BAD_TENSORS_V2],
)
def test_bad_tensor_names_it(bundle_path, tmp_path, schema, change, field):
    tensors, manifest = _read_raw(bundle_path)
    change(tensors)
    path = tmp_path / "bad.bsplat"
    _write_raw(path, tensors, manifest)
    assert _error(path).field == field
    assert _error(path, verify=False).field == field  # shapes, dtypes and the avatar's invariants: always checked


def _camera_without_k(m):
    m["default_camera"] = {k: v for k, v in m["default_camera"].items() if k != "K"}


@pytest.mark.parametrize(
    "edit, field",
    [
        (lambda m: m["expression_names"].pop(), "expression_names"),
        (lambda m: m["expression_names"].__setitem__(1, m["expression_names"][0]), "expression_names"),
        (lambda m: m["joint_names"].__setitem__(4, "eye_l"), "joint_names"),
        (lambda m: m.update(joint_parents=[-1, 0, 1, 1, 4]), "joint_parents"),
        (lambda m: m.update(joint_parents=[-1, 0, -1, 1, 1]), "joint_parents"),
        (lambda m: m.update(mouth_joint_names=["neck", "chin"]), "mouth_joint_names"),
        (lambda m: m.update(precision="bf16"), "precision"),
        (lambda m: m.update(precision="fp32"), {1: "deltas.means", 2: "pose_correctives"}),  # stored fp16
        (lambda m: m.update(raster_mode="fancy"), "raster_mode"),
        (lambda m: m.update(sh_degree=4), "sh_degree"),
        (lambda m: m.update(sh_degree=2), {1: "neutral.sh", 2: "gaussians"}),
        (lambda m: m["counts"].update(gaussians=7), {1: "neutral.means", 2: "gaussians"}),
        (lambda m: m["counts"].update(blendshapes=5), "expression_names"),
        (lambda m: m.update(face_model=""), "face_model"),
        (_camera_without_k, "default_camera"),
        (lambda m: m["default_camera"].update(K=[[1, 0, 0], [0, 1, 0]]), "default_camera.K"),
        (lambda m: m["default_camera"].update(R=[[2, 0, 0], [0, 1, 0], [0, 0, 1]]), "default_camera.R"),
        (lambda m: m["default_camera"].update(width=0), "default_camera.width"),
        (lambda m: m.update(provenance="trained"), "provenance"),
    ],
    ids=["names-length", "names-duplicate", "joint-duplicate", "parent-order", "two-roots", "mouth-joint",
         "precision", "precision-mismatch", "raster", "sh", "sh-mismatch", "counts", "counts-blendshapes",
         "face-model", "camera-keys", "camera-K", "camera-R", "camera-width", "provenance"],
)
def test_bad_manifest_field_names_it(bundle_path, tmp_path, schema, edit, field):
    tensors, manifest = _read_raw(bundle_path)
    edit(manifest)
    path = tmp_path / "bad.bsplat"
    _write_raw(path, tensors, manifest)
    assert _error(path).field == (field[schema] if isinstance(field, dict) else field)
    with pytest.raises(BundleError):
        read_manifest(path)


def test_nan_tensor_is_rejected_on_read(bundle_path, tmp_path, schema):
    name = SH_DELTAS[schema]
    tensors, manifest = _read_raw(bundle_path)
    flat = tensors[name].view(-1)  # a view: writes go to the tensor
    flat[100] = float("nan")
    flat[1001] = float("inf")
    path = tmp_path / "nan.bsplat"
    _write_raw(path, tensors, manifest)
    error = _error(path)
    assert error.field == name and "2 of" in str(error) and "non-finite" in str(error)
    loaded = read_bundle(path, verify=False)  # verify=False skips the scan
    assert _held_tensors(loaded)[name].isnan().sum() == 1


def test_write_refuses_non_finite_avatar(avatar, tmp_path, schema):
    bad = replace(avatar, deltas=avatar.deltas.map(torch.clone))
    bad.deltas.sh[1, 2, 0, 0] = float("nan")
    fresh = tmp_path / "fresh.bsplat"
    with pytest.raises(BundleError) as info:
        write_bundle(bad, fresh, schema_version=schema)
    assert info.value.field == "deltas.sh" and "non-finite" in str(info.value)
    assert os.listdir(tmp_path) == []

    existing = tmp_path / "existing.bsplat"
    write_bundle(avatar, existing, schema_version=schema)
    before = existing.read_bytes()
    with pytest.raises(BundleError):
        write_bundle(bad, existing, schema_version=schema)
    assert existing.read_bytes() == before and os.listdir(tmp_path) == ["existing.bsplat"]


def test_write_refuses_fp16_overflow_and_invalid_avatars(avatar, tmp_path, schema):
    big = replace(avatar, deltas=avatar.deltas.map(torch.clone))
    big.deltas.sh[0, 0, 0, 0] = 1e6
    with pytest.raises(BundleError, match="overflow") as info:
        write_bundle(big, tmp_path / "a.bsplat", precision="fp16", schema_version=schema)
    assert info.value.field == "deltas.sh"
    with pytest.raises(BundleError, match="overflow"):  # fp16 is the default
        write_bundle(big, tmp_path / "a.bsplat", schema_version=schema)
    assert not (tmp_path / "a.bsplat").exists()
    write_bundle(big, tmp_path / "a.bsplat", precision="fp32", schema_version=schema)  # fine in fp32
    assert float(read_bundle(tmp_path / "a.bsplat").dense_deltas().sh[0, 0, 0, 0]) == 1e6

    with pytest.raises(BundleError) as info:
        write_bundle(replace(avatar, expression_names=avatar.expression_names[:-1]), tmp_path / "b.bsplat",
                     schema_version=schema)
    assert info.value.field == "expression_names"
    with pytest.raises(BundleError) as info:
        write_bundle(replace(avatar, default_camera={}), tmp_path / "b.bsplat", schema_version=schema)
    assert info.value.field == "default_camera"
    with pytest.raises(BundleError) as info:
        write_bundle(avatar, tmp_path / "b.bsplat", precision="bf16", schema_version=schema)  # type: ignore[arg-type]
    assert info.value.field == "precision"
    assert not (tmp_path / "b.bsplat").exists()


def test_atomic_write_keeps_the_previous_file_when_writing_fails(avatar, tmp_path, monkeypatch):
    path = tmp_path / "head.bsplat"
    write_bundle(avatar, path)
    before = path.read_bytes()

    def crash(arrays, tmp, metadata):
        Path(tmp).write_bytes(b"half a bundle")  # what a crash mid-write leaves in the temp file
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(bundle, "_serialize", crash)
    with pytest.raises(OSError, match="No space"):
        write_bundle(replace(avatar, face_model="other"), path)
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["head.bsplat"]
    monkeypatch.undo()

    write_bundle(replace(avatar, face_model="other"), path)  # a successful overwrite replaces it whole
    assert read_bundle(path).face_model == "other"
    assert os.listdir(tmp_path) == ["head.bsplat"]


# ----------------------------------------------------------------------------------------- schema versions


def test_schema_2_is_current_and_written_by_default(avatar, tmp_path):
    assert CURRENT_SCHEMA_VERSION == 2 and 1 in bundle.UPGRADERS
    path = tmp_path / "default.bsplat"
    manifest = write_bundle(avatar, path)
    assert (manifest["schema_version"], manifest["precision"]) == (2, "fp16")
    assert stored_schema_version(path) == 2 and "gaussians" in manifest["tensors"]
    assert isinstance(read_bundle(path).deltas, SparseDeltas)


def test_future_schema_version_is_refused(avatar, bundle_path, tmp_path, schema):
    tensors, manifest = _read_raw(bundle_path)
    path = tmp_path / "future.bsplat"
    _write_raw(path, tensors, {**manifest, "schema_version": 3})  # a valid digest: the version alone is refused
    for call in (read_bundle, read_manifest, validate_bundle, stored_schema_version):
        with pytest.raises(BundleError) as info:
            call(path)
        assert info.value.field == "schema_version"
        assert "schema_version 3 is newer than this build reads (1, 2)" in str(info.value)
    with pytest.raises(BundleError) as info:
        write_bundle(avatar, tmp_path / "w.bsplat", schema_version=3)
    assert info.value.field == "schema_version" and not (tmp_path / "w.bsplat").exists()


@pytest.mark.parametrize("precision", ["fp32", "fp16"])
def test_schema_1_file_loads_with_dense_deltas(avatar, tmp_path, precision):
    path = tmp_path / "v1.bsplat"
    stored = write_bundle(avatar, path, precision, schema_version=1)
    assert stored["schema_version"] == 1 and "neutral.means" in stored["tensors"]
    loaded, manifest = read_bundle_and_manifest(path)
    assert manifest == {**stored, "schema_version": 2}  # upgraded; the digest is the stored manifest's
    assert stored_schema_version(path) == 1
    assert isinstance(loaded.deltas, Gaussians) and loaded.precision == precision
    dtype = torch.float16 if precision == "fp16" else torch.float32
    for key, t in avatar.deltas.tensors().items():
        assert torch.equal(getattr(loaded.deltas, key), t.to(dtype)), key


def test_older_schema_version_loads_through_an_upgrader(avatar, tmp_path, monkeypatch):
    # A schema-1 file from a past where the face-model field was called "model".
    v1 = tmp_path / "v1.bsplat"
    write_bundle(avatar, v1, schema_version=1)
    tensors, manifest = _read_raw(v1)
    manifest["model"] = manifest.pop("face_model")
    path = tmp_path / "old.bsplat"
    _write_raw(path, tensors, manifest)
    assert _error(path).field == "face_model"  # this build's upgrader from 1 does not know the old name

    monkeypatch.delitem(bundle.UPGRADERS, 1)
    with pytest.raises(BundleError, match=r"schema_version 1 cannot be read: no upgrader from 1 to 2 \(this build "
                                          r"reads 2\)") as info:
        read_bundle(path)
    assert info.value.field == "schema_version"

    calls = []

    def rename(m: dict) -> dict:
        calls.append(m["schema_version"])
        m["face_model"] = m.pop("model")
        return m

    monkeypatch.setitem(bundle.UPGRADERS, 1, rename)
    loaded = read_bundle(path)  # the digest still verifies: it covers the manifest as stored (v1)
    assert loaded.face_model == avatar.face_model and calls == [1]
    assert isinstance(loaded.deltas, Gaussians)  # the tensors are read in the stored (v1) layout
    upgraded = read_manifest(path)
    assert upgraded["schema_version"] == 2 and "model" not in upgraded
    assert upgrade_manifest({"schema_version": 2}) == {"schema_version": 2}

    # A chain to a schema 3: a v1 file goes through 1 -> 2 -> 3, a v2 file through 2 -> 3, each still read in
    # the layout it was stored in.
    def tag(m: dict) -> dict:
        calls.append(m["schema_version"])
        m["provenance"] = {**m["provenance"], "upgraded": True}
        return m

    v2 = tmp_path / "v2.bsplat"
    write_bundle(avatar, v2)
    monkeypatch.setattr(bundle, "CURRENT_SCHEMA_VERSION", 3)
    monkeypatch.setitem(bundle.UPGRADERS, 2, tag)
    calls.clear()
    assert read_bundle(path).provenance["upgraded"] and calls == [1, 2]
    calls.clear()
    loaded = read_bundle(v2)
    assert loaded.provenance["upgraded"] and calls == [2] and isinstance(loaded.deltas, SparseDeltas)
    assert read_manifest(v2)["schema_version"] == 3 and stored_schema_version(v2) == 2

    def broken(m: dict) -> dict:
        raise KeyError("counts")

    monkeypatch.setitem(bundle.UPGRADERS, 2, broken)
    with pytest.raises(BundleError, match="upgrading from 2 to 3 failed: KeyError") as info:
        read_bundle(v2)
    assert info.value.field == "schema_version"


def test_upgrade_manifest_rejects_bad_versions():
    for bad in (None, "1", 0, True):
        with pytest.raises(BundleError) as info:
            upgrade_manifest({} if bad is None else {"schema_version": bad})
        assert info.value.field == "schema_version"
    assert upgrade_manifest({"schema_version": 1}) == {"schema_version": 2}


# --------------------------------------------------------------------------------------------- read_manifest


def test_read_manifest_reads_only_the_header(bundle_path, monkeypatch):
    # Corrupt the tensor data: read_manifest must not notice, because it never maps or hashes the data.
    raw = bytearray(bundle_path.read_bytes())
    raw[-3] ^= 0xFF
    bundle_path.write_bytes(bytes(raw))

    def no_mmap(*args, **kwargs):
        raise AssertionError("read_manifest mapped the tensor data")

    monkeypatch.setattr(bundle.mmap, "mmap", no_mmap)
    manifest = read_manifest(bundle_path)
    assert manifest["expression_names"] == [f"exp_{i:02d}" for i in range(6)]
    assert manifest["joint_names"] == ["root", "neck", "jaw", "eye_l", "eye_r"]
    assert manifest["counts"]["gaussians"] == 600
    monkeypatch.undo()
    assert _error(bundle_path).field == "digest"


def test_written_bundles_are_readable_by_other_processes(avatar, tmp_path, schema):
    path = tmp_path / "shared.bundle"
    write_bundle(avatar, path, schema_version=schema)
    assert path.stat().st_mode & 0o777 == 0o644
