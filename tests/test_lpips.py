"""LPIPS in plain torch (render_core.evaluation.lpips): weight loading, the distance's plumbing, evaluation's use of it.

The official weights are not available here: random weights (non-negative linear layers, like the trained ones)
saved to a temporary file stand in for them."""

from __future__ import annotations

import pytest
import torch
from safetensors.torch import save_file

from render_core.evaluation.lpips import ENV, LPIPS, expected_shapes, from_environment, load_weights


def random_weights(seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    out = {}
    for key, shape in expected_shapes().items():
        t = torch.randn(shape, generator=g) * 0.1
        out[key] = t.abs() if key.startswith("lin") else t
    out["scaling_layer.shift"] = torch.zeros(1, 3, 1, 1)  # extra keys of the lpips package are ignored
    return out


@pytest.fixture(scope="module")
def weights_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("lpips") / "alex.safetensors"
    save_file(random_weights(), str(path))
    return path


def test_identical_images_give_zero_and_different_ones_a_positive_symmetric_distance(weights_file):
    metric = LPIPS.from_file(weights_file)
    g = torch.Generator().manual_seed(1)
    a = torch.rand(3, 40, 48, 3, generator=g)
    b = (a + 0.2 * torch.randn(a.shape, generator=g)).clamp(0, 1)
    same = metric(a, a)
    assert same.shape == (3,) and torch.equal(same, torch.zeros(3))
    d = metric(a, b)
    assert d.shape == (3,) and bool((d > 0).all())
    torch.testing.assert_close(metric(b, a), d)
    assert metric(a[0], b[0]).shape == (1,)  # one [H, W, 3] image
    # A per-image distance: the batch does not mix images.
    torch.testing.assert_close(metric(a[1:2], b[1:2]), d[1:2])


def test_the_distance_follows_the_lpips_definition(weights_file):
    """Stage by stage: unit-normalised features, squared difference, the linear layer, spatial mean, summed."""
    w = load_weights(weights_file)
    metric = LPIPS(w)
    g = torch.Generator().manual_seed(2)
    a, b = torch.rand(1, 33, 35, 3, generator=g), torch.rand(1, 33, 35, 3, generator=g)

    def feats(img):
        x = img.permute(0, 3, 1, 2) * 2 - 1
        x = (x - torch.tensor([-0.030, -0.088, -0.188]).reshape(1, 3, 1, 1)) / \
            torch.tensor([0.458, 0.448, 0.450]).reshape(1, 3, 1, 1)
        out = []
        for i, (key, stride, pad, pool) in enumerate([("net.slice1.0", 4, 2, False), ("net.slice2.3", 1, 2, True),
                                                      ("net.slice3.6", 1, 1, True), ("net.slice4.8", 1, 1, False),
                                                      ("net.slice5.10", 1, 1, False)]):
            if pool:
                x = torch.nn.functional.max_pool2d(x, 3, 2)
            x = torch.relu(torch.nn.functional.conv2d(x, w[key + ".weight"], w[key + ".bias"], stride, pad))
            out.append((x, w[f"lin{i}.model.1.weight"]))
        return out

    want = 0.0
    for (fa, lin), (fb, _) in zip(feats(a), feats(b), strict=True):
        na = fa / (fa.norm(dim=1, keepdim=True) + 1e-10)
        nb = fb / (fb.norm(dim=1, keepdim=True) + 1e-10)
        want += float(((na - nb) ** 2 * lin.reshape(1, -1, 1, 1)).sum(1).mean())
    assert float(metric(a, b)[0]) == pytest.approx(want, rel=1e-5)


def test_bad_weights_and_inputs_are_errors_that_name_the_problem(tmp_path, weights_file):
    w = random_weights()
    del w["lin3.model.1.weight"]
    save_file(w, str(tmp_path / "missing.safetensors"))
    with pytest.raises(ValueError, match="lin3.model.1.weight"):
        load_weights(tmp_path / "missing.safetensors")
    w = random_weights()
    w["net.slice2.3.weight"] = torch.zeros(192, 64, 3, 3)
    save_file(w, str(tmp_path / "shape.safetensors"))
    with pytest.raises(ValueError, match=r"net.slice2.3.weight.*\[192, 64, 3, 3\].*\[192, 64, 5, 5\]"):
        load_weights(tmp_path / "shape.safetensors")
    with pytest.raises(FileNotFoundError, match="nowhere"):
        load_weights(tmp_path / "nowhere.safetensors")
    with pytest.raises(ValueError, match=r"\.safetensors"):
        (tmp_path / "w.npz").write_bytes(b"x")
        load_weights(tmp_path / "w.npz")
    # A torch state dict is read with weights_only=True (the same tensors give the same metric).
    torch.save(random_weights(), tmp_path / "alex.pth")
    g = torch.Generator().manual_seed(3)
    a, b = torch.rand(1, 32, 32, 3, generator=g), torch.rand(1, 32, 32, 3, generator=g)
    torch.testing.assert_close(LPIPS.from_file(tmp_path / "alex.pth")(a, b), LPIPS.from_file(weights_file)(a, b))
    metric = LPIPS.from_file(weights_file)
    with pytest.raises(ValueError, match="at least 31 x 31"):
        metric(torch.rand(1, 30, 64, 3), torch.rand(1, 30, 64, 3))
    with pytest.raises(ValueError, match="one shape"):
        metric(torch.rand(1, 32, 32, 3), torch.rand(1, 32, 33, 3))


def test_the_environment_names_the_weights(monkeypatch, weights_file, tmp_path):
    monkeypatch.delenv(ENV, raising=False)
    metric, note = from_environment()
    assert metric is None and ENV in note and "never downloads" in note
    monkeypatch.setenv(ENV, str(tmp_path / "absent.safetensors"))
    metric, note = from_environment()
    assert metric is None and "absent.safetensors" in note
    monkeypatch.setenv(ENV, str(weights_file))
    metric, note = from_environment()
    assert isinstance(metric, LPIPS) and str(weights_file) in note
