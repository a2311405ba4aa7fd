"""int8 blendshape deltas (precision "int8", render_core.packed): quantisation and its error bound, the avatar's
precision, bundles that store them (and refuse them malformed, by name), the native blend that reads them as
stored, and the PSNR gate against fp16.

The gate: the shipped trained demo avatar rendered at 512 px in int8 against fp16, PSNR >= 50 dB per frame, over
random expressions and poses and a few extreme expressions; the dense synthetic avatar the same. Measured here (the
test's frames, in order): demo 68.1, 66.4, 63.8, 64.4 (random), 57.7 (every coefficient 1), 68.1 (jawOpen), 79.7
(both blinks), 69.2 (smile, brow, cheek), 57.2 (all 1, jaw open, head turned) dB; dense synthetic (6000
Gaussians, 20 blendshapes) 65.8, 58.7, 64.3, 64.2 (random), 61.8 (all 1), 61.8 (all 1, posed) dB. With one scale
per (blendshape, column) and no position residual (the first design) the demo read 46.1 to 58.0 dB on the random
frames and 43.7 dB on the last one: positions set the error.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import safetensors.torch
import torch
from test_bundle import _digest, _read_raw

from render_core import packed
from render_core.bundle import read_bundle, read_manifest, validate_bundle, write_bundle
from render_core.deform import Frame
from render_core.drive import default_camera
from render_core.errors import BundleError, OptionError
from render_core.evaluation.metrics import psnr
from render_core.facemodel.open_head import DEMO_AVATAR
from render_core.packed import SparseDeltas
from render_core.raster import native
from render_core.renderer import AvatarRenderer
from render_core.tools.bench import framed_camera, random_frames
from render_core.tools.cli import main
from render_core.tools.synth import synth_avatar

MIN_PSNR_INT8 = 50.0  # against fp16: the gate
MIN_PSNR_TWIN = 60.0  # one frame against the dequantised fp32 avatar: the same products in another order
needs_native = pytest.mark.skipif(not native.available(), reason="the native backend is not built")
SIMD = native.simd_paths() if native.available() else []
_DTYPE = {torch.float32: "F32", torch.float16: "F16", torch.int64: "I64", torch.int32: "I32", torch.uint16: "U16",
          torch.int8: "I8"}


@pytest.fixture(scope="module")
def small():
    """300 face Gaussians, 6 blendshapes, SH degree 1; sparse-ish: the last 20 Gaussians have no deltas."""
    avatar = synth_avatar(gaussians=300, blendshapes=6, seed=5, sh_degree=1)
    deltas = avatar.deltas.map(torch.clone)
    for t in deltas.tensors().values():
        t[:, -20:] = 0.0
    return dataclasses.replace(avatar, deltas=deltas)


@pytest.fixture(scope="module")
def int8_file(small, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("int8") / "small.bsplat"
    write_bundle(small, path, precision="int8")
    return path


# ------------------------------------------------------------------------------------------------ quantisation


def test_quantisation_is_within_half_a_step_and_dequantises_exactly(small):
    x = SparseDeltas.from_dense(small.deltas, torch.float32)
    q = x.to(dtype=torch.int8)
    assert q.quantized and q.dtype == torch.int8
    direct = SparseDeltas.from_dense(small.deltas, torch.int8).tensors()
    assert all(torch.equal(t, direct[name]) for name, t in q.tensors().items())
    q.check(small.num_gaussians, small.num_expressions, 4)
    k = small.num_expressions
    for name in ("geometry", "color"):
        ref, got = getattr(x, name), getattr(q, name)
        assert torch.equal(got.col, ref.col) and torch.equal(got.row_ptr, ref.row_ptr)  # no pair rounds to zero
        values = ref.matrix()
        # the scale: the largest |value| of each (blendshape, column) over 127, computed here from the dense form
        amax = torch.stack([values[ref.col.long() == i].abs().amax(0) for i in range(k)])
        want = torch.zeros(k, packed.ceil16(ref.length))
        want[:, : ref.length] = amax / 127
        assert torch.allclose(got.scale, want, rtol=1e-6, atol=0)
        assert int(got.matrix().abs().max()) == 127 and got.values[got.count * got.length :].eq(0).all()
        step = got.scale[got.col.long(), : got.length]
        err = (values - got.dequantized()).abs()
        assert bool((err <= step / 2 * (1 + 1e-5)).all())
        steps = got.matrix().float()
        if name == "geometry":  # positions: a second byte, 1/256 of a step
            assert got.position_residual.shape == (got.count * 3 + 13,) and got.position_residual[-13:].eq(0).all()
            assert bool((err[:, :3] <= step[:, :3] / 256 * (1 + 1e-3)).all())
            steps[:, :3] += got.residuals().float() / 256
        else:
            assert got.position_residual is None
        # dequantised exactly: steps times the scale in float32, one rounding
        assert torch.equal(got.dequantized(), steps * step)
        assert torch.equal(getattr(q.to(dtype=torch.float32), name).matrix(), got.dequantized())
    dense = q.to_dense()
    assert dense.means.dtype == torch.float32
    assert torch.equal(dense.sh, q.to(dtype=torch.float32).to_dense().sh)


def test_quantisation_drops_pairs_that_round_to_zero_and_keeps_zero_columns_at_zero_scale(small):
    deltas = small.deltas.map(torch.clone)
    deltas.sh[:, 5] = 1e-6 * deltas.sh[:, 5]  # below half a step of every blendshape's largest colour delta
    deltas.opacity_logits[:] = 0.0  # a column that is zero everywhere
    q = SparseDeltas.from_dense(deltas, torch.int8)
    colour_rows = q.color.row_ptr[1:] - q.color.row_ptr[:-1]
    assert int(colour_rows[5]) == 0 and int(colour_rows[4]) == small.num_expressions
    assert q.geometry.scale[:, 10].eq(0).all() and q.geometry.matrix()[:, 10].eq(0).all()
    assert q.geometry.scale[:, 11:].eq(0).all() and q.color.scale[:, 12:].eq(0).all()  # columns past the row
    # tiny position deltas keep their pairs through the residual byte
    moved = small.deltas.map(torch.clone)
    for key in ("quats", "log_scales", "opacity_logits", "sh"):
        getattr(moved, key)[:, 7] = 0.0
    moved.means[:, 7] = 0.0
    moved.means[:, 7, 0] = 0.3 * moved.means[..., 0].abs().amax(1) / 127  # 0.3 of a step: q = 0, residual 77
    pos = SparseDeltas.from_dense(moved, torch.int8)
    first, last = int(pos.geometry.row_ptr[7]), int(pos.geometry.row_ptr[8])
    assert last - first == small.num_expressions and pos.geometry.matrix()[first:last].eq(0).all()
    assert pos.geometry.residuals()[first:last, 0].eq(77).all()


def test_avatar_precision_int8(small):
    q = small.with_precision("int8")
    assert q.precision == "int8" and isinstance(q.deltas, SparseDeltas)
    assert q.pose_correctives.dtype == q.eyelid_offsets.dtype == torch.float16  # the rest of the blendshape data
    assert q.neutral.means.dtype == q.lbs_weights.dtype == torch.float32
    again = q.with_precision("int8").deltas.tensors()
    assert all(t is again[name] for name, t in q.deltas.tensors().items())  # no copy
    assert q.with_precision("fp16").precision == "fp16" and q.to(torch.float32).precision == "fp32"
    assert torch.equal(q.sparse_deltas(torch.float32).geometry.matrix(), q.deltas.geometry.dequantized())
    q.validate()
    with pytest.raises(OptionError, match="int8"):
        small.with_precision("int4")
    # the reference backend renders the dequantised values
    cams = framed_camera(small, 48)
    frame = random_frames(small, 2, torch.Generator().manual_seed(1))
    a = AvatarRenderer(q, "reference").render(frame, cams.expand(2))
    b = AvatarRenderer(q.with_precision("fp32"), "reference").render(frame, cams.expand(2))
    assert torch.equal(a.rgb, b.rgb)


def test_the_torch_paths_blend_the_dequantised_values(small):
    """No int8 path in torch: the cuda backend's DeviceAvatar (run on the CPU here) stores an int8 avatar's
    dequantised values in fp32, and deform.blend dequantises the stored pairs."""
    from render_core.deform import blend
    from render_core.renderer import DeviceAvatar

    q = small.with_precision("int8")
    e = torch.rand(2, small.num_expressions, generator=torch.Generator().manual_seed(6))
    want = blend(q.with_precision("fp32"), e)
    for layout in ("dense", "sparse"):
        device = DeviceAvatar(q, "cpu", layout=layout)
        got = device.blend(e)
        assert device.precision == "fp32"
        if layout == "sparse":  # the same pairs summed in the same order: bit for bit
            assert torch.equal(got.means, want.means) and torch.equal(got.sh, want.sh)
        else:  # one dense matmul: BLAS may sum in another order (an ulp apart on an AVX-512 FP16 Xeon)
            torch.testing.assert_close(got.means, want.means, rtol=1e-6, atol=1e-7)
            torch.testing.assert_close(got.sh, want.sh, rtol=1e-6, atol=1e-6)
    assert torch.equal(blend(q, e).sh, want.sh)


# ------------------------------------------------------------------------------------------------ bundles


def test_int8_bundle_round_trip(small, int8_file, tmp_path):
    manifest = validate_bundle(int8_file)  # digest, shapes, finite values
    assert manifest["precision"] == "int8" and read_manifest(int8_file) == manifest
    tensors = manifest["tensors"]
    assert tensors["deltas.geometry.values"]["dtype"] == tensors["deltas.color.values"]["dtype"] == "I8"
    assert tensors["deltas.geometry.position_residual"]["dtype"] == "I8"
    k, c3 = small.num_expressions, 12
    assert tensors["deltas.geometry.scale"] == {"dtype": "F32", "shape": [k, 16]}
    assert tensors["deltas.color.scale"] == {"dtype": "F32", "shape": [k, packed.ceil16(c3)]}
    assert tensors["pose_correctives"]["dtype"] == "F16"
    raw, stored = _read_raw(int8_file)
    assert stored["digest"] == _digest(stored, raw)  # the documented digest covers the int8 tensors too
    for verify in (True, False):
        avatar = read_bundle(int8_file, verify=verify)
        assert avatar.precision == "int8"
        mine = small.with_precision("int8").deltas.tensors()
        assert all(torch.equal(t, mine[name]) for name, t in avatar.deltas.tensors().items())
    # convert: fp16 -> int8 -> fp16 keeps every shape but the pair tables' values' dtype
    fp16 = tmp_path / "fp16.bsplat"
    write_bundle(small, fp16)
    assert main(["bundle", "convert", str(fp16), "--out", str(tmp_path / "i8.bsplat"), "--precision", "int8"]) == 0
    assert main(["bundle", "convert", str(tmp_path / "i8.bsplat"), "--out", str(tmp_path / "back.bsplat"),
                 "--precision", "fp16"]) == 0
    a, b, c = (read_manifest(tmp_path / name)["tensors"] for name in ("fp16.bsplat", "i8.bsplat", "back.bsplat"))
    assert set(b) == set(a) | {"deltas.geometry.scale", "deltas.geometry.position_residual", "deltas.color.scale"}
    assert a == c and all(b[name]["shape"] == a[name]["shape"] for name in a)
    back = read_bundle(tmp_path / "back.bsplat")
    assert torch.allclose(back.dense_deltas().sh.float(), read_bundle(tmp_path / "i8.bsplat").dense_deltas().sh,
                          rtol=1e-3, atol=1e-6)


def test_bundle_commands_take_int8(tmp_path, capsys):
    out = tmp_path / "synth.bsplat"
    assert main(["bundle", "synth", "--out", str(out), "--gaussians", "200", "--blendshapes", "3",
                 "--precision", "int8"]) == 0
    assert json.loads(capsys.readouterr().out)["precision"] == "int8"
    assert read_bundle(out).precision == "int8"
    # int8 is schema 2's: a schema-1 file is refused by name
    assert main(["bundle", "convert", str(out), "--out", str(tmp_path / "v1.bsplat"), "--schema", "1"]) == 1
    assert "precision" in capsys.readouterr().err


def _write_raw(path: Path, tensors: dict[str, torch.Tensor], manifest: dict) -> Path:
    """A hand-made bundle (int8 tensors too) with a tensor table and digest that match."""
    manifest = dict(manifest)
    manifest["tensors"] = {k: {"dtype": _DTYPE[v.dtype], "shape": list(v.shape)} for k, v in tensors.items()}
    manifest["digest"] = _digest(manifest, tensors)
    safetensors.torch.save_file({k: v.contiguous() for k, v in tensors.items()}, str(path),
                                metadata={"blendsplat.manifest": json.dumps(manifest)})
    return path


def _nan_scale(t):
    t["deltas.color.scale"][2, 1] = float("nan")


def _negative_scale(t):
    t["deltas.geometry.scale"][0, 4] = -0.5


def _fp16_values(t):
    t["deltas.color.values"] = t["deltas.color.values"].half()


def _short_residual(t):
    t["deltas.geometry.position_residual"] = t["deltas.geometry.position_residual"][:-13]


def _wide_scale(t):
    t["deltas.geometry.scale"] = torch.zeros(t["deltas.geometry.scale"].shape[0], 32)


@pytest.mark.parametrize("verify", [True, False], ids=["verify", "no-verify"])
@pytest.mark.parametrize("edit, field, text", [
    (lambda t: t.pop("deltas.geometry.scale"), "deltas.geometry.scale", "missing"),
    (lambda t: t.pop("deltas.color.scale"), "deltas.color.scale", "missing"),
    (lambda t: t.pop("deltas.geometry.position_residual"), "deltas.geometry.position_residual", "missing"),
    (_nan_scale, "deltas.color.scale", "finite"),
    (_negative_scale, "deltas.geometry.scale", "negative"),
    (_fp16_values, "deltas.color.values", "F16"),
    (_short_residual, "deltas.geometry.position_residual", "shape"),
    (_wide_scale, "deltas.geometry.scale", "shape"),
], ids=["no-geometry-scale", "no-color-scale", "no-residual", "nan-scale", "negative-scale", "fp16-values",
        "short-residual", "wide-scale"])
def test_malformed_int8_bundles_are_refused_by_name(int8_file, tmp_path, edit, field, text, verify):
    tensors, manifest = _read_raw(int8_file)
    edit(tensors)
    path = _write_raw(tmp_path / "bad.bsplat", tensors, manifest)
    with pytest.raises(BundleError, match=text) as info:
        read_bundle(path, verify=verify)
    assert info.value.field == field


def test_int8_needs_schema_2_and_scales_need_int8(small, int8_file, tmp_path):
    with pytest.raises(BundleError, match="schema 2") as info:
        write_bundle(small, tmp_path / "v1.bsplat", precision="int8", schema_version=1)
    assert info.value.field == "precision" and not (tmp_path / "v1.bsplat").exists()
    tensors, manifest = _read_raw(int8_file)
    old = _write_raw(tmp_path / "old.bsplat", tensors, {**manifest, "schema_version": 1})
    with pytest.raises(BundleError, match="schema 2") as info:
        read_manifest(old)
    assert info.value.field == "precision"
    # an fp16 bundle holding scales: not its tensors
    fp16 = tmp_path / "fp16.bsplat"
    write_bundle(small, fp16)
    half, half_manifest = _read_raw(fp16)
    half["deltas.color.scale"] = tensors["deltas.color.scale"]
    with pytest.raises(BundleError, match="unexpected") as info:
        read_bundle(_write_raw(tmp_path / "extra.bsplat", half, half_manifest))
    assert info.value.field == "deltas.color.scale"


# ------------------------------------------------------------------------------------------------ native


@needs_native
@pytest.mark.parametrize("simd", SIMD)
def test_native_int8_renders_its_dequantised_twin(simd, small):
    """Batches dequantise each pair as packed.py does (bit for bit the fp32 twin's images); one frame weighs the
    int8 values by psi scale instead (the same products in another order); both against the torch reference."""
    q = small.with_precision("int8")
    twin = q.with_precision("fp32")
    r8, r32 = (AvatarRenderer(a, "native", simd=simd) for a in (q, twin))
    cams = framed_camera(small, 96)
    frames = random_frames(small, 3, torch.Generator().manual_seed(2))
    batch, ref = r8.render(frames, cams.expand(3)), r32.render(frames, cams.expand(3))
    assert torch.equal(batch.rgb, ref.rgb) and torch.equal(batch.alpha, ref.alpha)
    one = Frame(frames.expression[:1], frames.joint_rotations[:1], frames.eyelids[:1])  # synthetic: eyelids
    single, twin_single = r8.render(one, cams), r32.render(one, cams)
    assert psnr(single.rgb, twin_single.rgb) >= MIN_PSNR_TWIN
    assert float((single.rgb - twin_single.rgb).abs().max()) <= 1e-4
    reference = AvatarRenderer(twin, "reference").render(frames, cams.expand(3))
    assert psnr(batch.rgb, reference.rgb) >= 50.0
    # the bytes a frame streams: int8 values, scales and residuals instead of fp16 values
    half = native.NativeAvatar(small.with_precision("fp16"))
    assert r8.stats.precision == "int8" and r8.stats.blend_bytes < half.stats.blend_bytes

    def value_bytes(deltas) -> int:
        return sum(t.nbytes for name, t in deltas.tensors().items() if name.split(".")[1] not in ("row_ptr", "col"))

    assert value_bytes(q.deltas) < 0.6 * value_bytes(half.avatar.sparse_deltas(torch.float16))


@needs_native
def test_native_int8_with_many_blendshapes_dequantises_per_pair(small):
    """Past 512 blendshapes (at 3C = 48) a frame's weighted scales would not fit the cache: one frame takes the
    batched path, bit for bit the fp32 twin."""
    big = synth_avatar(gaussians=120, blendshapes=600, seed=2)
    q = big.with_precision("int8")
    cams = framed_camera(big, 48)
    frame = random_frames(big, 1, torch.Generator().manual_seed(4))
    a = AvatarRenderer(q, "native").render(frame, cams)
    b = AvatarRenderer(q.with_precision("fp32"), "native").render(frame, cams)
    assert torch.equal(a.rgb, b.rgb)


@needs_native
def test_native_refuses_broken_int8_tables(small):
    q = small.with_precision("int8")
    bad = dataclasses.replace(q, deltas=dataclasses.replace(q.deltas, color=dataclasses.replace(
        q.deltas.color, scale=q.deltas.color.scale.clone())))
    bad.deltas.color.scale[0, 0] = float("inf")
    with pytest.raises(ValueError, match="color.scale: scales must be finite"):
        native.NativeAvatar(bad)
    short = dataclasses.replace(q, deltas=dataclasses.replace(q.deltas, geometry=dataclasses.replace(
        q.deltas.geometry, position_residual=q.deltas.geometry.position_residual[:-1])))
    with pytest.raises(ValueError, match="geometry.residual"):
        native.NativeAvatar(short)


# ------------------------------------------------------------------------------------------------ the PSNR gate


def _gate_frames(avatar, seed: int) -> list[Frame]:
    """Four random frames (coefficients in [0, 1], random head, jaw and eye poses), then extremes: every
    coefficient 1, single expressions at 1 where the avatar names them, and all 1 with the jaw open and the head
    turned."""
    g = torch.Generator().manual_seed(seed)
    frames = [random_frames(avatar, 1, g) for _ in range(4)]
    k, names = avatar.num_expressions, avatar.expression_names
    frames.append(Frame.from_params(avatar, expression=torch.ones(1, k)))
    for group in (["jawOpen"], ["eyeBlinkLeft", "eyeBlinkRight"],
                  ["mouthSmileLeft", "mouthSmileRight", "browInnerUp", "cheekPuff"]):
        if all(name in names for name in group):
            frames.append(Frame.from_params(avatar, expression={name: 1.0 for name in group}))
    joints = {"jaw": torch.tensor([[0.25, 0.0, 0.0]]), "neck": torch.tensor([[0.1, 0.3, 0.0]])}
    frames.append(Frame.from_params(avatar, expression=torch.ones(1, k), joints=joints))
    return frames


def _gate(avatar, cams) -> list[float]:
    """PSNR (dB) of each gate frame rendered natively in int8 against fp16."""
    half, int8 = AvatarRenderer(avatar.with_precision("fp16"), "native"), AvatarRenderer(
        avatar.with_precision("int8"), "native")
    return [round(psnr(int8.render(f, cams).rgb, half.render(f, cams).rgb), 2) for f in _gate_frames(avatar, 3)]


@needs_native
def test_psnr_gate_on_the_trained_demo_avatar():
    demo = read_bundle(DEMO_AVATAR)
    assert demo.precision == "fp16"
    values = _gate(demo, default_camera(demo, 512, 512))
    assert len(values) == 9 and min(values) >= MIN_PSNR_INT8, values


@needs_native
def test_psnr_gate_on_the_dense_synthetic_avatar():
    dense = synth_avatar(gaussians=6000, blendshapes=20, seed=0)
    values = _gate(dense, framed_camera(dense, 512))
    assert len(values) == 6 and min(values) >= MIN_PSNR_INT8, values


@needs_native
def test_bench_render_takes_int8():
    from render_core.tools.bench import bench_render

    report = bench_render("native", gaussians=300, blendshapes=4, size=64, frames=1, warmup=0, precision="int8")
    assert report["precision"] == "int8" and report["blend"]["bytes"] > 0
