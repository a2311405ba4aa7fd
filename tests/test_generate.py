"""``data synth``: the procedural albedo, the scripted performance, the rendered dataset and the blur bar."""

import json
import math

import numpy as np
import pytest
import torch

from render_core.data import read_dataset, validate_dataset
from render_core.data.albedo import SkinAlbedo, face_landmarks, lambert
from render_core.data.generate import (
    contact_sheet,
    held_out_count,
    make_script,
    render_frames,
    script_cameras,
    synth_dataset,
)
from render_core.data.meshraster import icosphere, rasterize
from render_core.data.portable import TRACKING_ARRAYS
from render_core.evaluation.metrics import psnr_masked
from render_core.facemodel.model import FaceModel
from render_core.rotation import axis_angle_to_matrix

JOINTS = ["root", "neck", "jaw", "eye_l", "eye_r"]
PARENTS = [-1, 0, 1, 1, 1]
EYES = ((0.032, 0.025, 0.066), (-0.032, 0.025, 0.066))


def toy_face_model(arkit_names: bool = False) -> FaceModel:
    """A small head: an ellipsoid icosphere (642 vertices) with two eyeballs, FLAME's joints (the jaw carries the
    lower front of the face), and three smooth expression bumps (ARKit-named or not)."""
    head, faces = icosphere(3, 1.0, torch.float64)
    head = head * torch.tensor([0.075, 0.10, 0.09], dtype=torch.float64)
    eye, eye_faces = icosphere(1, 0.012, torch.float64)
    verts, tris, groups = [head], [faces], {}
    for name, c in zip(("eyeball_l", "eyeball_r"), EYES, strict=True):
        base = sum(v.shape[0] for v in verts)
        verts.append(eye + torch.tensor(c, dtype=torch.float64))
        tris.append(eye_faces + base)
        groups[name] = torch.arange(base, base + eye.shape[0])
    v = torch.cat(verts)
    n = v.shape[0]
    joints = torch.tensor([(0.0, -0.09, -0.02), (0.0, -0.06, -0.02), (0.0, -0.03, 0.01), *EYES],
                          dtype=torch.float64)
    w = torch.zeros(n, 5, dtype=torch.float64)
    jaw = ((-0.03 - v[:, 1]) / 0.02).clamp(0, 1) * (v[:, 2] > 0)
    w[:, 2] = jaw
    w[:, 1] = 1 - jaw
    for j, name in ((3, "eyeball_l"), (4, "eyeball_r")):
        w[groups[name]] = 0.0
        w[groups[name], j] = 1.0
    normals = torch.nn.functional.normalize(v, dim=-1)

    def bump(centre, radius, amount):
        d2 = ((v - torch.tensor(centre, dtype=torch.float64)) ** 2).sum(-1)
        return normals * (amount * torch.exp(-d2 / (2 * radius**2)))[:, None]

    basis = torch.stack([bump((0.03, -0.045, 0.07), 0.015, 0.008), bump((0.0, 0.05, 0.08), 0.02, 0.006),
                         bump((-0.02, 0.0, 0.08), 0.02, -0.005)])
    for g in groups.values():
        basis[:, g] = 0.0
    names = ["mouthSmileLeft", "browInnerUp", "cheekPuff"] if arkit_names else ["e0", "e1", "e2"]
    model = FaceModel(name="toy-head", template=v.float(), faces=torch.cat(tris), expression_names=names,
                      expression_basis=basis.float(), joint_names=list(JOINTS), joint_parents=list(PARENTS),
                      joint_positions=joints.float(), lbs_weights=w.float(), vertex_groups=groups)
    model.validate()
    return model


@pytest.fixture(scope="module")
def toy():
    return toy_face_model()


@pytest.fixture(scope="module")
def open_head_model():
    from render_core.facemodel.open_head import open_head

    return open_head()


def _blur(img: np.ndarray, sigma: float = 1.0) -> np.ndarray:
    """Separable Gaussian blur of [H, W, C] (zeros beyond the border)."""
    r = int(math.ceil(4 * sigma))
    x = torch.arange(-r, r + 1, dtype=torch.float64)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    t = torch.from_numpy(img).double().permute(2, 0, 1)[:, None]
    t = torch.nn.functional.conv2d(torch.nn.functional.pad(t, (r, r, 0, 0)), k.view(1, 1, 1, -1))
    t = torch.nn.functional.conv2d(torch.nn.functional.pad(t, (0, 0, r, r)), k.view(1, 1, -1, 1))
    return t[:, 0].permute(1, 2, 0).numpy()


def _dataset_files(root):
    return sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file())


# ------------------------------------------------------------------------------------------------------- script
def test_split_is_the_last_fifteen_percent(toy):
    for n in (2, 12, 20, 100, 333):
        sc = make_script(toy, n, seed=1)
        k = held_out_count(n)
        assert k == max(1, round(0.15 * n))
        assert sc.train.tolist() == list(range(n - k)) and sc.test.tolist() == list(range(n - k, n))
    with pytest.raises(ValueError):
        make_script(toy, 1, seed=1)


@pytest.mark.parametrize("arkit", [False, True])
def test_test_set_holds_novel_combinations_and_poses(arkit):
    model = toy_face_model(arkit)
    sc = make_script(model, 200, seed=5)
    act, tr, te = sc.activation, sc.train, sc.test
    assert sc.conflicts
    # Conflicting actions never overlap in training; every test frame has a conflicting pair both clearly active.
    for a, b in sc.conflicts:
        assert float(torch.minimum(act[tr, a], act[tr, b]).max()) == 0.0
    both = torch.stack([torch.minimum(act[te, a], act[te, b]) for a, b in sc.conflicts], 1)
    assert float(both.max(1).values.min()) >= 0.4
    # Head poses: training inside the L1 diamond, test outside it (and a little beyond either range).
    l1 = sc.head[:, 0].abs() / 25.0 + sc.head[:, 1].abs() / 12.0
    assert float(l1[tr].max()) <= 1.0 + 1e-5 and float(l1[te].min()) >= 1.12 - 1e-5
    # No test frame's parameters (expression, joints, camera rotation) are close to any training frame's.
    cams = script_cameras(model, sc, 64)
    feats = torch.cat([sc.expression, sc.joint_rotations.flatten(1), cams.R.flatten(1)], 1)
    nearest = torch.cdist(feats[te], feats[tr]).min(1).values
    assert float(nearest.min()) > 0.1
    assert float(sc.expression[te].max()) > 0.0


def test_jaw_and_gaze_use_joints_without_arkit_names(toy):
    sc = make_script(toy, 150, seed=2)
    assert sc.jaw_mode == "joint" and sc.gaze_mode == "joints"
    jaw, eye_l, eye_r = (JOINTS.index(j) for j in ("jaw", "eye_l", "eye_r"))
    assert float(sc.joint_rotations[:, jaw, 0].max()) > 0.05  # talking opens the jaw about +x
    assert float(sc.joint_rotations[:, jaw, 1:].abs().max()) == 0.0
    assert torch.equal(sc.joint_rotations[:, eye_l], sc.joint_rotations[:, eye_r])
    assert float(sc.joint_rotations[:, eye_l].abs().max()) > 0.05
    assert float(sc.joint_rotations[:, :2].abs().max()) == 0.0  # root and neck stay at rest (pose: camera)
    assert float(sc.expression.min()) >= 0.0 and float(sc.expression.max()) <= 1.0
    # Smooth: small frame-to-frame steps within the training part.
    steps = (sc.expression[1:-held_out_count(150)] - sc.expression[:-1 - held_out_count(150)]).abs().max()
    assert float(steps) < 0.35


def test_script_is_deterministic_for_a_seed(toy):
    a, b, c = make_script(toy, 60, seed=4), make_script(toy, 60, seed=4), make_script(toy, 60, seed=5)
    for name in ("expression", "joint_rotations", "head", "activation"):
        assert torch.equal(getattr(a, name), getattr(b, name))
    assert not torch.equal(a.expression, c.expression)


# ------------------------------------------------------------------------------------------------------ dataset
def test_synth_dataset_is_valid_with_exact_masks_and_no_albedo(toy, tmp_path):
    out = tmp_path / "ds"
    summary = synth_dataset(out, frames=20, size=64, seed=3, facemodel=toy)
    assert summary["out"] == str(out) and summary["frames"] == 20 and summary["size"] == 64
    assert (summary["train"], summary["test"]) == (17, 3) and summary["face_model"] == "toy-head"
    json.dumps(summary)
    assert validate_dataset(out) == []
    # Only the portable format's files: no albedo (or any other texture) is written.
    files = _dataset_files(out)
    assert files == sorted(["dataset.json", "tracking.npz", *(f"frames/{i:05d}.png" for i in range(20)),
                            *(f"masks/{i:05d}.png" for i in range(20))])
    with np.load(out / "tracking.npz", allow_pickle=False) as npz:
        assert sorted(npz.files) == sorted(TRACKING_ARRAYS)
    ds = read_dataset(out)
    tr = ds.tracking
    assert tr.test.tolist() == [17, 18, 19] and tr.train.tolist() == list(range(17))
    assert tr.shape.shape == (0,) and tr.expression.shape == (20, 3) and tr.joint_rotations.shape == (20, 5, 3)
    assert (tr.eyelids == 0).all()
    # The tracking holds exactly what was rendered: re-rasterizing from it gives the masks bit for bit.
    from render_core.camera import Cameras

    cams = Cameras(torch.from_numpy(tr.K), torch.from_numpy(tr.R), torch.from_numpy(tr.t), 64, 64)
    posed, _ = toy.evaluate(torch.from_numpy(tr.expression), axis_angle_to_matrix(torch.from_numpy(tr.joint_rotations)))
    coverage = rasterize(posed, toy.faces, cams).mask.numpy()
    for i in range(20):
        mask = ds.mask(i) > 0.5
        assert np.array_equal(mask, coverage[i])
        frame = ds.frame(i)
        assert (frame[~mask] == 0).all()  # black background
        assert frame[mask].mean() > 0.2
    # The head fills about 65% of the image height in the rest pose, front view.
    rows = np.nonzero(coverage[0].any(1))[0]
    assert 0.5 < (rows.max() - rows.min() + 1) / 64 < 0.9
    # Contact sheet.
    sheet = contact_sheet(out, tmp_path / "sheet.png", count=6)
    import OpenImageIO as oiio

    spec = oiio.ImageInput.open(str(sheet)).spec()
    assert spec.nchannels == 3 and spec.width > 2 * 64 and spec.height >= 64


def test_synth_dataset_is_deterministic(toy, tmp_path):
    a = synth_dataset(tmp_path / "a", frames=6, size=48, seed=9, facemodel=toy)
    b = synth_dataset(tmp_path / "b", frames=6, size=48, seed=9, facemodel=toy)
    c = synth_dataset(tmp_path / "c", frames=6, size=48, seed=10, facemodel=toy)
    files = _dataset_files(tmp_path / "a")
    assert files == _dataset_files(tmp_path / "b")
    for f in files:
        if f.endswith(".png"):
            assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f
    ta, tb = read_dataset(a["out"]).tracking, read_dataset(b["out"]).tracking
    for name in ("expression", "joint_rotations", "K", "R", "t"):
        assert np.array_equal(getattr(ta, name), getattr(tb, name))
    assert not np.array_equal(ta.expression, read_dataset(c["out"]).tracking.expression)


def test_synth_dataset_refuses_a_non_empty_folder(toy, tmp_path):
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "keep").write_text("")
    from render_core.errors import DatasetError

    with pytest.raises(DatasetError):
        synth_dataset(tmp_path / "x", frames=4, size=32, seed=0, facemodel=toy)


# ------------------------------------------------------------------------------------------------------- albedo
def test_albedo_is_a_function_of_the_rest_surface(toy):
    alb = SkinAlbedo(toy, seed=1)
    attrs = alb.vertex_attributes()
    assert attrs.shape == (toy.num_vertices, 7)
    a = alb(attrs, torch.full((toy.num_vertices,), 1e-3))
    b = SkinAlbedo(toy, seed=1)(attrs, torch.full((toy.num_vertices,), 1e-3))
    assert torch.equal(a, b) and a.shape == (toy.num_vertices, 3)
    assert float(a.min()) >= 0 and float(a.max()) <= 1
    assert not torch.equal(a, SkinAlbedo(toy, seed=2)(attrs, torch.full((toy.num_vertices,), 1e-3)))
    # Shading: Lambert with two-sided normals.
    n = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    rgb = torch.full((2, 3), 0.5)
    lit = lambert(rgb, n, view=torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]))
    assert torch.allclose(lit[0], lit[1]) and float(lit[0, 0]) > 0.5 * 0.32


def test_albedo_regions_on_the_open_head(open_head_model):
    m = open_head_model
    alb = SkinAlbedo(m, seed=0)
    lm = face_landmarks(m)
    assert float(lm.eye_l[0]) > 0 > float(lm.eye_r[0]) and 0.05 < lm.iod < 0.075
    assert float(lm.mouth[1]) < float(lm.eye_l[1]) - 0.7 * lm.iod
    attrs = alb.vertex_attributes()
    col = alb(attrs, torch.full((m.num_vertices,), 1e-4))
    t = m.template
    lum, red = col.mean(-1), col[:, 0] - col[:, 1]
    skin = attrs[:, 3:].sum(-1) == 0

    def patch(dx, dy):
        """Mean skin albedo of a 4 mm patch of the front surface at eye_r + (dx, dy)."""
        x, y = float(lm.eye_r[0]) + dx, float(lm.eye_r[1]) + dy
        near = skin & ((t[:, 0] - x).abs() < 0.006) & ((t[:, 1] - y).abs() < 0.006)
        z = float(t[near, 2].max())
        g = torch.linspace(-0.002, 0.002, 5)
        pts = torch.stack([x + g[:, None].expand(5, 5), y + g[None].expand(5, 5), torch.full((5, 5), z)], -1)
        a = torch.cat([pts.reshape(-1, 3), torch.zeros(25, 4)], 1)
        c = alb(a, torch.full((25,), 1e-4)).mean(0)
        return float(c.mean()), float(c[0] - c[1])

    (_, cheek_red), (brow, _), (forehead, _) = patch(0.0, -0.035), patch(-0.007, 0.025), patch(0.0, 0.06)
    mouth = float(lm.mouth[0]) - float(lm.eye_r[0]), float(lm.mouth[1]) - float(lm.eye_r[1])
    assert patch(*mouth)[1] > cheek_red + 0.05  # redder lips
    assert brow < forehead - 0.2  # darker eyebrows
    teeth = torch.cat([m.vertex_groups["teeth_upper"], m.vertex_groups["teeth_lower"]])
    assert float(lum[teeth].mean()) > 0.8
    assert float(red[m.vertex_groups["tongue"]].mean()) > 0.25
    # The distinct marks lie on the subject's left (+x) only.
    assert (alb.spot_centres[:, 0] > 0).all()


# ---------------------------------------------------------------------------------------------- the open head
def test_blur_bar_and_acceptance_run_with_the_open_head(open_head_model, tmp_path):
    """THE BAR: a 1-pixel Gaussian blur lowers a 256x256 frame's head-mask PSNR below 30 dB. And the acceptance
    run: 12 frames at 128x128 of the open head make a valid dataset."""
    m = open_head_model
    sc = make_script(m, 4, seed=0)
    cams = script_cameras(m, sc, 256)
    alb = SkinAlbedo(m, seed=0)
    for rgb, mask in render_frames(m, sc, cams, alb):
        frame = rgb.astype(np.float64) / 255.0
        head = mask > 0
        assert 0.15 < head.mean() < 0.5
        assert psnr_masked(frame, _blur(frame), head) < 30.0
    summary = synth_dataset(tmp_path / "oh", frames=12, size=128, seed=1, facemodel=m)
    assert validate_dataset(tmp_path / "oh") == []
    assert (summary["train"], summary["test"], summary["face_model"]) == (10, 2, m.name)
    assert summary["jaw"] == "coefficient" and summary["gaze"] == "coefficients"
    tr = read_dataset(tmp_path / "oh").tracking
    assert (tr.joint_rotations == 0).all() and tr.expression.shape == (12, 52) and tr.shape.shape == (0,)


def test_blinks_drive_the_eyelid_basis_when_the_model_has_one(toy, tmp_path):
    from dataclasses import replace

    lids = torch.zeros(2, toy.num_vertices, 3)
    lids[:, :10, 1] = -0.002
    model = replace(toy, eyelid_basis=lids)
    sc = make_script(model, 400, seed=3)
    assert float(sc.eyelids.max()) > 0.9 and torch.equal(sc.eyelids[:, 0], sc.eyelids[:, 1])
    synth_dataset(tmp_path / "lids", frames=8, size=32, seed=3, facemodel=model)
    assert validate_dataset(tmp_path / "lids") == []


def test_synth_dataset_reads_a_face_model_file(toy, tmp_path):
    from render_core.facemodel import write_facemodel

    path = write_facemodel(toy, tmp_path / "toy.facemodel")
    summary = synth_dataset(tmp_path / "ds", frames=3, size=32, seed=0, facemodel=str(path))
    assert summary["face_model"] == "toy-head" and validate_dataset(tmp_path / "ds") == []
