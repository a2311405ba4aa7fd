"""AvatarRenderer.nbytes: the memory a renderer holds for its avatar, host or device, for every backend."""

import pytest
import torch

from render_core.raster import native
from render_core.renderer import STORAGE_DTYPES, AvatarRenderer
from render_core.tools.synth import synth_avatar


def blendshape_floats(avatar) -> int:
    """Values of the blendshape data (deltas, pose correctives, eyelid offsets): what fp16 storage halves."""
    extra = [t for t in (avatar.pose_correctives, avatar.eyelid_offsets) if t is not None]
    return sum(t.numel() for t in [*avatar.deltas.tensors().values(), *extra])


@pytest.mark.skipif(not native.available(), reason="the native backend is not built")
def test_native_nbytes_counts_the_packed_arrays(avatar):
    dense = AvatarRenderer(avatar, "native")
    # Every (Gaussian, blendshape) pair of a dense avatar is stored: at least the deltas' values, in fp32.
    assert dense.nbytes == dense.native.nbytes >= dense.stats.blend_bytes
    assert dense.nbytes >= sum(t.numel() for t in avatar.deltas.tensors().values()) * 4
    half = AvatarRenderer(avatar.with_precision("fp16"), "native")
    assert half.nbytes < dense.nbytes
    # A local avatar stores only the pairs that change anything, and says so.
    local = synth_avatar(gaussians=600, blendshapes=6, seed=3, local=True)
    sparse = AvatarRenderer(local, "native")
    assert sparse.stats.stored_fraction < 1 and sparse.nbytes < dense.nbytes


def test_reference_nbytes_counts_only_its_own_copy(avatar):
    # fp32: the reference path renders the avatar it was given; it holds nothing of its own.
    assert AvatarRenderer(avatar, "reference").nbytes == 0
    # fp16: it keeps a float32 copy of the blendshape data (the rest is shared with the avatar).
    half = avatar.with_precision("fp16")
    assert AvatarRenderer(half, "reference").nbytes == 4 * blendshape_floats(half)


@pytest.mark.parametrize("precision", ["fp32", "fp16", "bf16"])
def test_cuda_nbytes_counts_the_device_avatar_emulated(monkeypatch, avatar, precision):
    pytest.importorskip("gsplat", reason="gsplat is not installed")
    import gsplat_cpu

    gsplat_cpu.emulate_cuda_backend(monkeypatch)  # the cuda path, its device the CPU
    renderer = AvatarRenderer(avatar, "cuda", precision=precision, layout="sparse")
    dev = renderer.device_avatar
    sparse = avatar.sparse_deltas()
    size = {"fp32": 4, "fp16": 2, "bf16": 2}[precision]
    packed = sum(t.numel() * (size if t.is_floating_point() else t.element_size())
                 for t in sparse.tensors().values())
    assert dev.nbytes == packed and dev.deltas.dtype == STORAGE_DTYPES[precision]
    # On the CPU the float32 tensors skinning reads are the avatar's own: only the sparse blendshapes are new.
    assert renderer.nbytes == packed
    # An fp16 avatar's pose correctives and eyelid offsets get float32 copies on the device too.
    half = avatar.with_precision("fp16")
    extra = sum(t.numel() for t in (half.pose_correctives, half.eyelid_offsets) if t is not None) * 4
    assert AvatarRenderer(half, "cuda", precision=precision, layout="sparse").nbytes == packed + extra
    # The default dense layout: one [K, N x D] matrix in the storage precision.
    dense = AvatarRenderer(avatar, "cuda", precision=precision).device_avatar
    assert dense.layout == "dense" and dense.nbytes == dense.matrix.numel() * size
    # ... plus the two empty pair tables (N + 1 row pointers each) the device avatar keeps in place of the pairs.
    empty_tables = 2 * (avatar.num_gaussians + 1) * 4
    total = AvatarRenderer(avatar, "cuda", precision=precision).nbytes
    assert dense.nbytes <= total <= dense.nbytes + empty_tables + 64


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_nbytes_matches_the_gpu_memory_it_allocates(avatar):
    AvatarRenderer(avatar, "cuda")  # gsplat's extension and the CUDA context: loaded first, not counted
    torch.cuda.synchronize()
    before = torch.cuda.memory_allocated()
    renderer = AvatarRenderer(avatar, "cuda")
    torch.cuda.synchronize()
    allocated = torch.cuda.memory_allocated() - before
    # Everything of the avatar is copied to the GPU; the allocator rounds each tensor up to 512 bytes.
    assert renderer.nbytes > 0
    assert renderer.nbytes <= allocated <= renderer.nbytes + 512 * 64


@pytest.mark.parametrize("precision", ["fp32", "fp16", "bf16"])
def test_device_avatar_blends_only_the_stored_pairs_cpu_emulation(precision):
    """The cuda path's blend (DeviceAvatar, here on the CPU) reads the sparse layout of schema-2 bundles: only
    the non-zero (Gaussian, blendshape) pairs are on the device, and Eq. 1 over them equals the dense blend."""
    from render_core.deform import blend
    from render_core.renderer import DeviceAvatar

    avatar = synth_avatar(gaussians=500, blendshapes=7, seed=9, local=True)  # compact: most pairs are zero
    dense = avatar.dense_deltas()
    geometry = torch.cat([dense.means, dense.quats, dense.log_scales, dense.opacity_logits[..., None]], -1)
    dev = DeviceAvatar(avatar, "cpu", precision, "sparse")
    assert dev.deltas.geometry.count == int(geometry.ne(0).any(-1).sum()) < 500 * 7
    assert dev.deltas.color.count == int(dense.sh.flatten(2).ne(0).any(-1).sum())
    assert dev.nbytes < sum(t.numel() for t in dense.tensors().values()) * STORAGE_DTYPES[precision].itemsize
    psi = torch.rand(3, 7, generator=torch.Generator().manual_seed(1)) * 2 - 0.5
    want = blend(avatar.with_precision("fp32"), psi.to(STORAGE_DTYPES[precision]).float())
    got = dev.blend(psi)
    tol = {"fp32": 1e-6, "fp16": 2e-3, "bf16": 2e-2}[precision]
    for key, t in got.tensors().items():
        torch.testing.assert_close(t, getattr(want, key), atol=tol, rtol=tol, msg=key)
