"""Avatar bundles: round trips, memory mapping, and every way a file can be bad (render_core.bundle)."""

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

from render_core import bundle
from render_core.bundle import (
    CURRENT_SCHEMA_VERSION,
    read_bundle,
    read_bundle_and_manifest,
    read_manifest,
    upgrade_manifest,
    validate_bundle,
    write_bundle,
)
from render_core.errors import BundleError
from render_core.tools.synth import synth_avatar

_DTYPE = {torch.float32: "F32", torch.float16: "F16", torch.int64: "I64", torch.int32: "I32"}


def _tensors(avatar) -> dict[str, torch.Tensor]:
    """The avatar's tensors under their bundle names."""
    out = {}
    for group in ("neutral", "deltas", "mouth"):
        for key, t in getattr(avatar, group).tensors().items():
            out[f"{group}.{key}"] = t
    out.update(mouth_group=avatar.mouth_group, lbs_weights=avatar.lbs_weights,
               joint_positions=avatar.joint_positions)
    for name in ("pose_correctives", "eyelid_offsets"):
        if getattr(avatar, name) is not None:
            out[name] = getattr(avatar, name)
    return out


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


@pytest.fixture
def bundle_path(avatar, tmp_path) -> Path:
    path = tmp_path / "head.bsplat"
    write_bundle(avatar, path)
    return path


# ------------------------------------------------------------------------------------------------ round trips


@pytest.mark.parametrize("variant", ["fixture", "sh1-antialiased-no-optionals"])
def test_fp32_round_trip_is_bit_exact(avatar, tmp_path, variant):
    if variant != "fixture":
        avatar = synth_avatar(gaussians=40, blendshapes=3, seed=5, sh_degree=1, raster_mode="antialiased")
        avatar = replace(avatar, pose_correctives=None, eyelid_offsets=None)
    path = tmp_path / "a.bsplat"
    manifest = write_bundle(avatar, path)
    loaded = read_bundle(path)

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
    assert manifest["schema_version"] == CURRENT_SCHEMA_VERSION
    assert manifest["precision"] == "fp32"
    assert manifest["counts"] == {"gaussians": avatar.num_gaussians, "blendshapes": avatar.num_expressions,
                                  "joints": avatar.num_joints, "mouth": avatar.num_mouth}
    assert manifest["tensors"]["deltas.sh"] == {"dtype": "F32", "shape": list(avatar.deltas.sh.shape)}
    assert read_manifest(path) == manifest
    assert validate_bundle(path) == manifest
    # The documented digest definition, recomputed from what the safetensors library reads back.
    raw_tensors, stored = _read_raw(path)
    assert stored == manifest
    assert manifest["digest"] == _digest(stored, raw_tensors)

    # Writing a loaded (memory-mapped) avatar again keeps the provenance and the tensors.
    again = tmp_path / "b.bsplat"
    assert write_bundle(loaded, again)["provenance"] == manifest["provenance"]
    assert torch.equal(read_bundle(again).deltas.means, avatar.deltas.means)


def test_fp16_round_trip_stays_fp16_within_tolerance(avatar, tmp_path):
    path = tmp_path / "half.bsplat"
    manifest = write_bundle(avatar, path, precision="fp16")
    loaded = read_bundle(path)
    assert manifest["precision"] == "fp16"
    assert manifest["counts"] == read_manifest(path)["counts"]
    assert (loaded.num_gaussians, loaded.num_expressions, loaded.num_joints, loaded.num_mouth) == (
        avatar.num_gaussians, avatar.num_expressions, avatar.num_joints, avatar.num_mouth)

    original, back = _tensors(avatar), _tensors(loaded)
    blendshape_data = [n for n in original if n.startswith("deltas.") or n in ("pose_correctives", "eyelid_offsets")]
    assert len(blendshape_data) == 7
    for name, t in original.items():
        if name not in blendshape_data:  # neutral and mouth Gaussians, weights, joints: exact in fp32
            assert back[name].dtype == original[name].dtype and torch.equal(back[name], t), name
            continue
        assert back[name].dtype == torch.float16, name
        # fp16 keeps 11 significant bits: relative error <= 2^-11, absolute <= 3e-8 in the subnormal range.
        torch.testing.assert_close(back[name].float(), t, rtol=1e-3, atol=1e-6, msg=name)
    assert loaded.precision == "fp16" and avatar.precision == "fp32"


def test_bundle_and_manifest_read_together_equal_their_separate_reads(bundle_path):
    avatar, manifest = read_bundle_and_manifest(bundle_path)
    alone = read_bundle(bundle_path)
    assert manifest == read_manifest(bundle_path) and manifest["digest"].startswith("sha256:")
    assert torch.equal(avatar.neutral.means, alone.neutral.means)
    assert avatar.expression_names == alone.expression_names


def test_loaded_tensors_are_memory_mapped_views_of_the_file(bundle_path):
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
    for name, t in _tensors(avatar).items():
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


def test_flipped_data_byte_fails_the_digest(bundle_path):
    raw = bytearray(bundle_path.read_bytes())
    end = _header_end(bundle_path)
    raw[(end + len(raw)) // 2] ^= 0x01
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


def test_swapped_tensor_offsets_fail_the_digest(bundle_path, tmp_path):
    """Two equal-sized tensors swapping places keep the data region's bytes but not their meaning."""

    def swap(header):
        a, b = header["neutral.means"], header["neutral.log_scales"]
        a["data_offsets"], b["data_offsets"] = b["data_offsets"], a["data_offsets"]

    path = tmp_path / "swapped.bsplat"
    _rewrite_header(bundle_path, path, swap)
    assert _error(path).field == "digest"


def _shift_last_tensor(header):
    last = max((v for k, v in header.items() if k != "__metadata__"), key=lambda v: v["data_offsets"][1])
    last["data_offsets"] = [o + 8 for o in last["data_offsets"]]


@pytest.mark.parametrize(
    "edit, field, text",
    [
        (lambda h: h["neutral.sh"].update(dtype="F64"), "neutral.sh", "not allowed"),
        (lambda h: h["neutral.means"].update(data_offsets=[0, 4]), "neutral.means", "needs"),
        (_shift_last_tensor, None, "a gap of 8 bytes"),
        (lambda h: h["neutral.means"].update(shape=[2, 3], data_offsets=[0, 24]), None, "overlap"),
        (lambda h: h["neutral.means"].update(data_offsets=[8, 4]), "neutral.means", "begin <= end"),
        (lambda h: h.pop("__metadata__"), "manifest", "__metadata__"),
    ],
    ids=["dtype", "length", "gap", "overlap", "reversed", "no-metadata"],
)
def test_malformed_header_is_rejected(bundle_path, tmp_path, edit, field, text):
    path = tmp_path / "bad.bsplat"
    _rewrite_header(bundle_path, path, edit)
    error = _error(path)
    assert text in str(error)
    if field:
        assert error.field == field


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


def test_wrong_shape_names_the_tensor(avatar, bundle_path, tmp_path):
    tensors, manifest = _read_raw(bundle_path)
    tensors["deltas.means"] = tensors["deltas.means"][..., :2].contiguous()
    path = tmp_path / "shape.bsplat"
    _write_raw(path, tensors, manifest)
    k, n = avatar.num_expressions, avatar.num_gaussians
    for call in (read_bundle, read_manifest):
        with pytest.raises(BundleError) as info:
            call(path)
        assert info.value.field == "deltas.means"
        assert f"[K, N, 3] = [{k}, {n}, 3], got [{k}, {n}, 2]" in str(info.value)


@pytest.mark.parametrize(
    "change, field",
    [
        (lambda t: t.pop("lbs_weights"), "lbs_weights"),
        (lambda t: t.update(extra=torch.zeros(3)), "extra"),
        (lambda t: t.update(lbs_weights=t["lbs_weights"][:, :-1].contiguous()), "lbs_weights"),
        (lambda t: t.update(pose_correctives=t["pose_correctives"][:9].contiguous()), "pose_correctives"),
        (lambda t: t.update(eyelid_offsets=t["eyelid_offsets"][:1].contiguous()), "eyelid_offsets"),
        (lambda t: t.update(mouth_group=t["mouth_group"].int()), "mouth_group"),
        (lambda t: t.update({"neutral.sh": t["neutral.sh"][:, :4].contiguous()}), "neutral.sh"),
        (lambda t: t.update({"mouth.quats": t["mouth.quats"].half()}), "mouth.quats"),
        (lambda t: t.update(mouth_group=t["mouth_group"] * 2), "mouth_group"),  # avatar.validate()
    ],
    ids=["missing", "unexpected", "lbs-joints", "correctives", "eyelids", "int32", "sh-coeffs",
         "mixed-precision", "mouth-group-values"],
)
def test_bad_tensor_names_it(bundle_path, tmp_path, change, field):
    tensors, manifest = _read_raw(bundle_path)
    change(tensors)
    path = tmp_path / "bad.bsplat"
    _write_raw(path, tensors, manifest)
    assert _error(path).field == field


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
        (lambda m: m.update(raster_mode="fancy"), "raster_mode"),
        (lambda m: m.update(sh_degree=4), "sh_degree"),
        (lambda m: m["counts"].update(gaussians=7), "neutral.means"),
        (lambda m: m.update(face_model=""), "face_model"),
        (_camera_without_k, "default_camera"),
        (lambda m: m["default_camera"].update(K=[[1, 0, 0], [0, 1, 0]]), "default_camera.K"),
        (lambda m: m["default_camera"].update(R=[[2, 0, 0], [0, 1, 0], [0, 0, 1]]), "default_camera.R"),
        (lambda m: m["default_camera"].update(width=0), "default_camera.width"),
        (lambda m: m.update(provenance="trained"), "provenance"),
    ],
    ids=["names-length", "names-duplicate", "joint-duplicate", "parent-order", "two-roots", "mouth-joint",
         "precision", "raster", "sh", "counts", "face-model", "camera-keys", "camera-K", "camera-R",
         "camera-width", "provenance"],
)
def test_bad_manifest_field_names_it(bundle_path, tmp_path, edit, field):
    tensors, manifest = _read_raw(bundle_path)
    edit(manifest)
    path = tmp_path / "bad.bsplat"
    _write_raw(path, tensors, manifest)
    assert _error(path).field == field
    with pytest.raises(BundleError):
        read_manifest(path)


def test_nan_tensor_is_rejected_on_read(bundle_path, tmp_path):
    tensors, manifest = _read_raw(bundle_path)
    tensors["deltas.sh"][1, 2, 0, 0] = float("nan")
    tensors["deltas.sh"][3, 4, 1, 2] = float("inf")
    path = tmp_path / "nan.bsplat"
    _write_raw(path, tensors, manifest)
    error = _error(path)
    assert error.field == "deltas.sh" and "2 of" in str(error) and "non-finite" in str(error)
    assert read_bundle(path, verify=False).deltas.sh.isnan().sum() == 1  # verify=False skips the scan


def test_write_refuses_non_finite_avatar(avatar, tmp_path):
    bad = replace(avatar, deltas=avatar.deltas.map(torch.clone))
    bad.deltas.sh[1, 2, 0, 0] = float("nan")
    fresh = tmp_path / "fresh.bsplat"
    with pytest.raises(BundleError) as info:
        write_bundle(bad, fresh)
    assert info.value.field == "deltas.sh" and "non-finite" in str(info.value)
    assert os.listdir(tmp_path) == []

    existing = tmp_path / "existing.bsplat"
    write_bundle(avatar, existing)
    before = existing.read_bytes()
    with pytest.raises(BundleError):
        write_bundle(bad, existing)
    assert existing.read_bytes() == before and os.listdir(tmp_path) == ["existing.bsplat"]


def test_write_refuses_fp16_overflow_and_invalid_avatars(avatar, tmp_path):
    big = replace(avatar, deltas=avatar.deltas.map(torch.clone))
    big.deltas.sh[0, 0, 0, 0] = 1e6
    with pytest.raises(BundleError, match="overflow") as info:
        write_bundle(big, tmp_path / "a.bsplat", precision="fp16")
    assert info.value.field == "deltas.sh"
    write_bundle(big, tmp_path / "a.bsplat")  # fine in fp32

    with pytest.raises(BundleError) as info:
        write_bundle(replace(avatar, expression_names=avatar.expression_names[:-1]), tmp_path / "b.bsplat")
    assert info.value.field == "expression_names"
    with pytest.raises(BundleError) as info:
        write_bundle(replace(avatar, default_camera={}), tmp_path / "b.bsplat")
    assert info.value.field == "default_camera"
    with pytest.raises(BundleError) as info:
        write_bundle(avatar, tmp_path / "b.bsplat", precision="int8")  # type: ignore[arg-type]
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


def test_future_schema_version_is_refused(avatar, tmp_path, monkeypatch):
    path = tmp_path / "future.bsplat"
    with monkeypatch.context() as m:
        m.setattr(bundle, "CURRENT_SCHEMA_VERSION", 7)
        assert write_bundle(avatar, path)["schema_version"] == 7
    for call in (read_bundle, read_manifest):
        with pytest.raises(BundleError) as info:
            call(path)
        assert info.value.field == "schema_version"
        assert "schema_version 7 is newer than this build reads (1)" in str(info.value)


def test_older_schema_version_loads_through_an_upgrader(avatar, bundle_path, tmp_path, monkeypatch):
    # A "version 1" file from a past where the face-model field was called "model".
    tensors, manifest = _read_raw(bundle_path)
    manifest["model"] = manifest.pop("face_model")
    path = tmp_path / "v1.bsplat"
    _write_raw(path, tensors, manifest)
    assert _error(path).field == "face_model"  # this build's v1 reader does not know the old name

    monkeypatch.setattr(bundle, "CURRENT_SCHEMA_VERSION", 2)
    with pytest.raises(BundleError, match="schema_version 1 cannot be read: no upgrader from 1 to 2"):
        read_bundle(path)

    calls = []

    def rename(m: dict) -> dict:
        calls.append(m["schema_version"])
        m["face_model"] = m.pop("model")
        return m

    monkeypatch.setitem(bundle.UPGRADERS, 1, rename)
    loaded = read_bundle(path)  # the digest still verifies: it covers the manifest as stored (v1)
    assert loaded.face_model == avatar.face_model and calls == [1]
    upgraded = read_manifest(path)
    assert upgraded["schema_version"] == 2 and "model" not in upgraded
    assert upgrade_manifest({"schema_version": 2}) == {"schema_version": 2}


def test_upgrade_manifest_rejects_bad_versions():
    for bad in (None, "1", 0, True):
        with pytest.raises(BundleError) as info:
            upgrade_manifest({} if bad is None else {"schema_version": bad})
        assert info.value.field == "schema_version"


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


def test_written_bundles_are_readable_by_other_processes(avatar, tmp_path):
    path = tmp_path / "shared.bundle"
    write_bundle(avatar, path)
    assert path.stat().st_mode & 0o777 == 0o644
