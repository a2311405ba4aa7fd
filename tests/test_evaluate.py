"""The metrics (the one PSNR and SSIM of training and evaluation) and the held-out evaluation (PSNR, SSIM, psnr_head;
LPIPS only with local weights; the contact sheet, or the reason it was skipped)."""

from __future__ import annotations

import json
import logging
import math

import numpy as np
import pytest
import torch

from render_core.errors import DatasetError
from render_core.evaluation.metrics import PSNR_CAP, psnr, psnr_from_mse, psnr_masked, ssim
from render_core.evaluation.report import evaluate
from render_core.tools.cli import main as cli


def _image(seed: int = 0, h: int = 24, w: int = 20) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(h, w, 3, generator=g, dtype=torch.float64)


def _blur(img: torch.Tensor) -> torch.Tensor:
    """3x3 box blur per channel (edges replicated)."""
    x = torch.nn.functional.pad(img.permute(2, 0, 1)[None], (1, 1, 1, 1), mode="replicate")
    return torch.nn.functional.avg_pool2d(x, 3, stride=1)[0].permute(1, 2, 0)


def _read_png(path):
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    assert inp is not None, oiio.geterror()
    spec = inp.spec()
    pixels = inp.read_image("uint8")
    inp.close()
    return spec.width, spec.height, spec.nchannels, pixels


# ---------------------------------------------------------------------------------------------------- metrics
def test_psnr_of_identical_images_is_capped_and_ssim_is_one():
    img = _image()
    assert psnr(img, img) == PSNR_CAP == 100.0  # documented cap instead of inf: reports stay standard JSON
    assert psnr_from_mse(0.0) == PSNR_CAP
    assert float(ssim(img, img)) == pytest.approx(1.0, abs=1e-12)
    assert psnr_masked(img, img, torch.ones(24, 20)) == PSNR_CAP


def test_known_mse_gives_known_psnr():
    a = torch.zeros(8, 8, 3, dtype=torch.float64)
    assert psnr(a, a + 0.1) == pytest.approx(20.0, abs=1e-9)  # MSE 0.01 -> 20 dB
    assert psnr(a, a + 0.01) == pytest.approx(40.0, abs=1e-9)  # MSE 1e-4 -> 40 dB
    b = a.clone()
    b[0, 0, 0] = 1.0  # one wrong value of 192: MSE 1/192
    assert psnr(a, b) == pytest.approx(10 * math.log10(192), abs=1e-9)
    assert psnr_from_mse(0.25) == pytest.approx(10 * math.log10(4), abs=1e-12)
    assert psnr(np.zeros((4, 4, 3)), np.full((4, 4, 3), 0.5)) == pytest.approx(10 * math.log10(4))  # numpy too


def test_psnr_head_uses_only_the_mask_pixels():
    gt = torch.zeros(10, 10, 3, dtype=torch.float64)
    mask = torch.zeros(10, 10)
    mask[2:6, 3:8] = 1.0  # 20 head pixels
    pred = gt.clone()
    pred[mask > 0] = 0.1  # error 0.1 everywhere inside: MSE 0.01 -> 20 dB
    assert psnr_masked(pred, gt, mask) == pytest.approx(20.0, abs=1e-9)
    assert psnr(pred, gt) == pytest.approx(10 * math.log10(100 / 0.2), abs=1e-9)  # full frame: 20% of the pixels
    noisy = pred.clone()
    noisy[mask == 0] = torch.rand(80, 3, dtype=noisy.dtype)  # the background changes, the head score does not
    assert psnr_masked(noisy, gt, mask) == pytest.approx(20.0, abs=1e-9)
    assert psnr(noisy, gt) < psnr(pred, gt)
    assert psnr_masked(pred, gt, torch.zeros(10, 10)) is None  # empty mask: no head score
    with pytest.raises(ValueError):
        psnr_masked(pred, gt, torch.ones(9, 10))


def test_psnr_of_8_bit_images_uses_their_data_range():
    a = np.zeros((4, 4, 3), np.uint8)
    assert psnr(a, np.full_like(a, 51), data_range=255) == pytest.approx(20 * math.log10(5))  # 51 = 255 / 5
    assert psnr(a, a, data_range=255) == PSNR_CAP
    with pytest.raises(ValueError, match="shapes differ"):
        psnr(a, a[:3])


def test_ssim_of_a_blurred_copy_is_below_one_and_symmetric():
    img = _image(1)
    blurred = _blur(img)
    s = float(ssim(img, blurred))
    assert 0.0 < s < 0.99
    assert float(ssim(blurred, img)) == pytest.approx(s, abs=1e-12)
    batch = ssim(torch.stack([img, img]), torch.stack([img, blurred]), reduction="none")
    assert batch.shape == (2,) and batch[0].item() == pytest.approx(1.0) and batch[1].item() == pytest.approx(s)
    assert float(ssim(torch.stack([img, img]), torch.stack([img, blurred]))) == pytest.approx((1 + s) / 2)
    assert ssim(img, blurred, reduction="none").shape == ()  # one image, one value
    assert float(ssim(img[..., 0], blurred[..., 0])) < 1.0  # greyscale [H, W]
    assert float(ssim(img.numpy(), blurred.numpy())) == pytest.approx(s, abs=1e-12)  # numpy too


def test_ssim_of_a_constant_offset_matches_the_formula():
    # Constant images: variances and covariance are 0, so SSIM = (2 mx my + C1) / (mx^2 + my^2 + C1) exactly.
    a, b = torch.full((16, 16, 3), 0.2, dtype=torch.float64), torch.full((16, 16, 3), 0.6, dtype=torch.float64)
    c1 = 0.01 ** 2
    assert float(ssim(a, b)) == pytest.approx((2 * 0.2 * 0.6 + c1) / (0.2 ** 2 + 0.6 ** 2 + c1), rel=1e-9)


def _direct_ssim(x: np.ndarray, y: np.ndarray, padding: str) -> float:
    """SSIM written out window by window (2-D Gaussian weights, 11 x 11, sigma 1.5), as a check of the separable,
    batched implementation. ``padding="same"`` pads with zeros by 5 pixels."""
    r = np.arange(11) - 5.0
    g = np.exp(-(r ** 2) / (2 * 1.5 ** 2))
    win = np.outer(g, g) / np.outer(g, g).sum()
    if padding == "same":
        x, y = (np.pad(v, ((5, 5), (5, 5), (0, 0))) for v in (x, y))
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    values = []
    for i in range(x.shape[0] - 10):
        for j in range(x.shape[1] - 10):
            for c in range(x.shape[2]):
                px, py = x[i:i + 11, j:j + 11, c], y[i:i + 11, j:j + 11, c]
                mx, my = (win * px).sum(), (win * py).sum()
                vx, vy = (win * px * px).sum() - mx ** 2, (win * py * py).sum() - my ** 2
                cxy = (win * px * py).sum() - mx * my
                values.append((2 * mx * my + c1) * (2 * cxy + c2) / ((mx ** 2 + my ** 2 + c1) * (vx + vy + c2)))
    return float(np.mean(values))


def test_ssim_conventions_match_a_direct_computation():
    a, b = _image(2, 16, 14), _blur(_image(3, 16, 14))
    valid = float(ssim(a, b, padding="valid"))
    same = float(ssim(a, b, padding="same"))
    assert valid == pytest.approx(_direct_ssim(a.numpy(), b.numpy(), "valid"), abs=1e-12)
    assert same == pytest.approx(_direct_ssim(a.numpy(), b.numpy(), "same"), abs=1e-12)
    assert abs(same - valid) > 1e-3  # the border convention matters: training and evaluation each name theirs
    for kwargs in ({"padding": "reflect"}, {"reduction": "sum"}, {"padding": "same", "window": 10}):
        with pytest.raises(ValueError):
            ssim(a, b, **kwargs)
    with pytest.raises(ValueError, match="one shape"):
        ssim(a, b[:8])
    small = _image(4, 6, 7)  # smaller than the window: "valid" shrinks the window to the image
    assert float(ssim(small, small)) == pytest.approx(1.0) and float(ssim(small, _blur(small))) < 1.0


def _pattern(b: int = 2, h: int = 20, w: int = 23) -> torch.Tensor:
    y, x = torch.arange(h, dtype=torch.float64)[:, None], torch.arange(w, dtype=torch.float64)[None, :]
    return torch.stack([torch.stack([0.5 + 0.4 * torch.sin(0.3 * x + 0.2 * y + k),
                                     0.5 + 0.4 * torch.cos(0.25 * y - 0.1 * x * k),
                                     0.5 + 0.3 * torch.sin(0.05 * x * y + k)], -1) for k in range(b)])


def test_ssim_keeps_the_numbers_of_the_former_loss_and_evaluation_ssims():
    # Values of the two SSIMs this one replaced (the training loss's zero-padded float32 one and the evaluation's
    # valid-window float64 one), on a fixed pattern: training and reported results do not change.
    a, t = _pattern(), _pattern().flip(2)
    assert ssim(a.float(), t.float(), padding="same").item() == pytest.approx(0.4568280577659607, rel=1e-6)
    assert ssim(a, t, reduction="none").tolist() == pytest.approx([0.38848313530364503, 0.14633355242198048],
                                                                 abs=1e-12)


def test_the_training_loss_uses_the_same_ssim_zero_padded_and_differentiable():
    from render_core.train.losses import RGB_DSSIM, MouthCylinder, total_loss

    g = torch.Generator().manual_seed(0)
    target = _pattern(1).float()
    rgb = (target + 0.05 * torch.randn(target.shape, generator=g)).clamp(0, 1).requires_grad_()
    mask = torch.ones(1, 20, 23)
    cylinder = MouthCylinder.from_points(torch.zeros(2, 3))
    loss, terms = total_loss(rgb, mask, target, mask, torch.zeros(2, 3), cylinder)
    assert terms["ssim"].dtype == torch.float32
    assert torch.equal(terms["ssim"], ssim(rgb, target, padding="same"))  # the same code, same border convention
    assert not torch.equal(terms["ssim"], ssim(rgb, target))
    (grad,) = torch.autograd.grad(RGB_DSSIM * (1 - ssim(rgb, target, padding="same")), rgb)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0
    loss.backward()
    assert torch.isfinite(rgb.grad).all()


# ------------------------------------------------------------------------------------------------- evaluation
@pytest.fixture(scope="module")
def scene(head, tmp_path_factory):
    from render_core.data.generate import synth_dataset
    from render_core.train.initialize import init_avatar

    root = tmp_path_factory.mktemp("evaluate")
    summary = synth_dataset(root / "ds", frames=6, size=48, seed=1, facemodel=head)
    avatar = init_avatar(head, gaussians=400, mouth=20, opacity=0.9, seed=0)
    return root, summary, avatar


def test_evaluate_reports_every_held_out_frame(scene, monkeypatch):
    monkeypatch.delenv("BLENDSPLAT_LPIPS_WEIGHTS", raising=False)
    root, summary, avatar = scene
    result = evaluate(avatar, root / "ds", batch=4, contact_sheet=root / "sheet.png", report=root / "report.json")
    for key in ("psnr", "ssim", "psnr_head", "lpips", "frames", "split", "per_frame", "bundle", "data", "notes"):
        assert key in result
    assert result["frames"] == summary["test"] == len(result["per_frame"]) >= 1
    assert result["split"] == "test" and result["bundle"] is None and result["data"] == str(root / "ds")
    for key in ("psnr", "ssim", "psnr_head"):
        assert math.isfinite(result[key])
    assert 0.0 < result["ssim"] < 1.0 and 0.0 < result["psnr"] < PSNR_CAP
    assert result["lpips"] is None and any("lpips" in n for n in result["notes"])  # no local weights here
    assert result["psnr"] == pytest.approx(np.mean([r["psnr"] for r in result["per_frame"]]))

    saved = json.loads((root / "report.json").read_text())
    assert saved["psnr"] == pytest.approx(result["psnr"]) and saved["frames"] == result["frames"]
    assert result["contact_sheet"] == str(root / "sheet.png")
    assert result["plots"] == {"contact_sheet": str(root / "sheet.png")}
    # The file names files relative to its folder, others by name: never this machine's absolute paths (a training
    # job's report is served to API clients).
    assert (saved["contact_sheet"], saved["plots"], saved["report"]) == ("sheet.png", {"contact_sheet": "sheet.png"},
                                                                         "report.json")
    assert saved["data"] == "ds" and saved["bundle"] is None
    assert str(root) not in (root / "report.json").read_text()
    w, h, c, px = _read_png(root / "sheet.png")
    rows = min(4, result["frames"])
    assert c == 4 and w > 2 * 48 and h > 48 * rows
    assert px[..., :3].std() > 10  # not blank


def test_evaluate_all_frames_in_batches_and_from_a_bundle(scene, capsys, monkeypatch):
    from render_core.bundle import write_bundle

    monkeypatch.delenv("BLENDSPLAT_LPIPS_WEIGHTS", raising=False)
    root, summary, avatar = scene
    write_bundle(avatar, root / "avatar.bsplat")
    one = evaluate(avatar, root / "ds", split="all", batch=4)
    other = evaluate(root / "avatar.bsplat", root / "ds", split="all", batch=5)
    assert one["frames"] == other["frames"] == summary["frames"]
    assert [r["index"] for r in other["per_frame"]] == list(range(summary["frames"]))
    assert other["bundle"] == str(root / "avatar.bsplat")
    assert other["psnr"] == pytest.approx(one["psnr"], abs=1e-3)  # batch size does not matter

    assert cli(["eval", "--bundle", str(root / "avatar.bsplat"), "--data", str(root / "ds"), "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert {"psnr", "ssim", "psnr_head", "frames"} <= set(printed) and printed["lpips"] is None


def test_evaluate_reports_lpips_when_its_weights_are_local(scene, monkeypatch, tmp_path, capsys):
    from safetensors.torch import save_file

    from tests.test_lpips import random_weights

    root, summary, avatar = scene
    save_file(random_weights(), str(tmp_path / "alex.safetensors"))
    monkeypatch.setenv("BLENDSPLAT_LPIPS_WEIGHTS", str(tmp_path / "alex.safetensors"))
    result = evaluate(avatar, root / "ds")
    assert result["lpips"] is not None and result["lpips"] > 0
    assert all(r["lpips"] is not None and r["lpips"] > 0 for r in result["per_frame"])
    assert result["lpips"] == pytest.approx(np.mean([r["lpips"] for r in result["per_frame"]]))
    assert any("alex.safetensors" in n for n in result["notes"])
    from render_core.bundle import write_bundle

    write_bundle(avatar, tmp_path / "a.bsplat")
    assert cli(["eval", "--bundle", str(tmp_path / "a.bsplat"), "--data", str(root / "ds")]) == 0
    out = capsys.readouterr().out
    assert "LPIPS " in out and "LPIPS n/a" not in out
    # An unusable file: lpips is null and the note says why; the other metrics are unaffected.
    monkeypatch.setenv("BLENDSPLAT_LPIPS_WEIGHTS", str(tmp_path / "nothing.safetensors"))
    result = evaluate(avatar, root / "ds")
    assert result["lpips"] is None and any("nothing.safetensors" in n for n in result["notes"])


def test_evaluate_rejects_a_mismatched_avatar_and_bad_arguments(scene):
    from render_core.tools.synth import synth_avatar

    root, _, avatar = scene
    with pytest.raises(DatasetError, match="cannot be evaluated on .*expressions"):
        evaluate(synth_avatar(gaussians=50, blendshapes=3), root / "ds")
    with pytest.raises(ValueError, match="split"):
        evaluate(avatar, root / "ds", split="val")
    with pytest.raises(DatasetError):
        evaluate(avatar, root / "missing")


def test_evaluate_without_matplotlib_writes_the_numbers_and_says_why_the_sheet_was_skipped(scene, monkeypatch,
                                                                                          tmp_path, caplog, capsys):
    from tests.test_plot import hide_matplotlib

    monkeypatch.delenv("BLENDSPLAT_LPIPS_WEIGHTS", raising=False)
    root, summary, avatar = scene
    hide_matplotlib(monkeypatch)
    with caplog.at_level(logging.WARNING, logger="render_core.evaluation"):
        result = evaluate(avatar, root / "ds", contact_sheet=tmp_path / "sheet.png", report=tmp_path / "report.json")
    reason = result["plots"]["skipped"]
    assert "matplotlib is not installed" in reason and "blendsplat[train]" in reason
    assert result["contact_sheet"] is None and not (tmp_path / "sheet.png").exists()
    assert any(reason in n for n in result["notes"]) and reason in caplog.text
    assert capsys.readouterr().out == ""  # logged, not printed
    saved = json.loads((tmp_path / "report.json").read_text())
    assert saved["plots"] == {"skipped": reason} and saved["frames"] == result["frames"] >= 1
    assert math.isfinite(saved["psnr"]) and math.isfinite(saved["ssim"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.json"]  # no temporary file left behind
    from render_core.bundle import write_bundle

    write_bundle(avatar, tmp_path / "a.bsplat")
    caplog.clear()
    assert cli(["eval", "--bundle", str(tmp_path / "a.bsplat"), "--data", str(root / "ds"),
                "--contact-sheet", str(tmp_path / "sheet.png")]) == 0
    assert f"contact sheet skipped: {reason}" in caplog.text  # the command line says so (stderr)
    assert "PSNR" in capsys.readouterr().out


def test_the_metrics_examples_run():
    import doctest

    from render_core.evaluation import metrics

    result = doctest.testmod(metrics)
    assert result.attempted >= 8 and result.failed == 0
