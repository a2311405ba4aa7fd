"""Held-out evaluation (PSNR, SSIM, psnr_head; LPIPS only with local weights) and the loss-curve plot."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from render_core.errors import DatasetError
from render_core.evaluation.plot import nice_ticks, plot_curves
from render_core.evaluation.report import (
    PSNR_CAP,
    evaluate,
    psnr,
    psnr_from_mse,
    psnr_masked,
    run_eval,
    ssim,
    ssim_batch,
)


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
    assert ssim(img, img) == pytest.approx(1.0, abs=1e-12)
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


def test_ssim_of_a_blurred_copy_is_below_one_and_symmetric():
    img = _image(1)
    blurred = _blur(img)
    s = ssim(img, blurred)
    assert 0.0 < s < 0.99
    assert ssim(blurred, img) == pytest.approx(s, abs=1e-12)
    batch = ssim_batch(torch.stack([img, img]), torch.stack([img, blurred]))
    assert batch[0].item() == pytest.approx(1.0) and batch[1].item() == pytest.approx(s)
    assert ssim(img[..., 0], blurred[..., 0]) < 1.0  # greyscale [H, W]


def test_ssim_of_a_constant_offset_matches_the_formula():
    # Constant images: variances and covariance are 0, so SSIM = (2 mx my + C1) / (mx^2 + my^2 + C1) exactly.
    a, b = torch.full((16, 16, 3), 0.2, dtype=torch.float64), torch.full((16, 16, 3), 0.6, dtype=torch.float64)
    c1 = 0.01 ** 2
    assert ssim(a, b) == pytest.approx((2 * 0.2 * 0.6 + c1) / (0.2 ** 2 + 0.6 ** 2 + c1), rel=1e-9)


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
    w, h, c, px = _read_png(root / "sheet.png")
    assert c == 3 and w > 2 * 48 and h > 48 * result["frames"]
    assert px.max() > 100  # not blank


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

    assert run_eval(root / "avatar.bsplat", root / "ds", as_json=True) == 0
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
    assert run_eval(avatar, root / "ds", as_json=False) == 0
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


# ------------------------------------------------------------------------------------------------------- plot
def test_plot_curves_writes_a_png_of_the_expected_size(tmp_path):
    log = tmp_path / "log.jsonl"
    with open(log, "w") as f:
        for i in range(0, 200, 10):
            f.write(json.dumps({"iteration": i, "loss": 0.3 * math.exp(-i / 50) + 0.02, "l1": 0.1, "ssim": 0.9,
                                "alpha": 0.01, "psnr": 15 + i / 20, "seconds": i * 0.1}) + "\n")
        f.write('{"iteration": 200, "loss": 0.0')  # a line being written: skipped
    out = plot_curves(log, tmp_path / "plots" / "curves.png")
    w, h, c, px = _read_png(out)
    assert (w, h, c) == (640, 400, 3)
    assert (px != 255).any(axis=2).mean() > 0.01  # axes, grid, text and curves drawn
    blue = (px == (31, 119, 180)).all(axis=2)
    assert blue[:200].sum() > 100 and blue[200:].sum() == 0  # the first key's curve stays in its panel
    out = plot_curves(log, tmp_path / "one.png", keys=("psnr", "missing"), width=300, panel_height=120)
    assert _read_png(out)[:3] == (300, 240, 3)


def test_nice_ticks_are_round_and_cover_the_range():
    ticks = nice_ticks(0.013, 0.31, 5)
    assert np.allclose(ticks, [0.1, 0.2, 0.3])
    assert np.allclose(nice_ticks(0, 1000, 5), [0, 500, 1000])
    assert np.allclose(nice_ticks(0, 1000, 11), [0, 100, 200, 300, 400, 500, 600, 700, 800, 900, 1000])
