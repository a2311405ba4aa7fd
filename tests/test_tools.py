"""The library side of the command-line tools: typed errors naming the option, progress through a callback, and
no library module writing to stdout or stderr (only the CLIs print)."""

import ast
import json
from pathlib import Path

import numpy as np
import pytest

import render_core
import service
from render_core.avatar import check_raster_mode
from render_core.bundle import write_bundle
from render_core.data.generate import synth_dataset
from render_core.errors import BlendsplatError, OptionError
from render_core.evaluation.report import evaluate
from render_core.media.files import VideoWriter, write_image
from render_core.raster import check_backend, differentiable
from render_core.tools.bench import bench_codecs, bench_raster_backward, bench_render
from render_core.tools.offline import render_bundle
from render_core.tools.synth import synth_avatar
from render_core.train import get_preset
from render_core.train.trainer import raster_step

CLIS = {Path(render_core.__file__).parent / "tools" / "cli.py",
        Path(render_core.__file__).parent / "tracking" / "fetch_models.py",  # the models' maintainer command
        Path(render_core.__file__).parent / "tracking" / "correspond.py",  # rebuilds the shipped correspondence
        *(Path(service.__file__).parent / name
          for name in ("cli.py", "jobs/cli.py", "jobs/display.py", "access/keys_cli.py"))}


@pytest.mark.parametrize("call,field", [
    (lambda: synth_avatar(gaussians=0), "gaussians"),
    (lambda: synth_avatar(gaussians=10, blendshapes=-1), "blendshapes"),
    (lambda: synth_avatar(gaussians=10, mouth=-1), "mouth"),
    (lambda: bench_render("reference", gaussians=100, blendshapes=2, size=16, precision="bf16"), "precision"),
    (lambda: bench_render("reference", gaussians=100, blendshapes=2, size=16, warmup=-1), "warmup"),
    (lambda: bench_render("reference", gaussians=100, blendshapes=2, size=16, frames=0), "frames"),
    (lambda: bench_render("reference", gaussians=100, blendshapes=2, size=16, output="png"), "output"),
    (lambda: bench_raster_backward(gaussians=100, size=16, device="tpu"), "device"),
    (lambda: bench_raster_backward(gaussians=100, size=16, batch=0), "batch"),
    (lambda: bench_codecs(size=0), "size"),
    (lambda: check_backend("tpu"), "backend"),
    (lambda: differentiable("reference"), "backend"),
    (lambda: raster_step("tpu"), "device"),
    (lambda: get_preset("huge"), "preset"),
    (lambda: check_raster_mode("fancy"), "raster_mode"),
    (lambda: write_image("out.gif", np.zeros((2, 2, 3), np.uint8)), "format"),
    (lambda: VideoWriter("out.mp4", 33, 32), "size"),
    (lambda: synth_dataset("never-written", frames=1, size=16, seed=0), "frames"),
    (lambda: evaluate(synth_avatar(gaussians=10), "nowhere", batch=0), "batch"),
], ids=["gaussians", "blendshapes", "mouth", "precision", "warmup", "frames", "output", "device", "batch", "size",
        "backend", "differentiable", "train-device", "preset", "raster-mode", "image-format", "video-size",
        "synth-frames", "eval-batch"])
def test_bad_options_raise_option_error_naming_the_field(call, field):
    with pytest.raises(OptionError) as e:
        call()
    assert e.value.field == field and str(e.value).startswith(f"{field}: ")
    assert isinstance(e.value, BlendsplatError) and isinstance(e.value, ValueError)  # what they raised before


def _drive(tmp_path, frames: int = 3):
    avatar = synth_avatar(gaussians=200, blendshapes=2, seed=1)
    write_bundle(avatar, tmp_path / "a.bundle")
    drive = tmp_path / "drive.jsonl"
    drive.write_text("".join(json.dumps({"expression": [0.1 * i, 0.0]}) + "\n" for i in range(frames)))
    return tmp_path / "a.bundle", drive


def test_offline_render_reports_progress_through_a_callback_and_prints_nothing(tmp_path, capfd):
    bundle, drive = _drive(tmp_path)
    seen = []
    summary = render_bundle(bundle, drive, tmp_path / "out", size=16, progress=lambda done, total: seen.append(
        (done, total)))
    assert summary["frames"] == 3 and seen == [(1, 3), (2, 3), (3, 3)]
    render_bundle(bundle, drive, tmp_path / "quiet", size=16)  # no callback: no progress at all
    out = capfd.readouterr()
    assert out.out == "" and out.err == ""
    with pytest.raises(OptionError) as e:
        render_bundle(bundle, drive, tmp_path / "out", size=16, fmt="gif")
    assert e.value.field == "format"


def test_the_render_command_draws_the_bar(tmp_path, capfd):
    from render_core.tools.cli import main

    bundle, drive = _drive(tmp_path)
    assert main(["render", "--bundle", str(bundle), "--drive", str(drive), "--out", str(tmp_path / "out"),
                 "--size", "16"]) == 0
    out = capfd.readouterr()
    assert json.loads(out.out)["frames"] == 3 and "3/3" in out.err


def _writes_output(node: ast.AST) -> bool:
    """print(...), sys.stdout / sys.stderr, or a tqdm bar."""
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("print", "tqdm"):
        return True
    if isinstance(node, ast.Attribute) and node.attr in ("stdout", "stderr") and isinstance(node.value, ast.Name) \
            and node.value.id == "sys":
        return True
    return isinstance(node, ast.ImportFrom | ast.Import) and any(a.name.split(".")[0] == "tqdm" for a in node.names) \
        or isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "tqdm"


def test_only_the_command_line_prints():
    offenders = []
    for package in (render_core, service):
        root = Path(package.__file__).parent
        for path in sorted(root.rglob("*.py")):
            name = f"{root.name}/{path.relative_to(root).as_posix()}"
            if path in CLIS:
                continue
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if _writes_output(node):
                    offenders.append(f"{name}:{node.lineno}")
    assert not offenders, f"library modules writing to the terminal (use logging or a progress callback): " \
                          f"{offenders}"
