"""Small CPU tensors read, checked and joined through numpy, without giving the GIL up.

Most torch calls release the GIL while they run and must take it back afterwards; taking it back waits for the
interpreter's switch interval whenever another Python thread is running. A service renders on one thread while its
event loop, encoders and network threads run Python beside it, so each of the few dozen small torch calls that
prepare a batch (stack the poses, check them, hand them to the native renderer) could wait that long: a frame
check of 0.27 ms took 31 ms beside one busy Python thread, the native renderer's input checks 0.2 ms took 25 ms.
numpy keeps the GIL for arrays this small, and a CPU tensor's ``.numpy()`` is a view, not a torch call.

Tensors on another device, or that need a gradient, go through torch as before.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

_NUMPY = {torch.float16: np.float16, torch.float32: np.float32, torch.float64: np.float64, torch.int32: np.int32,
          torch.int64: np.int64, torch.uint8: np.uint8, torch.bool: np.bool_}
_TORCH = {np.dtype(v): k for k, v in _NUMPY.items()}


def _viewable(t: Tensor) -> bool:
    return t.device.type == "cpu" and not t.requires_grad and t.dtype in _NUMPY


def array(t: Tensor, dtype: type | None = None) -> np.ndarray:
    """``t`` as a C-contiguous host array of ``dtype`` (default: its own): ``t``'s memory when that is already
    so (a view), else a copy."""
    if _viewable(t):
        a = t.numpy()
        return np.ascontiguousarray(a, dtype=dtype) if dtype is not None else np.ascontiguousarray(a)
    torch_dtype = _TORCH[np.dtype(dtype)] if dtype is not None else None
    return t.detach().to(device="cpu", dtype=torch_dtype).contiguous().numpy()


def finite(t: Tensor) -> bool:
    """Whether every value of ``t`` is finite."""
    if _viewable(t):
        return bool(np.isfinite(t.numpy()).all())
    return bool(torch.isfinite(t).all())


def zeros(shape: tuple[int, ...], like: Tensor) -> Tensor:
    """``torch.zeros(shape)`` of ``like``'s dtype and device."""
    if _viewable(like):
        return torch.from_numpy(np.zeros(shape, _NUMPY[like.dtype]))
    return torch.zeros(shape, dtype=like.dtype, device=like.device)


def cat(tensors: Sequence[Tensor]) -> Tensor:
    """``torch.cat(tensors)`` (along the first dimension)."""
    if tensors and all(_viewable(t) for t in tensors) and len({t.dtype for t in tensors}) == 1:
        return torch.from_numpy(np.concatenate([t.numpy() for t in tensors]))
    return torch.cat(list(tensors))


def stack(tensors: Sequence[Tensor]) -> Tensor:
    """``torch.stack(tensors)`` (a new first dimension)."""
    if tensors and all(_viewable(t) for t in tensors) and len({t.dtype for t in tensors}) == 1:
        return torch.from_numpy(np.stack([t.numpy() for t in tensors]))
    return torch.stack(list(tensors))
