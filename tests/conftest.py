import pytest
import torch

from render_core.synth import synth_avatar


@pytest.fixture(scope="session")
def avatar():
    """A small synthetic avatar (600 face Gaussians, 6 blendshapes, SH degree 3, 75 mouth Gaussians)."""
    return synth_avatar(gaussians=600, blendshapes=6, seed=3)


@pytest.fixture(autouse=True)
def _deterministic():
    torch.manual_seed(0)
