"""AvatarRenderer.nbytes: the memory a renderer holds for its avatar, host or device, for every backend."""

import pytest
import torch

from render_core.raster import native
from render_core.renderer import AvatarRenderer
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
    renderer = AvatarRenderer(avatar, "cuda", precision=precision)
    dev = renderer.device_avatar
    n, k = avatar.num_gaussians, avatar.num_expressions
    width = sum(dev.widths)
    packed = n * width * 4 + k * n * width * {"fp32": 4, "fp16": 2, "bf16": 2}[precision]
    assert dev.nbytes == packed
    # On the CPU the float32 tensors skinning reads are the avatar's own: only the packed matrix is new.
    assert renderer.nbytes == packed
    # An fp16 avatar's pose correctives and eyelid offsets get float32 copies on the device too.
    half = avatar.with_precision("fp16")
    extra = sum(t.numel() for t in (half.pose_correctives, half.eyelid_offsets) if t is not None) * 4
    assert AvatarRenderer(half, "cuda", precision=precision).nbytes == packed + extra


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
