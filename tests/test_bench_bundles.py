"""`bench bundles` (render_core.tools.bench_bundles): bundles timed side by side on a dataset's own frames."""

from __future__ import annotations

import json

import pytest
import torch

from render_core.bundle import write_bundle
from render_core.data.frames import frame_inputs
from render_core.data.generate import synth_dataset
from render_core.data.portable import read_dataset
from render_core.errors import DatasetError, OptionError
from render_core.facemodel.synthetic import synth_avatar
from render_core.renderer import AvatarRenderer
from render_core.tools.bench_bundles import bench_bundles
from render_core.train.initialize import init_avatar


@pytest.fixture(scope="module")
def data(head, tmp_path_factory):
    """A 40 x 32 synthetic dataset of 10 frames on the open head (2 held out)."""
    out = tmp_path_factory.mktemp("bench-bundles") / "data"
    synth_dataset(out, frames=10, size=32, seed=1, facemodel=head)
    return out


def test_bundles_render_the_datasets_frames_side_by_side(head, data, tmp_path, monkeypatch, capsys):
    big, small = init_avatar(head, gaussians=300, mouth=30, seed=4), init_avatar(head, gaussians=100, mouth=10, seed=4)
    paths = [tmp_path / "big.bundle", tmp_path / "small.bundle"]
    write_bundle(big, paths[0])
    write_bundle(small, paths[1])
    seen = []  # what each call rendered: (expression, camera width, height, focal length)
    real = AvatarRenderer.render_rgba8

    def spy(self, frame, cameras, *args, **kwargs):
        seen.append((frame.expression.clone(), cameras.width, cameras.height, float(cameras.K[0, 0, 0])))
        return real(self, frame, cameras, *args, **kwargs)

    monkeypatch.setattr(AvatarRenderer, "render_rgba8", spy)
    report = bench_bundles(paths, data, size=64, streams=2, rounds=3, block=2, warmup=1, split="all")
    assert report["frames"] == 10 and report["size"] == 64 and report["height"] == 64 and report["streams"] == 2
    first, second = report["bundles"]
    assert (first["bundle"], second["bundle"]) == (str(paths[0]), str(paths[1]))
    assert (first["gaussians"], first["mouth"], second["gaussians"], second["mouth"]) == (300, 30, 100, 10)
    assert first["speedup"] == 1.0 and second["speedup"] == pytest.approx(first["ms"] / second["ms"], rel=5e-3)
    for b in (first, second):
        assert len(b["rounds_ms"]) == 3 and b["ms"] > 0 and b["ms_per_frame"] == pytest.approx(b["ms"] / 2, abs=1e-3)
        assert set(b["stages_ms"]) == {"blend", "lbs", "raster", "bin"}  # the native stage split
    # 2 bundles x (1 warm-up + 3 rounds x 2 calls), each call two consecutive frames of the dataset, its cameras
    # scaled from 32 to 64 px wide.
    assert len(seen) == 14
    tracking = read_dataset(data).tracking
    frames, cams = frame_inputs(big, tracking, list(range(10)))
    for expression, width, height, focal in seen:
        assert (width, height) == (64, 64) and focal == pytest.approx(2 * float(cams.K[0, 0, 0]))
        j = next(j for j in range(9) if torch.equal(frames.expression[j:j + 2], expression))
        assert 0 <= j <= 8
    # The command: the same report as JSON.
    from service.cli import main

    monkeypatch.setattr(AvatarRenderer, "render_rgba8", real)
    assert main(["bench", "bundles", *map(str, paths), "--data", str(data), "--size", "48", "--rounds", "1",
                 "--block", "1", "--warmup", "0", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["benchmark"] == "bundles" and out["split"] == "test" and out["frames"] == 2
    assert [b["gaussians"] for b in out["bundles"]] == [300, 100]


def test_bundles_refuse_what_they_cannot_time(head, data):
    avatar = init_avatar(head, gaussians=100, mouth=10, seed=4)
    with pytest.raises(OptionError, match="at least one bundle"):
        bench_bundles([], data)
    with pytest.raises(OptionError) as e:
        bench_bundles([avatar], data, rounds=0)
    assert e.value.field == "rounds"
    with pytest.raises(DatasetError, match="avatar 2 cannot render"):  # another face model's expressions
        bench_bundles([avatar, synth_avatar(50, 5, seed=1)], data, rounds=1, block=1, warmup=0)
    with pytest.raises(DatasetError, match="2 test frames"):
        bench_bundles([avatar], data, streams=3)
