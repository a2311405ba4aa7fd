"""render_core.host: small CPU tensors read, checked and joined through numpy (no torch call that gives the GIL up),
with torch's results; and the render thread's preparation of a batch built on it."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch

from render_core import host
from render_core.camera import Cameras, front_camera
from render_core.deform import Frame
from render_core.raster import native
from render_core.renderer import AvatarRenderer


def test_array_is_a_view_when_it_can_be_and_a_converted_copy_otherwise():
    t = torch.rand(4, 3)
    a = host.array(t)
    assert a.dtype == np.float32 and np.shares_memory(a, t.numpy())
    wide = host.array(t, np.float64)
    assert wide.dtype == np.float64 and np.array_equal(wide, t.numpy().astype(np.float64))
    strided = host.array(t.T)
    assert strided.flags.c_contiguous and np.array_equal(strided, t.numpy().T)
    expanded = host.array(t[:1].expand(5, 3))
    assert expanded.shape == (5, 3) and expanded.flags.c_contiguous
    grad = torch.rand(2, 3, requires_grad=True)
    assert np.array_equal(host.array(grad), grad.detach().numpy())
    assert host.array(torch.rand(2, 2, dtype=torch.bfloat16), np.float32).dtype == np.float32  # numpy has no bf16


@pytest.mark.parametrize("dtype", [torch.float16, torch.float32, torch.float64, torch.bfloat16])
def test_finite_finds_nan_and_infinity(dtype):
    assert host.finite(torch.zeros(3, dtype=dtype))
    for bad in (float("nan"), float("inf"), -float("inf")):
        t = torch.zeros(2, 3, dtype=dtype)
        t[1, 2] = bad
        assert not host.finite(t) and not host.finite(t.T)
    assert not host.finite(torch.tensor([1.0, float("nan")], requires_grad=True))


def test_cat_and_stack_are_torchs_and_keep_gradients():
    parts = [torch.rand(1, 4), torch.rand(2, 4), torch.rand(1, 4)]
    assert torch.equal(host.cat(parts), torch.cat(parts))
    assert torch.equal(host.stack([p[0] for p in parts]), torch.stack([p[0] for p in parts]))
    assert torch.equal(host.zeros((2, 3), like=parts[0]), torch.zeros(2, 3))
    assert host.zeros((1, 2), like=torch.rand(1, dtype=torch.float64)).dtype == torch.float64
    assert host.cat([torch.eye(3)[None].expand(2, 3, 3)]).shape == (2, 3, 3)
    mixed = host.cat([torch.rand(1, 2), torch.rand(1, 2, dtype=torch.float64)])  # torch's type promotion
    assert mixed.dtype == torch.float64
    leaf = torch.rand(1, 4, requires_grad=True)
    joined = host.cat([leaf, torch.rand(1, 4)])
    joined.sum().backward()
    assert joined.requires_grad and torch.equal(leaf.grad, torch.ones(1, 4))


def _torch_calls(fn):
    """The torch functions and tensor methods ``fn`` calls (by name)."""
    calls = []

    def hook(frame, event, arg):
        if event == "c_call":
            owner = getattr(arg, "__self__", None)
            if (getattr(arg, "__module__", None) or "").startswith("torch") or \
                    type(owner).__module__.startswith("torch"):
                calls.append(getattr(arg, "__name__", repr(arg)))

    sys.setprofile(hook)
    try:
        fn()
    finally:
        sys.setprofile(None)
    return calls


@pytest.mark.skipif(not native.available(), reason="the native backend is not built")
def test_a_batch_is_prepared_for_the_native_renderer_without_torch_calls(avatar):
    """What a render thread does before the native call (stack the frames and cameras, check them, convert them
    for the native entry point) calls torch only for numpy views: every other torch call gives the GIL up and may
    wait a switch interval to get it back behind the service's other Python threads."""
    renderer = AvatarRenderer(avatar, "native")
    k = avatar.num_expressions
    frames = [Frame(torch.rand(1, k) * 0.3, torch.eye(3).expand(1, avatar.num_joints, 3, 3).clone(),
                    torch.rand(1, 2) * 0.2 if i % 2 else None) for i in range(4)]
    cams = [front_camera(64, 64) for _ in frames]
    backgrounds = [torch.rand(3) for _ in frames]

    def prepare():
        frame, cameras, bg = Frame.stack(frames), Cameras.cat(cams), host.stack(backgrounds)
        renderer._cameras(frame, cameras)
        return renderer.native._inputs(frame.expression, frame.joint_rotations, frame.eyelids, cameras, bg)

    calls = _torch_calls(prepare)
    assert calls and set(calls) <= {"numpy", "from_numpy", "dim"}, calls  # dim() keeps the GIL

