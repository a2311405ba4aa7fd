"""Training: learn Gaussian blendshapes from a tracked video (docs/method.md sections 3-6).

- :mod:`.model`: the trainable avatar with the blendshape-consistency parametrisation (Eq. 2) and its ablations;
- :mod:`.geometry`: closest surface points and per-blendshape displacement magnitudes d_{i,k};
- :mod:`.grids`: the lazily built 256^3 lookup grid of LBS weights and d_{i,k} (densified and moved Gaussians);
- :mod:`.densify`: densification and pruning (gradient, opacity, world and screen size) as a strategy that owns
  its schedule;
- :mod:`.prune`: pruning by contribution (each face Gaussian's summed blending weight alpha T on training frames),
  off unless the preset asks for it (``train --prune``);
- :mod:`.poses`: per-frame rigid corrections of the tracked head poses, learnt with the avatar (``train
  --refine-poses``);
- :mod:`.losses`: L1, D-SSIM, alpha MSE, mouth-cylinder regulariser;
- :mod:`.trainer`: :class:`Trainer` (step, checkpoint, exact resume, progress events, cancel between steps) and
  :func:`train`, the whole run (presets in :mod:`.presets`).
"""

from .densify import DensifyStrategy
from .model import CONSISTENCY, TrainableAvatar
from .presets import PRESETS, Preset, get_preset
from .trainer import Outcome, Progress, Trainer, train

__all__ = ["CONSISTENCY", "PRESETS", "DensifyStrategy", "Outcome", "Preset", "Progress", "TrainableAvatar",
           "Trainer", "get_preset", "train"]
