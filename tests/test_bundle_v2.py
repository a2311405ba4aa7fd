"""Schema-2 bundles (render_core.bundle, render_core.packed): the CSR pair tables refused when malformed, sparse
storage, and schema-1 files converted to schema 2 rendering the same images.

Every malformed file here is a valid schema-2 file with one tensor (or header entry) rewritten and the digest
recomputed, so the structural check, not the digest, must catch it; the structural checks protect the renderers'
memory reads, so they fire with ``verify=False`` too (which skips only the digest and the NaN scan).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import safetensors.torch
import torch
from test_bundle import _DTYPE, _digest, _error, _header, _pair_masks, _read_raw, _rewrite_header, _write_raw

from render_core import packed
from render_core.avatar import Gaussians
from render_core.bundle import read_bundle, read_manifest, stored_schema_version, write_bundle
from render_core.camera import orbit
from render_core.deform import Frame
from render_core.errors import BundleError
from render_core.packed import SparseDeltas
from render_core.raster import native
from render_core.renderer import AvatarRenderer
from render_core.rotation import axis_angle_to_matrix
from render_core.tools.synth import synth_avatar

N, K, SH_DEGREE, EMPTY_TAIL = 96, 5, 1, 4
C = (SH_DEGREE + 1) ** 2
LENGTH = {"geometry": packed.GEOMETRY_LENGTH, "color": 3 * C}
PARTS = ["geometry", "color"]
VERIFY = [pytest.param(True, id="verify"), pytest.param(False, id="no-verify")]
needs_native = pytest.mark.skipif(not native.available(), reason="the native backend is not built")


def _sparsify(avatar, seed: int = 0, empty_tail: int = EMPTY_TAIL):
    """A copy of ``avatar`` whose deltas are exactly zero: SH for ~60% of the (blendshape, Gaussian) pairs,
    geometry for ~30% (drawn independently), and everything for the last ``empty_tail`` Gaussians (empty rows)."""
    k, n = avatar.num_expressions, avatar.num_gaussians
    g = torch.Generator().manual_seed(seed)
    no_sh, no_geometry = torch.rand(k, n, generator=g) < 0.6, torch.rand(k, n, generator=g) < 0.3
    if empty_tail:
        no_sh[:, -empty_tail:] = no_geometry[:, -empty_tail:] = True
    deltas = avatar.deltas.map(torch.clone)
    deltas.sh[no_sh] = 0.0
    for key in ("means", "quats", "log_scales", "opacity_logits"):
        getattr(deltas, key)[no_geometry] = 0.0
    return dataclasses.replace(avatar, deltas=deltas)


@pytest.fixture(scope="module")
def sparse_avatar():
    """N=96 face Gaussians, K=5 blendshapes, SH degree 1; sparse deltas (_sparsify)."""
    return _sparsify(synth_avatar(gaussians=N, blendshapes=K, seed=7, sh_degree=SH_DEGREE))


@pytest.fixture(scope="module")
def v2_file(sparse_avatar, tmp_path_factory) -> Path:
    """The sparse avatar as a schema-2, fp16 bundle (the default)."""
    path = tmp_path_factory.mktemp("v2") / "sparse.bsplat"
    write_bundle(sparse_avatar, path)
    return path


def _rewritten(v2_file: Path, path: Path, edit) -> Path:
    """A copy of the valid file with its tensors passed through ``edit`` (digest and table recomputed)."""
    tensors, manifest = _read_raw(v2_file)
    edit(tensors)
    _write_raw(path, tensors, manifest)
    return path


def _row_with_pairs(row_ptr: torch.Tensor, at_least: int) -> int:
    """The first Gaussian whose row holds at least ``at_least`` pairs."""
    counts = (row_ptr[1:].long() - row_ptr[:-1].long())
    return int((counts >= at_least).nonzero()[0])


def _set_col(part: str, which: str):
    """Edits of one table's ``col``: a pair naming blendshape K or 65535 (the last of a row, so still sorted), the
    first two pairs of a row swapped (unsorted) or equal (duplicate)."""

    def edit(t):
        rp, col = t[f"deltas.{part}.row_ptr"], t[f"deltas.{part}.col"].to(torch.int32)
        row = _row_with_pairs(rp, 2)
        first, last = int(rp[row]), int(rp[row + 1]) - 1
        if which == "K":
            col[last] = K
        elif which == "max":
            col[last] = 65535
        elif which == "swap":
            col[first], col[first + 1] = col[first + 1].clone(), col[first].clone()
        elif which == "duplicate":
            col[first + 1] = col[first]
        t[f"deltas.{part}.col"] = col.to(torch.uint16)

    return edit


def _set_row_ptr(part: str, which: str):
    """Edits of one table's ``row_ptr``."""

    def edit(t):
        rp = t[f"deltas.{part}.row_ptr"]
        if which == "start":
            rp[0] = 1  # row 0 holds pairs: 1 <= row_ptr[1], so only the start is wrong
        elif which == "negative-start":
            rp[0] = -1
        elif which == "decrease":
            j = N // 2
            rp[j] = rp[j + 1] + 1
        elif which == "end-beyond":
            rp[-1] += 1
        elif which == "end-short":  # the last non-empty row loses its last pair: the tail rows end at P - 1
            rp[-(EMPTY_TAIL + 1):] -= 1
        elif which == "extra-col":  # one more col entry (and its values), row_ptr unchanged
            col, values = t[f"deltas.{part}.col"], t[f"deltas.{part}.values"]
            t[f"deltas.{part}.col"] = torch.cat([col, col[-1:]])
            t[f"deltas.{part}.values"] = torch.cat([values, values.new_zeros(LENGTH[part])])

    return edit


_STRUCTURE = [
    # (id, edit factory, which, tensor of the field, words of the message)
    ("col-equals-K", _set_col, "K", "col", ("names blendshape", f"the avatar has {K}")),
    ("col-65535", _set_col, "max", "col", ("names blendshape 65535",)),
    ("unsorted", _set_col, "swap", "col", ("unsorted",)),
    ("duplicate", _set_col, "duplicate", "col", ("duplicate",)),
    ("row-ptr-start", _set_row_ptr, "start", "row_ptr", ("start at 0",)),
    ("row-ptr-negative-start", _set_row_ptr, "negative-start", "row_ptr", ("start at 0",)),
    ("row-ptr-decreases", _set_row_ptr, "decrease", "row_ptr", ("decreases at Gaussian",)),
    ("row-ptr-end-beyond-col", _set_row_ptr, "end-beyond", "row_ptr", ("ends at", "col holds")),
    ("row-ptr-end-short-of-col", _set_row_ptr, "end-short", "row_ptr", ("ends at", "col holds")),
    ("col-longer-than-row-ptr", _set_row_ptr, "extra-col", "row_ptr", ("ends at", "col holds")),
]


@pytest.mark.parametrize("verify", VERIFY)
@pytest.mark.parametrize("part", PARTS)
@pytest.mark.parametrize("make, which, tensor, words", [pytest.param(*case[1:], id=case[0]) for case in _STRUCTURE])
def test_malformed_pair_table_is_refused(v2_file, tmp_path, part, verify, make, which, tensor, words):
    path = _rewritten(v2_file, tmp_path / "bad.bsplat", make(part, which))
    read_manifest(path)  # dtypes and shapes agree: only the values are wrong
    error = _error(path, verify=verify)
    assert error.field == f"deltas.{part}.{tensor}", str(error)
    for word in words:
        assert word in str(error)


@pytest.mark.parametrize("verify", VERIFY)
@pytest.mark.parametrize("part", PARTS)
@pytest.mark.parametrize("change", ["one-short", "one-pair-more", "no-padding"])
def test_values_length_must_match_the_pair_count(v2_file, tmp_path, part, verify, change):
    length = LENGTH[part]
    pad = packed.ceil16(length) - length
    assert pad > 0  # 11 -> 16 and 12 -> 16: both tables pad their last row

    def edit(t):
        values = t[f"deltas.{part}.values"]
        t[f"deltas.{part}.values"] = {"one-short": values[:-1], "one-pair-more": torch.cat([values, values[:length]]),
                                      "no-padding": values[:-pad]}[change].contiguous()

    path = _rewritten(v2_file, tmp_path / "bad.bsplat", edit)
    pairs = int(_read_raw(v2_file)[0][f"deltas.{part}.col"].numel())
    for call in (lambda p: read_bundle(p, verify=verify), read_manifest):
        with pytest.raises(BundleError) as info:
            call(path)
        assert info.value.field == f"deltas.{part}.values"
        assert f"with P = {pairs} pairs" in str(info.value) and f"= [{pairs * length + pad}]" in str(info.value)


@pytest.mark.parametrize(
    "name, dtype",
    [("deltas.geometry.col", torch.int32), ("deltas.color.col", torch.int32), ("deltas.geometry.col", torch.int64),
     ("deltas.geometry.row_ptr", torch.int64), ("deltas.color.row_ptr", torch.uint16),
     ("deltas.color.row_ptr", torch.float32), ("deltas.geometry.values", torch.float32)],
)
def test_pair_table_of_the_wrong_dtype_is_refused(v2_file, tmp_path, name, dtype):
    path = _rewritten(v2_file, tmp_path / "bad.bsplat", lambda t: t.update({name: t[name].to(dtype)}))
    want = {"col": "U16", "row_ptr": "I32", "values": "F16"}[name.rsplit(".", 1)[1]]
    for call in (read_manifest, lambda p: read_bundle(p, verify=False)):
        with pytest.raises(BundleError) as info:
            call(path)
        assert info.value.field == name
        assert f"dtype {_DTYPE[dtype]}" in str(info.value) and f"store {want}" in str(info.value)


def _write_with_table(path: Path, tensors: dict, manifest: dict, edit) -> None:
    """Like _write_raw, but the manifest's ``tensors`` table passes through ``edit`` before the digest is taken
    (the digest is valid; the table no longer describes the file)."""
    manifest = dict(manifest)
    table = {k: {"dtype": _DTYPE[v.dtype], "shape": list(v.shape)} for k, v in tensors.items()}
    edit(table)
    manifest["tensors"] = table
    manifest["digest"] = _digest(manifest, tensors)
    safetensors.torch.save_file({k: v.contiguous() for k, v in tensors.items()}, str(path),
                                metadata={"blendsplat.manifest": json.dumps(manifest)})


@pytest.mark.parametrize(
    "edit, named",
    [
        (lambda t: t["deltas.geometry.col"]["shape"].__setitem__(0, t["deltas.geometry.col"]["shape"][0] - 1),
         "deltas.geometry.col"),
        (lambda t: t["deltas.color.row_ptr"].update(dtype="I64"), "deltas.color.row_ptr"),
        (lambda t: t.pop("eyelid_offsets"), "eyelid_offsets"),
        (lambda t: t.update({"deltas.extra": {"dtype": "F16", "shape": [3]}}), "deltas.extra"),
        (lambda t: t.update({"neutral.means": {"dtype": "F32", "shape": [N, 3]}}), "neutral.means"),
    ],
    ids=["col-shape", "row-ptr-dtype", "missing-entry", "extra-entry", "v1-entry"],
)
@pytest.mark.parametrize("verify", VERIFY)
def test_manifest_tensor_table_must_describe_the_file(v2_file, tmp_path, edit, named, verify):
    tensors, manifest = _read_raw(v2_file)
    path = tmp_path / "table.bsplat"
    _write_with_table(path, tensors, manifest, edit)
    for call in (lambda p: read_bundle(p, verify=verify), read_manifest):
        with pytest.raises(BundleError) as info:
            call(path)
        assert info.value.field == "tensors"
        assert "the manifest lists" in str(info.value) and repr(named) in str(info.value)


@pytest.mark.parametrize("how", ["offsets-past-end", "file-cut"])
def test_tensor_running_past_the_end_of_the_file_is_refused(v2_file, tmp_path, how):
    """The last tensor of the data region (a col table: the writer puts 2-byte tensors last) claims bytes that
    the file does not hold. The reader names the data region (field "data"), as for any truncated file."""
    header = _header(v2_file)
    last = max((k for k in header if k != "__metadata__"), key=lambda k: header[k]["data_offsets"][1])
    assert last.endswith(".col")
    path = tmp_path / "short.bsplat"
    data = v2_file.stat().st_size - 8 - int.from_bytes(v2_file.read_bytes()[:8], "little")
    if how == "offsets-past-end":
        def grow(h):
            h[last]["shape"][0] += 8
            h[last]["data_offsets"][1] += 16

        _rewrite_header(v2_file, path, grow)
    else:
        path.write_bytes(v2_file.read_bytes()[:-2])  # one col entry short
    for call in (read_bundle, lambda p: read_bundle(p, verify=False), read_manifest):
        with pytest.raises(BundleError) as info:
            call(path)
        assert info.value.field == "data" and "truncated" in str(info.value)
        want = f"expected {data + 16} bytes of tensor data, file has {data}" if how == "offsets-past-end" else \
            f"expected {data} bytes of tensor data, file has {data - 2}"
        assert want in str(info.value)


@pytest.mark.parametrize(
    "name, at",
    [("deltas.geometry.values", 3), ("deltas.color.values", 10), ("gaussians", 17),
     ("deltas.geometry.values", -1), ("gaussians", 12)],
    ids=["geometry", "color", "gaussians-sh", "values-padding", "gaussians-unused-column"],
)
@pytest.mark.parametrize("value", [float("nan"), float("inf")], ids=["nan", "inf"])
def test_non_finite_values_are_refused_with_verify(v2_file, tmp_path, name, at, value):
    def edit(t):
        t[name].view(-1)[at] = value  # gaussians [N + M, R]: row 0, column ``at``

    path = _rewritten(v2_file, tmp_path / "nan.bsplat", edit)
    error = _error(path)
    assert error.field == name and "1 of" in str(error) and "non-finite" in str(error)
    loaded = read_bundle(path, verify=False)  # verify=False skips only the scan: the structure is sound
    assert isinstance(loaded.deltas, SparseDeltas)
    stored = {"gaussians": packed.pack_rows(loaded.neutral, loaded.mouth), **{
        f"deltas.{k}": v for k, v in loaded.deltas.tensors().items()}}[name]
    assert int((~torch.isfinite(stored)).sum()) == 1


@pytest.mark.parametrize("part", PARTS)
def test_row_ptr_decreasing_through_int32_overflow_is_refused(v2_file, tmp_path, part):
    """row_ptr [..., P, 2^31 - 1, -2^31, -1, P] over the empty last rows: steps 2^31 - 1 - P, -2^32 + 1, 2^31 - 1,
    P + 1. Exact arithmetic has a decrease (2^31 - 1 -> -2^31); int32 subtraction wraps the -2^32 + 1 to +1, and no
    step looks negative. Such a table claims 2^31 - 1 pairs for one Gaussian: the native module's own check
    refuses it, but SparseDeltas.rows() (the reference and cuda paths' blend, to_dense) would expand ~2^32
    indices."""

    def edit(t):
        rp = t[f"deltas.{part}.row_ptr"]
        assert bool((rp[-EMPTY_TAIL - 1:] == rp[-1]).all())  # the last rows are empty
        rp[-EMPTY_TAIL:-1] = torch.tensor([2**31 - 1, -(2**31), -1], dtype=torch.int32)

    path = _rewritten(v2_file, tmp_path / "wrap.bsplat", edit)
    error = _error(path, verify=False)
    assert error.field == f"deltas.{part}.row_ptr" and "decreases" in str(error)


# ------------------------------------------------------------------------------------------ sparse storage


def test_sparse_avatar_stores_only_its_non_zero_pairs_and_a_smaller_file(tmp_path):
    """SH degree 3, 12 blendshapes: the deltas are most of the file, and about 60% of the colour and 30% of the
    geometry pairs are zero (drawn independently). Schema 2 stores only the others (plus 2 bytes of blendshape
    index each and row pointers), so the file is smaller than the dense schema-1 file despite its padding."""
    avatar = _sparsify(synth_avatar(gaussians=200, blendshapes=12, seed=5), seed=2)
    n, k, c = avatar.num_gaussians, avatar.num_expressions, (avatar.sh_degree + 1) ** 2
    geometry_mask, color_mask = _pair_masks(avatar.deltas)  # [K, N]
    assert 0 < int(color_mask.sum()) < int(geometry_mask.sum()) < n * k
    assert not bool((geometry_mask | color_mask)[:, -EMPTY_TAIL:].any())
    for precision, size in (("fp16", 2), ("fp32", 4)):
        v1, v2 = tmp_path / f"v1-{precision}.bsplat", tmp_path / f"v2-{precision}.bsplat"
        write_bundle(avatar, v1, precision, schema_version=1)
        manifest = write_bundle(avatar, v2, precision)
        assert v2.stat().st_size < v1.stat().st_size, precision
        loaded = read_bundle(v2)
        delta_bytes = 0
        for part, mask in (("geometry", geometry_mask), ("color", color_mask)):
            pairs, length = getattr(loaded.deltas, part), {"geometry": 11, "color": 3 * c}[part]
            # Exactly the pairs of the dense mask, Gaussian-major then blendshape-minor.
            gaussian, shape = mask.T.nonzero(as_tuple=True)
            assert pairs.count == int(mask.sum()) == manifest["tensors"][f"deltas.{part}.col"]["shape"][0]
            assert torch.equal(pairs.col.long(), shape) and torch.equal(pairs.rows(), gaussian)
            assert torch.equal(pairs.row_ptr.long(), torch.cat([torch.zeros(1, dtype=torch.long),
                                                                mask.sum(0).cumsum(0)]))
            assert pairs.values.numel() == pairs.count * length + packed.ceil16(length) - length
            assert bool(pairs.matrix().ne(0).any(-1).all())  # no stored row is all zeros
            delta_bytes += 4 * (n + 1) + 2 * pairs.count + size * pairs.values.numel()
        stored = sum(t.numel() * t.element_size() for t in loaded.deltas.tensors().values())
        assert stored == delta_bytes < n * k * (11 + 3 * c) * size  # against the dense deltas of schema 1
        dtype = torch.float16 if precision == "fp16" else torch.float32
        for key, t in avatar.deltas.tensors().items():
            assert torch.equal(getattr(loaded.dense_deltas(), key), t.to(dtype)), key


def test_pairs_vanishing_in_fp16_are_dropped_whatever_the_source(tmp_path):
    """Pair (blendshape 1, Gaussian 4) holds only 1e-9 (0 in fp16). Writing the dense avatar as fp16 drops it;
    rewriting as fp16 the same avatar read from its fp32 schema-2 file must give the same file content."""
    avatar = synth_avatar(gaussians=30, blendshapes=3, seed=2, sh_degree=SH_DEGREE)
    deltas = avatar.deltas.map(torch.clone)
    for t in deltas.tensors().values():
        t[1, 4] = 1e-9
    avatar = dataclasses.replace(avatar, deltas=deltas)
    direct = write_bundle(avatar, tmp_path / "direct.bsplat", "fp16")
    write_bundle(avatar, tmp_path / "fp32.bsplat", "fp32")
    via_fp32 = write_bundle(read_bundle(tmp_path / "fp32.bsplat"), tmp_path / "via.bsplat", "fp16")
    assert direct["tensors"]["deltas.geometry.col"]["shape"] == [30 * 3 - 1]
    assert via_fp32["tensors"] == direct["tensors"]


def test_sparse_deltas_cast_with_replace_to_and_with_precision(sparse_avatar, tmp_path):
    path = tmp_path / "a.bsplat"
    write_bundle(sparse_avatar, path, "fp32")
    loaded = read_bundle(path)
    assert isinstance(loaded.deltas, SparseDeltas) and loaded.precision == "fp32"

    renamed = dataclasses.replace(loaded, face_model="renamed")
    renamed.validate()
    assert renamed.deltas is loaded.deltas
    write_bundle(renamed, tmp_path / "renamed.bsplat", "fp32")
    assert read_bundle(tmp_path / "renamed.bsplat").face_model == "renamed"

    half = loaded.with_precision("fp16")
    half.validate()
    assert isinstance(half.deltas, SparseDeltas) and half.precision == "fp16"
    assert half.deltas.dtype == torch.float16 and half.pose_correctives.dtype == torch.float16
    assert half.neutral.means.dtype == torch.float32 and half.eyelid_offsets.dtype == torch.float16
    for part in PARTS:
        a, b = getattr(loaded.deltas, part), getattr(half.deltas, part)
        assert torch.equal(a.row_ptr, b.row_ptr) and torch.equal(a.col, b.col)  # indices keep their dtypes
        assert b.row_ptr.dtype == torch.int32 and b.col.dtype == torch.uint16
        assert torch.equal(b.values, a.values.half())
    for key, t in loaded.dense_deltas().tensors().items():
        assert torch.equal(getattr(half.dense_deltas(), key), t.half()), key
    # The fp16 copy written and read back equals the fp16 file of the original.
    write_bundle(half, tmp_path / "half.bsplat")
    write_bundle(sparse_avatar, tmp_path / "direct.bsplat")
    for a, b in zip(read_bundle(tmp_path / "half.bsplat").deltas.tensors().values(),
                    read_bundle(tmp_path / "direct.bsplat").deltas.tensors().values(), strict=True):
        assert torch.equal(a, b)

    back = half.to(torch.float32)
    back.validate()
    assert back.deltas.dtype == torch.float32 and back.neutral.means.dtype == torch.float32
    assert torch.equal(back.deltas.color.values, half.deltas.color.values.float())
    assert back.deltas.geometry.col.dtype == torch.uint16
    moved = loaded.to(device="cpu")
    assert isinstance(moved.deltas, SparseDeltas) and torch.equal(moved.deltas.geometry.values,
                                                                  loaded.deltas.geometry.values)
    whole = loaded.to(torch.float16)
    whole.validate()
    assert whole.deltas.dtype == torch.float16 and whole.neutral.means.dtype == torch.float16


# -------------------------------------------------------------------------------------- v1 -> v2 conversion


def _frames(avatar, batch: int, seed: int) -> Frame:
    """``batch`` frames with every input non-zero: expressions (some negative), every joint rotated, both eyelids."""
    g = torch.Generator().manual_seed(seed)
    expression = torch.rand(batch, avatar.num_expressions, generator=g) * 1.5 - 0.25
    rotations = axis_angle_to_matrix((torch.rand(batch, avatar.num_joints, 3, generator=g) * 2 - 1) * 0.25)
    eyelids = torch.rand(batch, 2, generator=g) * 0.7 + 0.2
    return Frame(expression, rotations, eyelids)


def _cameras(batch: int):
    return orbit([0.0, 25.0, -30.0][:batch], [0.0, -10.0, 12.0][:batch], width=40, height=36, focal=90.0)


@pytest.fixture(scope="module", params=["fp16", "fp32"])
def converted(request, tmp_path_factory):
    """(v1 avatar, v2 avatar): a schema-1 file (dense deltas; a third of the pairs zero) read, rewritten with
    write_bundle (schema 2, same precision) and read again."""
    precision = request.param
    folder = tmp_path_factory.mktemp(f"convert-{precision}")
    avatar = _sparsify(synth_avatar(gaussians=400, blendshapes=6, seed=13), seed=1, empty_tail=0)
    assert avatar.pose_correctives is not None and avatar.eyelid_offsets is not None
    write_bundle(avatar, folder / "v1.bsplat", precision, schema_version=1)
    v1 = read_bundle(folder / "v1.bsplat")
    write_bundle(v1, folder / "v2.bsplat", precision)
    assert stored_schema_version(folder / "v1.bsplat") == 1 and stored_schema_version(folder / "v2.bsplat") == 2
    v2 = read_bundle(folder / "v2.bsplat")
    assert isinstance(v1.deltas, Gaussians) and isinstance(v2.deltas, SparseDeltas)
    assert v1.precision == v2.precision == precision
    for key, t in v1.deltas.tensors().items():  # the same content
        assert torch.equal(getattr(v2.dense_deltas(), key), t), key
    return v1, v2


@needs_native
@pytest.mark.parametrize("batch", [1, 3])
def test_converted_bundle_renders_the_same_images_native(converted, batch):
    v1, v2 = converted
    frame, cams = _frames(v1, batch, seed=batch), _cameras(batch)
    a = AvatarRenderer(v1, "native").render(frame, cams)
    b = AvatarRenderer(v2, "native").render(frame, cams)
    assert a.rgb.shape == (batch, 36, 40, 3)
    assert float(a.alpha.mean()) > 0.1  # the head fills a good part of the view
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.alpha, b.alpha) and torch.equal(a.depth, b.depth)
    # The deltas, pose and eyelids all reach the image (the comparison covers them).
    for still in (dataclasses.replace(frame, expression=torch.zeros_like(frame.expression)),
                  dataclasses.replace(frame, eyelids=torch.zeros_like(frame.eyelids)),
                  Frame(frame.expression, torch.eye(3).expand_as(frame.joint_rotations).clone(), frame.eyelids)):
        assert not torch.equal(AvatarRenderer(v2, "native").render(still, cams).rgb, b.rgb)


@pytest.mark.parametrize("batch", [1, 3])
def test_converted_bundle_renders_the_same_images_reference(converted, batch):
    v1, v2 = converted
    frame, cams = _frames(v1, batch, seed=10 + batch), _cameras(batch)
    a = AvatarRenderer(v1, "reference").render(frame, cams)
    b = AvatarRenderer(v2, "reference").render(frame, cams)
    assert float(a.alpha.mean()) > 0.1
    torch.testing.assert_close(b.rgb, a.rgb, atol=1e-5, rtol=0)
    torch.testing.assert_close(b.alpha, a.alpha, atol=1e-5, rtol=0)
