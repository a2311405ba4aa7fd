"""The blendsplat command end to end: bundles, offline rendering in every format, bad input, the benchmark."""

import json
import subprocess
import sys

import av
import numpy as np
import OpenImageIO as oiio
import pytest
import torch

from render_core.tools.cli import main


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli") / "a.bundle"
    assert main(["bundle", "synth", "--out", str(path), "--gaussians", "1500", "--blendshapes", "5",
                 "--seed", "1"]) == 0
    return path


def _json(capsys):
    return json.loads(capsys.readouterr().out)


def _read(path):
    return oiio.ImageBuf(str(path)).get_pixels(oiio.FLOAT)


def test_synth_validate_inspect(bundle, capsys):
    capsys.readouterr()
    assert main(["bundle", "validate", str(bundle)]) == 0
    assert _json(capsys)["valid"] is True
    assert main(["bundle", "inspect", str(bundle), "--json"]) == 0
    manifest = _json(capsys)
    assert manifest["expression_names"] == [f"exp_{i:02d}" for i in range(5)]
    assert manifest["joint_names"] == ["root", "neck", "jaw", "eye_l", "eye_r"]
    assert manifest["counts"]["gaussians"] == 1500
    assert main(["bundle", "inspect", str(bundle)]) == 0  # JSON without --json too: every command prints JSON
    assert _json(capsys) == manifest


def test_bundle_synth_stores_fp16_by_default(tmp_path, capsys):
    """The README: fp16 (the default) applies to the blendshape pairs and pose correctives."""
    from render_core.bundle import read_manifest

    out = tmp_path / "default.bundle"
    assert main(["bundle", "synth", "--out", str(out), "--gaussians", "300", "--blendshapes", "3"]) == 0
    assert _json(capsys)["precision"] == "fp16" and read_manifest(out)["precision"] == "fp16"
    assert main(["bundle", "synth", "--out", str(out), "--gaussians", "300", "--blendshapes", "3",
                 "--precision", "fp32"]) == 0
    assert _json(capsys)["precision"] == "fp32"


def _no_constants(name):
    raise ValueError(f"not strict JSON: {name}")


def test_printed_json_is_strict(capsys):
    """Non-finite floats (Python's and numpy's, at any depth) print as null: JavaScript's JSON.parse and other strict
    parsers refuse NaN and Infinity."""
    from render_core.tools import cli

    cli._emit({"nan": float("nan"), "deep": [{"inf": float("inf")}, (np.float64("-inf"), 1.5)], "ok": 2.0,
               "n": np.float32(0.25).item(), "text": "NaN"})
    out = capsys.readouterr().out
    assert json.loads(out, parse_constant=_no_constants) == {
        "nan": None, "deep": [{"inf": None}, [None, 1.5]], "ok": 2.0, "n": 0.25, "text": "NaN"}
    assert cli.dumps({"x": float("nan")}, indent=None) == '{"x": null}'


def test_validate_refuses_a_truncated_bundle(bundle, tmp_path, capsys):
    bad = tmp_path / "bad.bundle"
    bad.write_bytes(bundle.read_bytes()[:1000])
    assert main(["bundle", "validate", str(bad)]) == 1
    report = _json(capsys)
    assert report["valid"] is False and report["error"]


def test_render_png_follows_the_driving_file(bundle, tmp_path, capsys):
    drive = tmp_path / "d.jsonl"
    drive.write_text('{}\n{"expression": {"exp_00": 1.0}}\n{"joints": {"jaw": [0.35, 0, 0]}}\n')
    out = tmp_path / "png"
    assert main(["render", "--bundle", str(bundle), "--drive", str(drive), "--out", str(out), "--size", "64"]) == 0
    summary = _json(capsys)
    assert summary["frames"] == 3 and len(summary["files"]) == 3
    neutral, expr, jaw = (_read(p) for p in summary["files"])
    assert neutral.shape == (64, 64, 3)
    assert np.abs(neutral - jaw).max() > 1e-3 and np.abs(neutral - expr).max() > 1e-3
    assert neutral.max() > 0.3  # the head is visible


def test_render_exr_keeps_float_rgba(bundle, tmp_path, capsys):
    drive = tmp_path / "d.jsonl"
    drive.write_text("{}\n")
    assert main(["render", "--bundle", str(bundle), "--drive", str(drive), "--out", str(tmp_path / "exr"),
                 "--size", "48", "--format", "exr"]) == 0
    (path,) = _json(capsys)["files"]
    pixels = _read(path)
    assert pixels.shape == (48, 48, 4) and pixels.dtype == np.float32
    alpha = pixels[..., 3]
    assert alpha.max() > 0.9 and alpha.min() == 0.0
    assert len(np.unique(pixels[..., 0])) > 256  # not quantised to 8 bits


def test_render_mp4_is_h264_with_one_frame_per_line(bundle, tmp_path, capsys):
    drive = tmp_path / "d.jsonl"
    drive.write_text("".join(json.dumps({"camera": {"yaw": y}}) + "\n" for y in (-20, 0, 20, 40)))
    assert main(["render", "--bundle", str(bundle), "--drive", str(drive), "--out", str(tmp_path / "mp4"),
                 "--size", "64", "--format", "mp4"]) == 0
    (path,) = _json(capsys)["files"]
    with av.open(path) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264"
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(stream)]
    assert len(frames) == 4 and frames[0].shape == (64, 64, 3)


def test_bad_driving_lines_are_refused_before_anything_is_written(bundle, tmp_path, capsys):
    drive = tmp_path / "d.jsonl"
    drive.write_text('{}\n{"expression": [1.0]}\n')
    out = tmp_path / "never"
    assert main(["render", "--bundle", str(bundle), "--drive", str(drive), "--out", str(out), "--size", "32"]) == 1
    err = capsys.readouterr().err
    assert "d.jsonl:2" in err and "exactly 5" in err
    assert not out.exists() or not any(out.iterdir())


def test_bench_render_json(capsys):
    assert main(["bench", "render", "--backend", "reference", "--gaussians", "2000", "--blendshapes", "8",
                 "--size", "64", "--streams", "2", "--frames", "2", "--json"]) == 0
    report = _json(capsys)
    for key in ("backend", "gaussians", "blendshapes", "size", "streams", "sh_degree", "precision", "coverage",
                "fps", "aggregate_fps"):
        assert key in report
    assert set(report["ms"]) == {"blend", "lbs", "raster", "total"}
    assert report["streams"] == 2 and report["aggregate_fps"] == pytest.approx(2 * report["fps"], rel=1e-3)
    assert 0.4 <= report["coverage"] <= 0.6


def test_bench_render_times_the_reference_only_when_asked_and_says_what_it_does(capsys, caplog):
    """The reference backend's timing is opt-in (--reference-frames, default 0: tens of seconds a frame at 64k
    Gaussians); every stage is logged on stderr as it starts, the reference's frames one by one."""
    import logging

    from render_core.raster import default_backend
    from render_core.tools.cli import build_parser

    assert build_parser().parse_args(["bench", "render"]).reference_frames == 0
    backend = default_backend()
    tiny = ["bench", "render", "--backend", backend, "--gaussians", "300", "--blendshapes", "3", "--size", "32",
            "--frames", "1", "--warmup", "0", "--json"]
    with caplog.at_level(logging.INFO, logger="render_core.tools.bench"):
        assert main(tiny) == 0
    report = _json(capsys)
    assert "vs_reference" not in report
    assert "building a synthetic avatar" in caplog.text and "timing 1 frame(s)" in caplog.text
    if backend == "reference":
        return
    assert 0 < report["ms"]["bin"] <= report["ms"]["raster"]  # native: the depth sort and binning, within raster
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="render_core.tools.bench"):
        assert main([*tiny, "--reference-frames", "1"]) == 0
    assert _json(capsys)["vs_reference"]["frames"] == 1
    assert "reference backend" in caplog.text and "reference: frame 1/1" in caplog.text


def test_console_script_prints_only_json_on_stdout(bundle):
    proc = subprocess.run([sys.executable, "-m", "render_core.tools.cli", "bundle", "inspect", str(bundle), "--json"],
                          capture_output=True, text=True, check=True)
    assert json.loads(proc.stdout)["schema_version"] >= 1


def test_data_and_facemodel_commands(tmp_path, capsys):
    import numpy as np

    from render_core.data import write_dataset
    from service.cli import main
    from tests.test_data import make_masks, make_tracking, smooth_frames
    from tests.test_flame import pickle_flame, synthetic, write

    ds = write_dataset(tmp_path / "ds", smooth_frames(), make_masks(), make_tracking())
    assert main(["data", "validate", str(ds)]) == 0
    capsys.readouterr()
    first = sorted((ds / "frames").iterdir())[0]
    first.write_bytes(first.read_bytes()[:100])  # a truncated frame
    assert main(["data", "validate", str(ds), "--json"]) == 1
    report = capsys.readouterr().out
    assert first.name in report

    pkl = write(tmp_path, pickle_flame(synthetic()))
    out = tmp_path / "flame.fm"
    with np.errstate(all="ignore"):
        code = main(["facemodel", "import-flame", "--pkl", str(pkl), "--out", str(out), "--n-expression", "6"])
    assert code == 1  # the synthetic file has 8 shape components, not FLAME's 300: refused with a clear error
    assert "300 shape components" in capsys.readouterr().err


def test_bundle_init_from_a_face_model_file(tmp_path, head, capsys):
    import json

    from render_core.bundle import read_bundle
    from render_core.facemodel import write_facemodel
    from service.cli import main

    fm = write_facemodel(head, tmp_path / "head.facemodel")
    out = tmp_path / "init.bundle"
    assert main(["bundle", "init", "--facemodel", str(fm), "--out", str(out), "--gaussians", "800", "--mouth", "40",
                 "--albedo", "demo", "--opacity", "0.9"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["face_model"] == head.name and report["gaussians"] == 800 and report["mouth"] == 40
    avatar = read_bundle(out)
    assert avatar.expression_names == head.expression_names and avatar.precision == "fp16"


def test_data_synth_cli_writes_a_valid_dataset(tmp_path, head, capsys, monkeypatch):
    import json

    from render_core.data import validate_dataset
    from render_core.facemodel import write_facemodel
    from service.cli import main

    fm = write_facemodel(head, tmp_path / "head.facemodel")
    out = tmp_path / "ds"
    assert main(["data", "synth", "--out", str(out), "--frames", "7", "--size", "48", "--seed", "2",
                 "--facemodel", str(fm)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == 7 and summary["test"] >= 1 and summary["face_model"] == head.name
    assert validate_dataset(out) == []


def test_eval_cli_prints_the_metrics(tmp_path, head, capsys):
    import json

    from render_core.bundle import write_bundle
    from render_core.data.generate import synth_dataset
    from render_core.train.initialize import init_avatar
    from service.cli import main

    synth_dataset(tmp_path / "ds", frames=6, size=32, seed=1, facemodel=head)
    write_bundle(init_avatar(head, gaussians=2000, mouth=40, opacity=0.9), tmp_path / "a.bundle")
    assert main(["eval", "--bundle", str(tmp_path / "a.bundle"), "--data", str(tmp_path / "ds"), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert {"psnr", "ssim", "psnr_head", "frames"} <= set(report) and report["frames"] == 1


def test_train_cli_writes_a_bundle_and_its_workdir(tmp_path, head, capsys, monkeypatch):
    import json

    from render_core.bundle import read_bundle
    from render_core.data.generate import synth_dataset
    from service.cli import main

    monkeypatch.setenv("BLENDSPLAT_DATA_DIR", str(tmp_path / "data"))
    synth_dataset(tmp_path / "ds", frames=5, size=32, seed=1, facemodel=head)
    out = tmp_path / "a.bundle"
    assert main(["train", str(tmp_path / "ds"), "--out", str(out), "--iterations", "2", "--gaussians", "500",
                 "--quiet"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["bundle"] == str(out) and read_bundle(out).expression_names == head.expression_names
    work = tmp_path / "a.train"
    for name in ("log.jsonl", "summary.json", "report.json", "contact_sheet.png", "curves.png"):
        assert (work / name).is_file(), name
    assert {"psnr", "ssim", "psnr_head", "frames"} <= set(summary["eval"])
    assert summary["poses"] is None  # no per-frame corrections unless asked for
    refined = tmp_path / "b.bundle"
    assert main(["train", str(tmp_path / "ds"), "--out", str(refined), "--iterations", "2", "--gaussians", "500",
                 "--refine-expressions", "--quiet"]) == 0
    poses = json.loads(capsys.readouterr().out)["poses"]  # --refine-expressions brings the pose corrections too
    assert poses["frames"] == 4 and {"rotation_deg", "translation_mm", "expression"} <= set(poses)


def test_bundle_convert_rewrites_a_schema_1_bundle_as_schema_2_with_the_same_content(tmp_path, capsys):
    from render_core.bundle import read_bundle, read_manifest, stored_schema_version, write_bundle
    from render_core.tools.synth import synth_avatar

    avatar = synth_avatar(gaussians=300, blendshapes=5, seed=4, local=True)
    v1, v2 = tmp_path / "v1.bundle", tmp_path / "v2.bundle"
    write_bundle(avatar, v1, schema_version=1)
    assert main(["bundle", "convert", str(v1), "--out", str(v2)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert (out["from_schema"], out["schema_version"], out["precision"]) == (1, 2, "fp16")
    assert stored_schema_version(v2) == 2 and out["bytes"] == v2.stat().st_size < v1.stat().st_size
    # The same avatar, written directly as schema 2, is the same content (same digest: provenance is kept).
    direct = tmp_path / "direct.bundle"
    write_bundle(read_bundle(v1), direct)
    assert read_manifest(direct)["digest"] == out["digest"]
    a, b = read_bundle(v1), read_bundle(v2)
    assert all(torch.equal(x, y) for x, y in zip(a.dense_deltas().tensors().values(),
                                                 b.dense_deltas().tensors().values(), strict=True))
    # A broken input is refused before anything is written.
    broken = tmp_path / "broken.bundle"
    broken.write_bytes(v1.read_bytes()[:-10])
    assert main(["bundle", "convert", str(broken), "--out", str(tmp_path / "x.bundle")]) == 1
    assert not (tmp_path / "x.bundle").exists()
