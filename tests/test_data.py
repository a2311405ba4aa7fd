"""Tracked-video datasets: the portable format's round trips and every way a folder can be bad
(render_core.data.portable), and metrical-tracker folders (render_core.data.metrical)."""

from __future__ import annotations

import json
import os
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from render_core.data import (
    FORMAT,
    VERSION,
    Tracking,
    convert_metrical,
    load_frame_file,
    read_dataset,
    read_metrical,
    split_indices,
    validate_dataset,
    write_dataset,
)
from render_core.errors import DatasetError
from render_core.media.files import write_image
from render_core.media.pixels import to_uint8
from render_core.rotation import axis_angle_to_matrix, matrix_to_rot6d
from render_core.tools.cli import main as cli

N, H, W, NK = 6, 16, 16, 4
JOINTS = ["root", "neck", "jaw", "eye_l", "eye_r"]


def make_tracking(n: int = N, seed: int = 0, dtype=np.float32) -> Tracking:
    rng = np.random.default_rng(seed)
    aa = torch.from_numpy(rng.normal(size=(n, 3)) * 0.3)
    return Tracking(
        face_model="flame", expression_names=[f"exp_{i:02d}" for i in range(NK)], joint_names=list(JOINTS),
        expression=rng.normal(size=(n, NK)).astype(dtype),
        joint_rotations=(rng.normal(size=(n, len(JOINTS), 3)) * 0.1).astype(dtype),
        eyelids=rng.random((n, 2)).astype(dtype),
        K=np.tile(np.array([[20.0, 0, 8], [0, 21.0, 7.5], [0, 0, 1]]), (n, 1, 1)).astype(dtype),
        R=axis_angle_to_matrix(aa).numpy().astype(dtype), t=rng.normal(size=(n, 3)).astype(dtype),
        shape=rng.normal(size=7).astype(dtype), train=np.arange(n - 2, dtype=np.int64),
        test=np.arange(n - 2, n, dtype=np.int64), width=W, height=H, fps=25.0)


def smooth_frames(n: int = N, h: int = H, w: int = W) -> list[np.ndarray]:
    """Smooth colour ramps (lossy codecs keep them close), different per frame."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    out = []
    for i in range(n):
        rgb = np.stack([x / w, y / h, 0.5 + 0.3 * np.sin((x + y + 3 * i) / 6)], -1) * 200 + 20
        out.append(rgb.astype(np.uint8))
    return out


def make_masks(n: int = N, h: int = H, w: int = W) -> list[np.ndarray]:
    y, x = np.mgrid[0:h, 0:w]
    return [np.where((x - w / 2) ** 2 + (y - h / 2) ** 2 < (4 + i) ** 2, 255, (x * 7 + i) % 256).astype(np.uint8)
            for i in range(n)]


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> Path:
    """A valid PNG dataset (6 frames of 16x16); tests copy it before damaging it."""
    return write_dataset(tmp_path_factory.mktemp("good") / "ds", smooth_frames(), make_masks(), make_tracking())


@pytest.fixture
def copy(good, tmp_path) -> Path:
    return Path(shutil.copytree(good, tmp_path / "ds"))


def load_npz(root: Path) -> dict[str, np.ndarray]:
    with np.load(root / "tracking.npz", allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def save_npz(root: Path, arrays: dict) -> None:
    (root / "tracking.npz").unlink()
    np.savez(root / "tracking.npz", **arrays)


def edit_manifest(root: Path, **changes) -> None:
    m = json.loads((root / "dataset.json").read_text())
    for k, v in changes.items():
        if v is None:
            m.pop(k, None)
        else:
            m[k] = v
    (root / "dataset.json").write_text(json.dumps(m))


def assert_tracking_equal(a: Tracking, b: Tracking) -> None:
    for name in ("expression", "joint_rotations", "eyelids", "K", "R", "t", "shape", "train", "test"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and np.array_equal(x, y), name
    assert (a.face_model, a.expression_names, a.joint_names, a.width, a.height, a.fps) == \
        (b.face_model, b.expression_names, b.joint_names, b.width, b.height, b.fps)


# ------------------------------------------------------------------------------------------------- round trips
def test_png_round_trip_is_exact(good):
    ds = read_dataset(good)
    assert len(ds) == N
    assert_tracking_equal(ds.tracking, make_tracking())
    frames, masks = smooth_frames(), make_masks()
    for i in range(N):
        f, m = ds.frame(i), ds.mask(i)
        assert f.dtype == np.float32 and f.shape == (H, W, 3) and m.dtype == np.float32 and m.shape == (H, W)
        assert np.array_equal(to_uint8(f), frames[i])
        assert np.array_equal(to_uint8(m), masks[i])
    manifest = json.loads((good / "dataset.json").read_text())
    assert manifest == {"format": FORMAT, "version": VERSION, "frames": N, "width": W, "height": H, "fps": 25.0,
                        "face_model": "flame", "frame_files": "frames/{:05d}.png", "mask_files": "masks/{:05d}.png"}
    assert validate_dataset(good) == []
    assert sorted(p.name for p in good.parent.iterdir()) == ["ds"]  # the temporary folder was renamed away
    with pytest.raises(IndexError):
        ds.frame(N)


@pytest.mark.parametrize("fmt, tol, magic", [("jpeg", 10 / 255, b"\xff\xd8\xff"), ("exr", 1e-6, b"\x76\x2f\x31\x01"),
                                              ("mp4", 0.0, None)])
def test_lossy_and_float_round_trips(tmp_path, fmt, tol, magic):
    frames = smooth_frames()
    root = write_dataset(tmp_path / fmt, frames, make_masks(), make_tracking(), image_format=fmt)
    assert validate_dataset(root) == []
    ds = read_dataset(root)
    assert_tracking_equal(ds.tracking, make_tracking())
    if magic:
        assert ds.frame_path(0).read_bytes().startswith(magic)
    else:
        assert ds.frame_path(0) is None and (root / "frames.mp4").is_file()
    for i in range(N):
        err = np.abs(ds.frame(i) - frames[i] / np.float32(255)).max()
        assert err <= tol + 1e-7, (fmt, i, err)
        assert np.array_equal(to_uint8(ds.mask(i)), make_masks()[i])


def write_yuv_video(path: Path, frames: list[np.ndarray], fps: int = 30) -> None:
    import av

    with av.open(str(path), mode="w") as c:
        s = c.add_stream("libx264", rate=fps)
        s.width, s.height, s.pix_fmt = frames[0].shape[1], frames[0].shape[0], "yuv420p"
        s.options = {"crf": "10"}
        for f in frames:
            for p in s.encode(av.VideoFrame.from_ndarray(f, format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)


def test_reads_a_video_written_by_pyav(copy):
    frames = smooth_frames()
    shutil.rmtree(copy / "frames")
    write_yuv_video(copy / "clip.mp4", frames)
    edit_manifest(copy, frame_files=None, video="clip.mp4")
    assert validate_dataset(copy) == []
    ds = read_dataset(copy)
    for i in range(N):  # yuv420p halves the chroma resolution of these 16x16 ramps: a few levels off
        errors = [np.abs(ds.frame(i) * 255 - f).mean() for f in frames]
        assert errors[i] < 8 and np.argmin(errors) == i, (i, errors)

    write_yuv_video(copy / "clip.mp4", frames[:-1])  # one frame short
    assert validate_dataset(copy) == [f"clip.mp4: has {N - 1} frames, expected {N}"]
    with pytest.raises(DatasetError) as e:
        read_dataset(copy).frame(0)
    assert e.value.field == "clip.mp4"

    (copy / "clip.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42" + b"\x00" * 50)
    problems = validate_dataset(copy)
    assert len(problems) == 1 and problems[0].startswith("clip.mp4: ")


def test_writer_casts_float64_tracking_and_accepts_float_frames(tmp_path):
    frames = [f.astype(np.float64) / 255 for f in smooth_frames()]
    masks = [m > 127 for m in make_masks()]
    root = write_dataset(tmp_path / "ds", frames, masks, make_tracking(dtype=np.float64))
    ds = read_dataset(root)
    assert ds.tracking.expression.dtype == np.float32
    np.testing.assert_allclose(ds.tracking.R, make_tracking(dtype=np.float64).R, atol=1e-7)
    assert np.array_equal(to_uint8(ds.frame(2)), smooth_frames()[2])
    assert set(np.unique(ds.mask(1))) <= {0.0, 1.0}


def test_writer_refuses_and_leaves_nothing_behind(tmp_path, good):
    with pytest.raises(DatasetError) as e:
        write_dataset(good, smooth_frames(), make_masks(), make_tracking())
    assert e.value.field == "out_dir"

    (tmp_path / "empty").mkdir()  # an existing empty folder is fine
    assert validate_dataset(write_dataset(tmp_path / "empty", smooth_frames(), make_masks(), make_tracking())) == []

    out = tmp_path / "short"
    with pytest.raises(DatasetError) as e:
        write_dataset(out, smooth_frames()[:-1], make_masks(), make_tracking())
    assert e.value.field == "frames"
    with pytest.raises(DatasetError) as e:
        write_dataset(out, smooth_frames(), make_masks() + make_masks(), make_tracking())
    assert e.value.field == "masks"
    with pytest.raises(DatasetError) as e:
        write_dataset(out, smooth_frames(n=N, w=W + 2), make_masks(), make_tracking())
    assert e.value.field == "frames[0]"
    bad = make_tracking()
    bad.t[1, 0] = np.nan
    with pytest.raises(DatasetError) as e:
        write_dataset(out, smooth_frames(), make_masks(), bad)
    assert e.value.field == "t"
    with pytest.raises(DatasetError) as e:
        write_dataset(out, smooth_frames(), make_masks(), make_tracking(), image_format="gif")
    assert e.value.field == "image_format"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty"]  # no output, no temporary folders


# ------------------------------------------------------------------------------------------- Tracking.validate
def test_tracking_validate_reports_every_problem():
    assert make_tracking().validate() == []
    tr = make_tracking()
    tr.expression = tr.expression[:-1]
    tr.R = tr.R * 2
    tr.K = tr.K.copy()
    tr.K[3, 0, 0] = -1
    tr.joint_rotations = tr.joint_rotations.astype(np.float64)
    tr.test = np.array([3, 4, 5], dtype=np.int64)
    tr.expression_names = ["a", "a", "b", "c"]
    tr.width = 0
    tr.fps = float("nan")
    problems = tr.validate()
    fields = [p.split(": ", 1)[0] for p in problems]
    assert set(fields) == {"expression", "R", "K", "joint_rotations", "test", "expression_names", "width", "fps"}
    assert "expression: expected shape [N, K] = [6, ?], got [5, 4]" in problems
    assert "test: train and test overlap at frames 3" in problems
    assert "joint_rotations: dtype must be float32, got float64" in problems
    assert tr.frames == N


def test_split_rules():
    assert [len(s) for s in split_indices(2000, 350)] == [1650, 350]
    assert [len(s) for s in split_indices(700, 350)] == [350, 350]
    assert [len(s) for s in split_indices(699, 350)] == [594, 105]  # fewer than 2 x 350 frames: the last 15%
    assert [len(s) for s in split_indices(5, 350)] == [4, 1]
    assert [len(s) for s in split_indices(1, 350)] == [1, 0]
    assert [len(s) for s in split_indices(10, 0)] == [10, 0]
    train, test = split_indices(100, 350)
    assert np.array_equal(np.concatenate([train, test]), np.arange(100)) and test[0] == 85


# ------------------------------------------------------------------------------------------- damaged datasets
class Boom:
    """Unpickling this touches a marker file: proves that nothing is unpickled."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def _truncate(rel):
    def damage(root):
        p = root / rel
        p.write_bytes(p.read_bytes()[:100])
    return damage


def _npz(**changes):
    def damage(root):
        arrays = load_npz(root)
        for k, v in changes.items():
            if v is None:
                arrays.pop(k)
            else:
                arrays[k] = v(arrays[k]) if callable(v) else v
        save_npz(root, arrays)
    return damage


def _set(a, index, value):
    a = a.copy()
    a[index] = value
    return a


DAMAGE = {
    "truncated frame": (_truncate("frames/00002.png"), ["frames/00002.png: cannot decode"]),
    "truncated mask": (_truncate("masks/00004.png"), ["masks/00004.png: cannot decode"]),
    "missing frame": (lambda r: (r / "frames/00001.png").unlink(), ["frames/00001.png: missing"]),
    "mask wrong size": (lambda r: write_image(r / "masks/00003.png", np.zeros((8, 8), np.uint8)),
                        ["masks/00003.png: size 8x8, expected 16x16"]),
    "frame with alpha": (lambda r: write_image(r / "frames/00000.png", np.zeros((H, W, 4), np.uint8)),
                         ["frames/00000.png: 4 channels, expected 3 (RGB)"]),
    "mask with 3 channels": (lambda r: write_image(r / "masks/00000.png", np.zeros((H, W, 3), np.uint8)),
                             ["masks/00000.png: 3 channels, expected 1 (grey)"]),
    "jpeg named png": (lambda r: shutil.copy(write_dataset(r.parent / "j", smooth_frames(), make_masks(),
                                                           make_tracking(), "jpeg") / "frames/00000.jpg",
                                             r / "frames/00005.png"),
                       ["frames/00005.png: not a PNG file"]),
    "expression N-1 rows": (_npz(expression=lambda a: a[:-1]),
                            ["expression: expected shape [N, K] = [6, 4], got [5, 4]"]),
    "NaN in t": (_npz(t=lambda a: _set(a, (2, 1), np.nan)), ["t: 1 non-finite values (NaN/Inf) at frames 2"]),
    "Inf in expression": (_npz(expression=lambda a: _set(a, (4, 0), np.inf)),
                          ["expression: 1 non-finite values (NaN/Inf) at frames 4"]),
    "K wrong shape": (_npz(K=lambda a: a[:, :2]), ["K: expected shape [N, 3, 3] = [6, 3, 3], got [6, 2, 3]"]),
    "joint_rotations wrong J": (_npz(joint_rotations=lambda a: a[:, :3]),
                                ["joint_rotations: expected shape [N, J, 3] = [6, 5, 3], got [6, 3, 3]"]),
    "R not a rotation": (_npz(R=lambda a: _set(a, (1, 0, 0), 3.0)), ["R: not a rotation matrix"]),
    "R a reflection": (_npz(R=lambda a: _set(a, 0, -np.eye(3, dtype=np.float32))), ["R: not a rotation matrix"]),
    "K not pinhole": (_npz(K=lambda a: _set(a, (0, 2, 0), 0.5)), ["K: not a pinhole intrinsic matrix"]),
    "overlapping split": (_npz(train=np.arange(5, dtype=np.int64)), ["test: train and test overlap at frames 4"]),
    "index out of range": (_npz(test=np.array([4, 5, 6], np.int64)),
                           ["test: frame indices must lie in [0, 6), got 6"]),
    "split not covering": (_npz(train=np.arange(3, dtype=np.int64)),
                           ["train: train and test together must cover every frame; missing 3"]),
    "wrong dtype": (_npz(expression=lambda a: a.astype(np.float64)),
                    ["expression: dtype must be float32, got float64"]),
    "missing array": (_npz(eyelids=None), ["eyelids: missing from tracking.npz"]),
    "junk array": (_npz(junk=np.zeros(3)), ["junk: unknown array in tracking.npz"]),
    "names not unicode": (_npz(joint_names=np.zeros(5, np.float32)), ["joint_names: must be a 1-D unicode array"]),
    "npz not a zip": (lambda r: (r / "tracking.npz").write_bytes(b"PK\x03\x04 not really"),
                      ["tracking.npz: not a readable .npz (zip) file"]),
    "wrong format": (lambda r: edit_manifest(r, format="something-else"),
                     ["format: expected 'blendsplat-tracked-video', got 'something-else'"]),
    "wrong version": (lambda r: edit_manifest(r, version=2), ["version: version 2 is not supported"]),
    "junk keys": (lambda r: edit_manifest(r, evil=1, also="x"),
                  ["evil: unknown key in dataset.json", "also: unknown key in dataset.json"]),
    "frames count mismatch": (lambda r: edit_manifest(r, frames=5),
                              ["frames: dataset.json says 5 frames but tracking.npz has 6"]),
    "missing key": (lambda r: edit_manifest(r, mask_files=None), ["mask_files: missing from dataset.json"]),
    "width mismatch": (lambda r: edit_manifest(r, width=18), [f"{d}/{i:05d}.png: size 16x16, expected 18x16"
                                                              for d in ("frames", "masks") for i in range(N)]),
    "path traversal": (lambda r: edit_manifest(r, frame_files="../ds/frames/{:05d}.png"),
                       ["frame_files: must be a relative path"]),
    "format-string injection": (lambda r: edit_manifest(r, mask_files="masks/{0.__class__}.png"),
                                ["mask_files: must contain exactly one frame-number placeholder"]),
    "both frames and video": (lambda r: edit_manifest(r, video="frames.mp4"), ["frame_files: exactly one of"]),
    "bad json": (lambda r: (r / "dataset.json").write_text("{not json"), ["dataset.json: not valid UTF-8 JSON"]),
    "json integer bomb": (lambda r: (r / "dataset.json").write_text('{"frames": ' + "9" * 5000 + "}"),
                          ["dataset.json: not valid UTF-8 JSON"]),
    "manifest not an object": (lambda r: (r / "dataset.json").write_text("[1, 2]"),
                               ["dataset.json: must hold a JSON object"]),
    "link outside": (lambda r: ((r / "masks/00002.png").unlink(), (r / "masks/00002.png").symlink_to(
        r.parent / "outside.png"), shutil.copy(r / "masks/00001.png", r.parent / "outside.png")),
                     ["masks/00002.png: resolves outside the dataset folder"]),
    "fifo frame": (lambda r: ((r / "frames/00003.png").unlink(), os.mkfifo(r / "frames/00003.png")),
                   ["frames/00003.png: not a regular file"]),
}


@pytest.mark.parametrize("name", list(DAMAGE))
def test_validate_names_each_problem(copy, name):
    damage, expected = DAMAGE[name]
    damage(copy)
    problems = validate_dataset(copy)
    for want in expected:
        assert any(p.startswith(want) for p in problems), (want, problems)
    assert len(problems) == len(expected), problems


def test_huge_declared_array_is_refused_without_allocating(copy):
    arrays = load_npz(copy)
    save_npz(copy, arrays)
    # Rewrite the shape in expression.npy's header to 10^12 rows (the header is padded, so the length fits).
    with zipfile.ZipFile(copy / "tracking.npz") as zf:
        members = {i.filename: zf.read(i) for i in zf.infolist()}
    raw = members["expression.npy"]
    members["expression.npy"] = raw.replace(b"(6, 4)", b"(1000000000000, 4)", 1)
    assert members["expression.npy"] != raw
    with zipfile.ZipFile(copy / "tracking.npz", "w") as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    problems = validate_dataset(copy)
    assert any(p.startswith("expression: declares shape [1000000000000, 4]") for p in problems), problems


def test_object_array_is_refused_and_never_unpickled(copy, tmp_path):
    marker = tmp_path / "unpickled"
    arrays = load_npz(copy)
    arrays["expression_names"] = np.array([Boom(marker)] * NK, dtype=object)
    (copy / "tracking.npz").unlink()
    np.savez(copy / "tracking.npz", **arrays)  # allow_pickle defaults to True on save
    problems = validate_dataset(copy)
    assert problems == ["expression_names: is an object array; refused (loading it would need unpickling)"]
    with pytest.raises(DatasetError) as e:
        read_dataset(copy)
    assert e.value.field == "expression_names"
    assert not marker.exists()


def test_several_problems_reported_together(copy):
    for name in ("truncated frame", "NaN in t", "junk keys", "mask wrong size", "overlapping split",
                 "missing frame"):
        DAMAGE[name][0](copy)
    problems = validate_dataset(copy)
    fields = {p.split(": ", 1)[0] for p in problems}
    assert fields == {"frames/00002.png", "t", "evil", "also", "masks/00003.png", "test", "frames/00001.png"}, problems


def test_read_dataset_checks_tracking_and_files_but_not_pixels(copy):
    _truncate("frames/00002.png")(copy)
    ds = read_dataset(copy)  # pixels are not decoded by read_dataset
    with pytest.raises(DatasetError) as e:
        ds.frame(2)
    assert e.value.field == "frames/00002.png" and "cannot decode" in str(e.value)
    DAMAGE["NaN in t"][0](copy)
    DAMAGE["junk keys"][0](copy)
    with pytest.raises(DatasetError) as e:
        read_dataset(copy)
    assert e.value.field == "evil" and "t: 1 non-finite" in str(e.value)
    (copy / "frames/00001.png").unlink()
    edit_manifest(copy, evil=None, also=None)
    save_npz(copy, {**load_npz(copy), "t": make_tracking().t})
    with pytest.raises(DatasetError) as e:
        read_dataset(copy)
    assert e.value.field == "frames/00001.png"


def test_not_a_folder(tmp_path):
    assert validate_dataset(tmp_path / "nope") == [f"{tmp_path / 'nope'}: not a dataset folder (no such directory)"]
    problems = validate_dataset(tmp_path)
    assert problems == ["dataset.json: missing", "tracking.npz: missing"]


# ------------------------------------------------------------------------------------------- metrical-tracker
class TrackerConfig:
    """A non-tensor object as some tracker versions pickle into their frames."""

    def __init__(self):
        self.lr = 0.01


def rot6d(aa) -> np.ndarray:
    return matrix_to_rot6d(axis_angle_to_matrix(torch.tensor(aa, dtype=torch.float64))).numpy()


def make_metrical(root: Path, n: int = 8, size: tuple[int, int] = (16, 12), extra=None) -> dict:
    """A synthetic metrical-tracker folder (numpy arrays in the frames, as the tracker saves them); returns the
    values written."""
    w, h = size
    rng = np.random.default_rng(5)
    (root / "checkpoint").mkdir(parents=True)
    (root / "images").mkdir()
    truth = {"exp": rng.normal(size=(n, 100)), "jaw": rng.normal(size=(n, 3)) * 0.2,
             "eye_l": rng.normal(size=(n, 3)) * 0.1, "eye_r": rng.normal(size=(n, 3)) * 0.1,
             "eyelids": rng.random((n, 2)), "shape": rng.normal(size=300),
             "R": axis_angle_to_matrix(torch.from_numpy(rng.normal(size=(n, 3)) * 0.2)).numpy(),
             "t": rng.normal(size=(n, 3)), "rgba": rng.integers(0, 256, (n, h, w, 4), dtype=np.uint8)}
    truth["rgba"][:, :3, :, 3] = 0  # transparent pixels with colour: RGB must come back as stored
    for i in range(n):
        frame = {
            "flame": {"exp": truth["exp"][i][None].astype(np.float32), "shape": truth["shape"][None].astype(np.float32),
                      "tex": np.zeros((1, 50), np.float32),
                      "jaw": rot6d(truth["jaw"][i])[None].astype(np.float32),
                      "eyes": np.concatenate([rot6d(truth["eye_l"][i]), rot6d(truth["eye_r"][i])])[None]
                      .astype(np.float32),
                      "eyelids": torch.from_numpy(truth["eyelids"][i][None].astype(np.float32))},
            "camera": {"R": np.zeros((1, 6), np.float32), "t": np.zeros((1, 3), np.float32)},
            "opencv": {"R": truth["R"][i][None].astype(np.float32), "t": truth["t"][i][None].astype(np.float32),
                       "K": np.array([[[30.0, 0, w / 2], [0, 30.0, h / 2], [0, 0, 1]]], np.float32)},
            "img_size": np.array([h, w]), "frame_id": i, "global_step": 100 * i,
        }
        if extra is not None and i == n - 1:
            frame["config"] = extra
        torch.save(frame, root / "checkpoint" / f"{i:05d}.frame")
        write_image(root / "images" / f"{i:05d}.png", truth["rgba"][i])
    return truth


def test_read_metrical(tmp_path):
    truth = make_metrical(tmp_path / "subject")
    tracking, images = read_metrical(tmp_path / "subject", n_expression=10, test_frames=3)
    assert images == [tmp_path / "subject" / "images" / f"{i:05d}.png" for i in range(8)]
    assert tracking.face_model == "flame" and tracking.joint_names == JOINTS
    assert tracking.expression_names == [f"exp_{i:02d}" for i in range(10)]
    assert (tracking.width, tracking.height, tracking.frames) == (16, 12, 8)
    np.testing.assert_allclose(tracking.expression, truth["exp"][:, :10], atol=1e-6)
    np.testing.assert_allclose(tracking.shape, truth["shape"], atol=1e-6)
    assert not tracking.joint_rotations[:, :2].any()  # root and neck: the head pose is in the extrinsics
    for j, name in ((2, "jaw"), (3, "eye_l"), (4, "eye_r")):
        np.testing.assert_allclose(tracking.joint_rotations[:, j], truth[name], atol=1e-5, err_msg=name)
    np.testing.assert_allclose(tracking.eyelids, truth["eyelids"], atol=1e-6)
    np.testing.assert_allclose(tracking.R, truth["R"], atol=1e-6)
    np.testing.assert_allclose(tracking.t, truth["t"], atol=1e-6)
    assert tracking.K[0, 0, 0] == 30 and tracking.K[0, 0, 2] == 8 and tracking.K[0, 1, 2] == 6
    assert tracking.train.tolist() == [0, 1, 2, 3, 4] and tracking.test.tolist() == [5, 6, 7]
    assert tracking.validate() == []
    assert read_metrical(tmp_path / "subject", test_frames=350)[0].test.tolist() == [7]  # short: the last 15%


def test_convert_metrical(tmp_path):
    truth = make_metrical(tmp_path / "subject")
    out = convert_metrical(tmp_path / "subject", tmp_path / "portable", test_frames=3)
    assert validate_dataset(out) == []
    ds = read_dataset(out)
    assert len(ds) == 8 and ds.tracking.expression.shape == (8, 50)
    for i in range(8):
        assert np.array_equal(to_uint8(ds.frame(i)), truth["rgba"][i, ..., :3])
        assert np.array_equal(to_uint8(ds.mask(i)), truth["rgba"][i, ..., 3])


def test_metrical_frame_needing_unpickling_is_refused_unless_trusted(tmp_path):
    make_metrical(tmp_path / "subject", extra=TrackerConfig())
    with pytest.raises(DatasetError, match="trusted=True") as e:
        read_metrical(tmp_path / "subject")
    assert e.value.field.endswith("00007.frame") and "TrackerConfig" in str(e.value)
    tracking, _ = read_metrical(tmp_path / "subject", trusted=True)
    assert tracking.frames == 8
    assert not (tmp_path / "portable").exists()


def test_metrical_safe_load_never_runs_code(tmp_path):
    marker = tmp_path / "ran"
    torch.save({"flame": {}, "payload": Boom(marker)}, tmp_path / "evil.frame")
    with pytest.raises(DatasetError, match="refused"):
        load_frame_file(tmp_path / "evil.frame")
    assert not marker.exists()
    load_frame_file(tmp_path / "evil.frame", trusted=True)  # full unpickling does run it: that is what trusted means
    assert marker.exists()


def test_metrical_problems_are_named(tmp_path):
    make_metrical(tmp_path / "a", n=3)
    (tmp_path / "a/images/00001.png").unlink()
    with pytest.raises(DatasetError, match="00001.png") as e:
        read_metrical(tmp_path / "a")
    assert e.value.field == "images"

    make_metrical(tmp_path / "b", n=3, size=(10, 10))
    torch.save({"flame": {"exp": np.zeros((1, 100))}}, tmp_path / "b/checkpoint/00002.frame")
    with pytest.raises(DatasetError, match="flame.jaw"):
        read_metrical(tmp_path / "b")

    make_metrical(tmp_path / "c", n=3)
    write_image(tmp_path / "c/images/00000.png", np.zeros((12, 16, 3), np.uint8))
    with pytest.raises(DatasetError, match="expected 4"):
        read_metrical(tmp_path / "c")

    (tmp_path / "d").mkdir()
    with pytest.raises(DatasetError, match="no checkpoint"):
        read_metrical(tmp_path / "d")


# ------------------------------------------------------------------------------------------------ commands
def run_validate(directory, as_json=False) -> int:
    return cli(["data", "validate", str(directory), *(["--json"] if as_json else [])])


def test_data_validate_prints_every_problem(good, copy, capsys):
    assert run_validate(good) == 0
    assert "valid blendsplat-tracked-video v1, 6 frames of 16x16" in capsys.readouterr().out
    assert run_validate(good, as_json=True) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["valid"] and out["problems"] == [] and (out["frames"], out["train"], out["test"]) == (6, 4, 2)
    DAMAGE["truncated frame"][0](copy)
    DAMAGE["NaN in t"][0](copy)
    assert run_validate(copy) == 1
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2 and lines[0].startswith("t: ") and lines[1].startswith("frames/00002.png: cannot decode")
    assert run_validate(copy, as_json=True) == 1
    assert json.loads(capsys.readouterr().out)["problems"] == validate_dataset(copy)


def test_data_convert_prints_json(tmp_path, capsys):
    make_metrical(tmp_path / "subject", n=4)
    assert cli(["data", "convert", str(tmp_path / "subject"), "--out", str(tmp_path / "out"), "--n-expression", "20",
                "--test-frames", "2"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out == {"path": str(tmp_path / "out"), "frames": 4, "width": 16, "height": 12, "fps": 30.0,
                   "face_model": "flame", "expressions": 20, "train": 2, "test": 2}
