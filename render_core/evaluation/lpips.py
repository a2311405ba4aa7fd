"""LPIPS (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a Perceptual Metric"), AlexNet
variant v0.1, in plain torch: no torchvision, no ``lpips`` package, and never a download.

The distance between two images: both scaled to [-1, 1], shifted and scaled per channel (shift -0.030, -0.088,
-0.188; scale 0.458, 0.448, 0.450), passed through AlexNet's five convolution + ReLU stages (64, 192, 384, 256,
256 channels; 3x3 stride-2 max pools after the first two); at each stage the features are normalised to unit
length over channels, their squared difference is weighted per channel by a learned non-negative 1x1
convolution, averaged over the positions, and the five stage values are summed. Images need at least 31 x 31
pixels (the second pool's output is then 1 x 1).

Weights come from a local file (:func:`load_weights`; evaluation reads the path from ``BLENDSPLAT_LPIPS_WEIGHTS``):
safetensors (preferred) or a torch ``.pth``/``.pt`` state dict, loaded with ``weights_only=True``. Keys are those of
the ``lpips`` package's ``LPIPS(net="alex")`` state dict::

    net.slice1.0.weight  [64, 3, 11, 11]    net.slice1.0.bias  [64]     (torchvision alexnet features.0)
    net.slice2.3.weight  [192, 64, 5, 5]    net.slice2.3.bias  [192]    (features.3)
    net.slice3.6.weight  [384, 192, 3, 3]   net.slice3.6.bias  [384]    (features.6)
    net.slice4.8.weight  [256, 384, 3, 3]   net.slice4.8.bias  [256]    (features.8)
    net.slice5.10.weight [256, 256, 3, 3]   net.slice5.10.bias [256]    (features.10)
    lin0.model.1.weight  [1, 64, 1, 1]  ...  lin4.model.1.weight [1, 256, 1, 1]

(other keys, such as ``scaling_layer.shift``, are ignored). Converting the official weights, on a machine that has
them (the ``lpips`` package bundles the linear layers; torchvision supplies AlexNet)::

    import lpips
    from safetensors.torch import save_file

    state = lpips.LPIPS(net="alex", version="0.1").state_dict()
    save_file({k: v.contiguous() for k, v in state.items() if k.startswith(("net.", "lin"))},
              "lpips_alex_v0.1.safetensors")

or, from the two files themselves (torchvision's ``alexnet-owt-7be5be79.pth`` and lpips's
``weights/v0.1/alex.pth``): ``net.sliceS.I.{weight,bias}`` = ``features.I.{weight,bias}`` for
(S, I) = (1, 0), (2, 3), (3, 6), (4, 8), (5, 10), and the ``lin*`` tensors as they are.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from torch import Tensor, nn

ENV = "BLENDSPLAT_LPIPS_WEIGHTS"
MIN_SIZE = 31  # pixels (both sides)
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
# (key prefix, in channels, out channels, kernel, stride, padding, max pool before)
STAGES = (
    ("net.slice1.0", 3, 64, 11, 4, 2, False),
    ("net.slice2.3", 64, 192, 5, 1, 2, True),
    ("net.slice3.6", 192, 384, 3, 1, 1, True),
    ("net.slice4.8", 384, 256, 3, 1, 1, False),
    ("net.slice5.10", 256, 256, 3, 1, 1, False),
)


def expected_shapes() -> dict[str, tuple[int, ...]]:
    """Every key the weights need, with its shape."""
    out: dict[str, tuple[int, ...]] = {}
    for i, (key, cin, cout, k, _, _, _) in enumerate(STAGES):
        out[key + ".weight"] = (cout, cin, k, k)
        out[key + ".bias"] = (cout,)
        out[f"lin{i}.model.1.weight"] = (1, cout, 1, 1)
    return out


def load_weights(path: str | os.PathLike) -> dict[str, Tensor]:
    """The LPIPS AlexNet tensors from ``path`` (safetensors, or a torch state dict loaded with weights_only=True),
    checked: ValueError naming the key that is missing or has the wrong shape; FileNotFoundError if absent."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"LPIPS weights file {path} does not exist")
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        state = load_file(str(path))
    elif path.suffix in (".pth", ".pt"):
        state = torch.load(path, map_location="cpu", weights_only=True)
        if not isinstance(state, dict):
            raise ValueError(f"{path}: expected a state dict of tensors, got {type(state).__name__}")
    else:
        raise ValueError(f"{path}: LPIPS weights must be a .safetensors (or .pth / .pt) file")
    out = {}
    for key, shape in expected_shapes().items():
        t = state.get(key)
        if not isinstance(t, Tensor):
            raise ValueError(f"{path}: LPIPS weights lack {key!r} (shape {list(shape)})")
        if tuple(t.shape) != shape:
            raise ValueError(f"{path}: LPIPS weight {key!r} has shape {list(t.shape)}, expected {list(shape)}")
        if not torch.isfinite(t).all():
            raise ValueError(f"{path}: LPIPS weight {key!r} is not finite")
        out[key] = t.detach().float().contiguous()
    return out


class LPIPS(nn.Module):
    """LPIPS distance (AlexNet, v0.1) between batches of images.

    Example::

        metric = LPIPS.from_file("lpips_alex_v0.1.safetensors")
        d = metric(pred, target)  # [B], pred/target [B, H, W, 3] in [0, 1]
    """

    def __init__(self, weights: dict[str, Tensor]):
        super().__init__()
        self.convs = nn.ModuleList()
        self.lins = nn.ParameterList()
        for i, (key, cin, cout, k, stride, pad, _) in enumerate(STAGES):
            conv = nn.Conv2d(cin, cout, k, stride=stride, padding=pad)
            conv.weight.data.copy_(weights[key + ".weight"])
            conv.bias.data.copy_(weights[key + ".bias"])
            self.convs.append(conv)
            self.lins.append(nn.Parameter(weights[f"lin{i}.model.1.weight"].clone()))
        self.register_buffer("shift", torch.tensor(SHIFT).reshape(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).reshape(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    @classmethod
    def from_file(cls, path: str | os.PathLike) -> LPIPS:
        return cls(load_weights(path))

    def features(self, x: Tensor) -> list[Tensor]:
        """The five ReLU outputs for images [B, 3, H, W] in [-1, 1]."""
        h = (x - self.shift) / self.scale
        out = []
        for conv, (*_, pool) in zip(self.convs, STAGES, strict=True):
            if pool:
                h = nn.functional.max_pool2d(h, kernel_size=3, stride=2)
            h = torch.relu(conv(h))
            out.append(h)
        return out

    def forward(
        self,
        pred: Tensor,  # [B, H, W, 3] in [0, 1]
        target: Tensor,  # [B, H, W, 3] in [0, 1]
    ) -> Tensor:
        """LPIPS [B] (0 for identical images). Both [B, H, W, 3] (or [H, W, 3]) in [0, 1], H and W >= 31."""
        if pred.shape != target.shape:
            raise ValueError(f"LPIPS needs images of one shape, got {list(pred.shape)} and {list(target.shape)}")
        if pred.dim() == 3:
            pred, target = pred[None], target[None]
        if pred.dim() != 4 or pred.shape[-1] != 3:
            raise ValueError(f"LPIPS needs RGB images [B, H, W, 3], got {list(pred.shape)}")
        if min(pred.shape[1], pred.shape[2]) < MIN_SIZE:
            raise ValueError(f"LPIPS (AlexNet) needs images of at least {MIN_SIZE} x {MIN_SIZE} pixels, got "
                             f"{pred.shape[2]} x {pred.shape[1]}")
        dtype = self.shift.dtype
        x = pred.to(dtype).permute(0, 3, 1, 2) * 2 - 1
        y = target.to(dtype).permute(0, 3, 1, 2) * 2 - 1
        with torch.no_grad():
            total = torch.zeros(x.shape[0], dtype=dtype, device=x.device)
            for fx, fy, lin in zip(self.features(x), self.features(y), self.lins, strict=True):
                nx = fx / (fx.square().sum(1, keepdim=True).sqrt() + 1e-10)
                ny = fy / (fy.square().sum(1, keepdim=True).sqrt() + 1e-10)
                total = total + nn.functional.conv2d((nx - ny).square(), lin).mean(dim=(1, 2, 3))
        return total


def from_environment() -> tuple[LPIPS | None, str]:
    """(the metric, a note) from the file ``$BLENDSPLAT_LPIPS_WEIGHTS`` names; (None, why) when it is unset or
    unusable."""
    path = os.environ.get(ENV, "").strip()
    if not path:
        return None, (f"lpips is null: no LPIPS weights (set {ENV} to a local safetensors file of the LPIPS AlexNet "
                      "weights, see render_core/evaluation/lpips.py; evaluation never downloads them)")
    try:
        return LPIPS.from_file(path), f"lpips: AlexNet v0.1 with the weights in {path}, inputs scaled to [-1, 1]"
    except (OSError, ValueError, RuntimeError) as e:
        return None, f"lpips is null: {ENV}={path} is unusable ({type(e).__name__}: {e})"
