"""Figures (render_core.evaluation.plot): training curves and the contact sheet drawn with matplotlib (Agg), and the
reason recorded instead when matplotlib (the ``train`` extra) is not installed."""

from __future__ import annotations

import json
import logging
import math
import subprocess
import sys

import numpy as np
import pytest

from render_core.evaluation import plot
from render_core.evaluation.plot import (
    INSTALL_HINT,
    PlotsUnavailable,
    caption,
    contact_sheet_figure,
    curves_figure,
    plot_curves,
    read_log,
    save_figure,
    training_plots,
    unavailable,
    write_contact_sheet,
)

pytest.importorskip("matplotlib", reason="the figures need the train extra (matplotlib)")


def hide_matplotlib(monkeypatch) -> None:
    """Make ``import matplotlib`` (and every already imported submodule) fail as on a machine without it."""
    for name in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")] + ["matplotlib"]:
        monkeypatch.setitem(sys.modules, name, None)


def _read_png(path) -> np.ndarray:
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    assert inp is not None, oiio.geterror()
    pixels = inp.read_image("uint8")
    inp.close()
    return pixels


def _write_log(path, n: int = 40, step: int = 50) -> None:
    with open(path, "w") as f:
        for i in range(0, n * step, step):
            f.write(json.dumps({"iteration": i, "loss": 0.3 * math.exp(-i / 300) + 0.004, "l1": 0.1, "ssim": 0.9,
                                "psnr": 15 + 10 * (1 - math.exp(-i / 500)), "seconds": i * 0.1}) + "\n")
        f.write('{"iteration": 2000, "loss": 0.0')  # a line being written: skipped


def _texts(fig) -> list[str]:
    from matplotlib.text import Text

    return [t.get_text() for t in fig.findobj(Text) if t.get_visible() and t.get_text()]


def _without_text(fig, path):
    """Save ``fig`` with every text artist hidden (the same figure with no labels)."""
    from matplotlib.text import Text

    for t in fig.findobj(Text):
        t.set_visible(False)
    return _read_png(save_figure(fig, path))


# ---------------------------------------------------------------------------------------------------- curves
def test_curves_png_has_the_requested_size_and_is_not_blank(tmp_path):
    _write_log(tmp_path / "log.jsonl")
    px = _read_png(plot_curves(tmp_path / "log.jsonl", tmp_path / "plots" / "curves.png"))
    assert px.shape == (400, 640, 4)  # 640 x (2 panels of 200), RGBA
    assert px[..., :3].std() > 20 and (px[..., :3] < 128).any(axis=2).mean() > 0.005  # lines and text drawn
    px = _read_png(plot_curves(tmp_path / "log.jsonl", tmp_path / "one.png", keys=("psnr", "missing"), width=300,
                               panel_height=120))
    assert px.shape == (240, 300, 4)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["log.jsonl", "one.png", "plots"]  # no temporary files


def test_curves_have_labelled_axes_a_legend_a_title_and_a_log_loss_axis(tmp_path):
    _write_log(tmp_path / "log.jsonl")
    records = read_log(tmp_path / "log.jsonl")
    assert len(records) == 40  # the torn last line is skipped
    fig = curves_figure(records, ("loss", "psnr", "missing"), title="run 7")
    loss, psnr, missing = fig.axes
    assert loss.get_yscale() == "log"  # the loss spans two decades
    assert psnr.get_yscale() == "linear" and missing.get_yscale() == "linear"
    assert (loss.get_ylabel(), psnr.get_ylabel()) == ("loss", "PSNR (dB)")
    assert missing.get_xlabel() == "iteration" and fig.get_suptitle() == "run 7"
    assert [len(line.get_xdata()) for line in loss.get_lines()] == [40, 1]  # the curve and its best point
    legend = [t.get_text() for t in loss.get_legend().get_texts()]
    assert legend[0].startswith("loss (last 0.0") and legend[1].startswith("min ") and legend[1].endswith("at 1950")
    assert [t.get_text() for t in psnr.get_legend().get_texts()][1].startswith("max 24.")  # higher is better
    assert "missing: no data" in _texts(fig) and missing.get_legend() is None
    with pytest.raises(ValueError, match="at least one key"):
        curves_figure(records, ())
    with pytest.raises(ValueError, match="too small"):
        curves_figure(records, width=100)


def test_curves_text_is_drawn_with_a_real_font(tmp_path):
    _write_log(tmp_path / "log.jsonl")
    fig = curves_figure(read_log(tmp_path / "log.jsonl"))
    labelled = _read_png(save_figure(fig, tmp_path / "labelled.png"))
    bare = _without_text(fig, tmp_path / "bare.png")
    assert labelled.shape == bare.shape
    text = (labelled != bare).any(axis=2)
    assert text.mean() > 0.01  # the title, axis labels, tick labels and legend are in the image
    # Anti-aliased glyphs (a real font) have many grey levels; a bitmap font would have one ink colour.
    assert len(np.unique(labelled[text][:, :3], axis=0)) > 20


# --------------------------------------------------------------------------------------------- contact sheet
def test_contact_sheet_shows_prediction_and_ground_truth_per_row_pixel_for_pixel(tmp_path):
    h, w = 20, 24
    colours = [((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)), ((0.0, 1.0, 0.0), (1.0, 1.0, 0.0))]
    rows = [(5 + r, np.broadcast_to(np.asarray(p), (h, w, 3)), np.broadcast_to(np.asarray(g), (h, w, 3)), 20.0 + r)
            for r, (p, g) in enumerate(colours)]
    px = _read_png(write_contact_sheet(rows, tmp_path / "sheet" / "sheet.png"))
    s = math.ceil(plot.SHEET_MIN_WIDTH / w)  # small frames are enlarged by a whole factor
    assert px.shape[1] >= 2 * w * s and px.shape[2] == 4
    boxes = []
    for pred, gt in colours:
        for colour in (pred, gt):
            ys, xs = np.nonzero((px[..., :3] == np.asarray(colour) * 255).all(axis=2))
            assert ys.size == h * s * w * s  # every pixel of the image, nothing else of that colour
            assert (ys.max() - ys.min() + 1, xs.max() - xs.min() + 1) == (h * s, w * s)
            boxes.append((ys.min(), xs.min()))
    (p0, g0, p1, g1) = boxes
    assert p0[0] == g0[0] and p0[1] < g0[1]  # prediction | ground truth, side by side
    assert p1[0] > p0[0] + h * s and p1[1] == p0[1] and g1[1] == g0[1]  # one row per frame, top to bottom


def test_contact_sheet_is_captioned_with_a_real_font(tmp_path):
    g = np.random.default_rng(0)
    rows = [(i, g.random((32, 40, 3)), g.random((32, 40, 3)), 27.314 + i / 3) for i in (3, 12)]
    fig = contact_sheet_figure(rows)
    assert _texts(fig) == ["prediction", "ground truth", "frame 3  PSNR 28.31 dB", "frame 12  PSNR 31.31 dB"]
    assert caption(7, 31.0) == "frame 7  PSNR 31.00 dB"
    labelled = _read_png(save_figure(fig, tmp_path / "labelled.png"))
    bare = _without_text(fig, tmp_path / "bare.png")
    text = (labelled != bare).any(axis=2)
    assert text.sum() > 500 and len(np.unique(labelled[text][:, :3], axis=0)) > 20  # anti-aliased glyphs
    text_rows = np.nonzero(text.any(axis=1))[0]
    assert text_rows.min() < plot.SHEET_HEADER  # the column titles head the sheet
    with pytest.raises(ValueError, match="at least one frame"):
        contact_sheet_figure([])
    with pytest.raises(ValueError, match="not all 40 x 32"):
        contact_sheet_figure(rows + [(1, np.zeros((8, 8, 3)), np.zeros((8, 8, 3)), 10.0)])


# ------------------------------------------------------------------------------------------ without matplotlib
def test_without_matplotlib_the_plots_are_skipped_with_the_reason(tmp_path, monkeypatch, caplog, capsys):
    _write_log(tmp_path / "log.jsonl")
    assert unavailable() is None
    hide_matplotlib(monkeypatch)
    reason = unavailable()
    assert reason == f"matplotlib is not installed: {INSTALL_HINT}" and "pip install 'blendsplat[train]'" in reason
    with pytest.raises(PlotsUnavailable) as e:
        plot_curves(tmp_path / "log.jsonl", tmp_path / "curves.png")
    assert e.value.reason == reason
    with pytest.raises(PlotsUnavailable):
        write_contact_sheet([(0, np.zeros((8, 8, 3)), np.zeros((8, 8, 3)), 10.0)], tmp_path / "sheet.png")
    with caplog.at_level(logging.WARNING, logger="render_core.evaluation.plot"):
        assert training_plots(tmp_path / "log.jsonl", tmp_path / "curves.png") == {"skipped": reason}
    assert reason in caplog.text and capsys.readouterr() == ("", "")  # logged, not printed
    assert sorted(p.name for p in tmp_path.iterdir()) == ["log.jsonl"]
    monkeypatch.undo()
    assert training_plots(tmp_path / "log.jsonl", tmp_path / "curves.png") == {"curves": str(tmp_path / "curves.png")}


def test_the_library_imports_without_matplotlib():
    code = ("import sys; sys.modules['matplotlib'] = None\n"
            "import render_core, render_core.evaluation.report, render_core.evaluation.plot, render_core.train.losses\n"
            "assert render_core.evaluation.plot.unavailable().startswith('matplotlib is not installed')\n"
            "assert not [m for m in sys.modules if m.startswith('matplotlib.')]\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
