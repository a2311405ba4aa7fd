"""`blendsplat bench stream`'s drives (smooth, random) and --verify (streamed frames against a cold render)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from service.bench_drive import MAX_HZ, Drive
from service.bench_verify import Keeper, _compare, choose, keepers

NAMES = [f"e{i}" for i in range(20)]
JOINTS = ["root", "neck", "head", "jaw"]


def _values(drive: Drive, indices) -> np.ndarray:
    return np.stack([np.concatenate([c, a.ravel()]) for c, a in (drive.values(i) for i in indices)])


def test_smooth_drive_moves_like_a_person_and_depends_on_the_index_only():
    fps = 30.0
    smooth = Drive("smooth", 3, NAMES, JOINTS, fps)
    assert (smooth.hz < 2.0).all() and smooth.hz.max() <= MAX_HZ
    v = _values(smooth, range(1, 301))  # ten seconds
    coeffs, angles = v[:, :len(NAMES)], v[:, len(NAMES):]
    assert coeffs.min() >= 0.0 and coeffs.max() <= 0.6 and np.abs(angles).max() <= 0.15 + 1e-9
    assert coeffs.std(axis=0).min() > 0.0  # every coefficient moves
    # Consecutive frames differ little: a step is a small part of the range (a 2 Hz sinusoid at 30 fps moves at
    # most 2 pi 2 / 30 of its amplitude a frame); random frames jump by the whole range.
    random = _values(Drive("random", 3, NAMES, JOINTS, fps), range(1, 301))
    smooth_step, random_step = np.abs(np.diff(v, axis=0)).mean(), np.abs(np.diff(random, axis=0)).mean()
    assert smooth_step < random_step / 5
    assert np.abs(np.diff(v, axis=0)).max() <= 2 * np.pi * 2.0 / fps * 0.6
    # The pose of an index is the same whichever frames came before (a dropped frame changes nothing), and the
    # streams differ (their own phases).
    assert np.array_equal(_values(Drive("smooth", 3, NAMES, JOINTS, fps), [150])[0], v[149])
    assert not np.allclose(_values(Drive("smooth", 4, NAMES, JOINTS, fps), range(1, 301)), v)
    pose = smooth.pose(7)
    assert pose.index == 7 and len(pose.coefficients) == len(NAMES) and set(pose.joints) == {"neck", "head", "jaw"}
    with pytest.raises(ValueError, match="smooth, random"):
        Drive("wobbly", 0, NAMES, JOINTS, fps)


def test_keepers_spread_their_frames_over_the_run_and_choose_n_over_the_streams():
    from blendsplat.v1 import render_pb2 as pb

    k = Keeper(0, 5)
    for i in range(1, 1001):
        k.offer(i, pb.FrameParams(index=i), b"")
    assert 5 <= len(k.kept) < 10
    gaps = np.diff([s.index for s in k.kept])
    assert (gaps == gaps[0]).all() and k.kept[-1].index > 500  # evenly spaced, over the whole run
    k.offer(1001, None, b"")  # a frame without its pose (sent before the count began) is never kept
    assert [s.index for s in k.pick(3)] == [k.kept[0].index, k.kept[len(k.kept) // 2].index, k.kept[-1].index]

    keep = keepers(4, 10)
    for stream, count in enumerate((100, 100, 100, 1)):  # the last stream got one frame
        for i in range(1, count + 1):
            keep[stream].offer(i, pb.FrameParams(index=i), b"")
    chosen = choose(keep, 10)
    assert len(chosen) == 10 and sum(s.stream == 3 for s in chosen) == 1
    assert len({(s.stream, s.index) for s in chosen}) == 10


def _textured(size: int, seed: int = 0) -> np.ndarray:
    """A face-like RGBA test picture: smooth shading and fine texture on black."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    base = 0.5 + 0.3 * np.sin(9 * x)[..., None] * np.cos(7 * y)[..., None] + rng.normal(0, 0.05, (size, size, 3))
    inside = ((x - 0.5) ** 2 + (y - 0.5) ** 2 < 0.15)[..., None]
    rgb = np.clip(base * inside, 0, 1) * 255
    return np.concatenate([rgb, 255 * inside], axis=-1).round().astype(np.uint8)


def test_verify_compares_jpeg_frames_in_jpeg_so_only_what_changed_counts():
    from render_core.media.codecs import make_encoder

    size = 128
    cold = _textured(size)
    with make_encoder("jpeg", size, size) as enc:
        streamed = enc.encode(cold)
    same, lossless = _compare("jpeg", streamed, cold, size)
    assert same == 100.0  # identical pixels: identical JPEG
    assert 25.0 < lossless < 50.0  # what JPEG itself loses, which a lossless reference would have reported
    # A mechanism that moves a few pixels by a level shows, but far above what JPEG loses.
    changed = cold.copy()
    changed[40:48, 40:80, :3] += 1
    with make_encoder("jpeg", size, size) as enc:
        moved, _ = _compare("jpeg", enc.encode(changed), cold, size)
    assert 50.0 < moved < 100.0
    # One that changes the picture visibly fails the 50 dB gate.
    changed[30:90, 30:90, :3] //= 2
    with make_encoder("jpeg", size, size) as enc:
        assert _compare("jpeg", enc.encode(changed), cold, size)[0] < 35.0
    # PNG frames are compared as they are.
    with make_encoder("png", size, size) as enc:
        assert _compare("png", enc.encode(cold), cold, size) == (100.0, None)


def test_bench_stream_verify_reports_the_streamed_frames_against_a_cold_render(live_server, capsys, monkeypatch):
    from render_core.raster.native import Schedule
    from service.cli import main

    base = ["bench", "stream", "--target", live_server.grpc_target, "--avatar", "demo", "--streams", "2", "--seconds",
            "1.5", "--warmup", "0.2", "--fps", "20", "--size", "48", "--json", "--metrics-url",
            live_server.http_url + "/metrics"]
    # With the exact schedules alone, each streamed frame is the cold render's (identical, 100 dB)...
    renderer = live_server.engine.cache.get("demo").renderer
    monkeypatch.setattr(renderer, "schedule", Schedule(eight_bit_stop=False))
    assert main([*base, "--codec", "jpeg", "--verify", "5"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["drive"] == "smooth" and report["errors"] == 0
    assert 1.0 <= report["server_ms"]["batch_mean"] <= 2.0  # the stage timings are per call: frames per call
    v = report["verify"]
    assert v["frames"] == 5 and v["errors"] == 0 and report["psnr_vs_cold_db"] == v["psnr_db_min"] == 100.0
    assert v["identical"] == 5 and 20.0 < v["psnr_vs_lossless_db"] < 100.0
    assert main([*base, "--codec", "png", "--drive", "random", "--verify", "3"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["drive"] == "random" and report["psnr_vs_cold_db"] == 100.0 and report["verify"]["frames"] == 3
    assert report["verify"]["psnr_vs_lossless_db"] is None
    # ... and the precision switch (the 8-bit stop, on by default) shows: within a level, so >= 50 dB losslessly;
    # through JPEG a flipped coefficient spreads over its block (about 47 dB on this small head, 55 at 512 px).
    monkeypatch.undo()
    assert main([*base, "--codec", "png", "--verify", "3"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert 50.0 <= report["psnr_vs_cold_db"] < 100.0 and report["verify"]["identical"] < 3
    assert main([*base, "--codec", "jpeg", "--verify", "3"]) == 0
    assert 40.0 <= json.loads(capsys.readouterr().out)["psnr_vs_cold_db"] < 100.0
    # Without --verify there is no such figure; H.264 cannot be verified frame by frame (an error before streaming).
    assert main(base) == 0
    assert "psnr_vs_cold_db" not in json.loads(capsys.readouterr().out)
    assert main([*base, "--codec", "h264", "--verify", "3"]) == 1
    assert "h264" in capsys.readouterr().err
