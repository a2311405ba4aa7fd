import json

import pytest
import torch

from render_core.drive import parse_line, parse_lines, read_drive_file
from render_core.errors import FrameError


def test_neutral_line_uses_the_default_camera(avatar):
    df = parse_line(avatar, {}, 64, 64)
    assert torch.equal(df.frame.expression, torch.zeros(1, avatar.num_expressions))
    assert torch.equal(df.frame.joint_rotations, torch.eye(3).expand(1, avatar.num_joints, 3, 3))
    assert df.camera.width == 64 and torch.allclose(df.camera.centres.norm(), torch.tensor(0.6), atol=1e-4)


def test_expression_by_position_and_by_name_agree(avatar):
    k = avatar.num_expressions
    values = [0.0] * k
    values[2] = 0.7
    a = parse_line(avatar, {"expression": values}, 32, 32).frame.expression
    b = parse_line(avatar, {"expression": {avatar.expression_names[2]: 0.7}}, 32, 32).frame.expression
    assert torch.equal(a, b) and float(a[0, 2]) == pytest.approx(0.7)


def test_wrong_length_and_unknown_names_list_what_is_valid(avatar):
    with pytest.raises(FrameError, match=f"exactly {avatar.num_expressions}"):
        parse_line(avatar, {"expression": [1.0]}, 32, 32)
    with pytest.raises(FrameError, match=avatar.expression_names[-1]):
        parse_line(avatar, {"expression": {"smile_big": 1.0}}, 32, 32)
    with pytest.raises(FrameError, match="root, neck, jaw, eye_l, eye_r"):
        parse_line(avatar, {"joints": {"elbow": [0, 0, 0]}}, 32, 32)
    with pytest.raises(FrameError, match="3 values.*6D"):
        parse_line(avatar, {"joints": {"jaw": [0, 0]}}, 32, 32)
    with pytest.raises(FrameError, match="valid keys"):
        parse_line(avatar, {"expresion": []}, 32, 32)
    with pytest.raises(FrameError, match="presets"):
        parse_line(avatar, {"camera": "behind"}, 32, 32)


def test_non_finite_values_are_refused(avatar):
    line = json.loads(f'{{"expression": {{"{avatar.expression_names[0]}": NaN}}}}')
    with pytest.raises(FrameError, match="finite"):
        parse_line(avatar, line, 32, 32)
    with pytest.raises(FrameError, match="finite"):
        parse_line(avatar, {"joints": {"jaw": [float("inf"), 0, 0]}}, 32, 32)
    with pytest.raises(FrameError, match="eyelids"):
        parse_line(avatar, {"eyelids": [1.0]}, 32, 32)


def test_joint_rotations_axis_angle_and_6d(avatar):
    aa = parse_line(avatar, {"joints": {"jaw": [0.3, 0, 0]}}, 32, 32).frame.joint_rotations
    jaw = avatar.joint_index("jaw")
    r6 = aa[0, jaw, :2].reshape(-1).tolist()
    six = parse_line(avatar, {"joints": {"jaw": r6}}, 32, 32).frame.joint_rotations
    assert torch.allclose(aa, six, atol=1e-6)
    assert not torch.allclose(aa[0, jaw], torch.eye(3))


def test_cameras_presets_orbits_and_explicit(avatar):
    left = parse_line(avatar, {"camera": "left"}, 32, 32).camera
    assert float(left.centres[0, 0]) > 0.3  # subject's left is +x
    orb = parse_line(avatar, {"camera": {"yaw": -30, "distance": 1.0}}, 32, 32).camera
    assert torch.allclose(orb.centres.norm(), torch.tensor(1.0), atol=1e-5) and float(orb.centres[0, 0]) < 0
    explicit = {"K": [[100, 0, 50], [0, 100, 50], [0, 0, 1]], "R": [[1, 0, 0], [0, -1, 0], [0, 0, -1]],
                "t": [0, 0, 0.5], "width": 100, "height": 100}
    cam = parse_line(avatar, {"camera": explicit}, 50, 50).camera
    assert float(cam.K[0, 0, 0]) == pytest.approx(50.0) and cam.width == 50


def test_file_errors_name_the_line(avatar, tmp_path):
    path = tmp_path / "d.jsonl"
    path.write_text('{}\n\n{"expression": [1]}\n')
    with pytest.raises(FrameError, match=r"d.jsonl:3: .*exactly"):
        read_drive_file(path, avatar, 32, 32)
    path.write_text("{}\n{not json\n")
    with pytest.raises(FrameError, match=r":2: not valid JSON"):
        read_drive_file(path, avatar, 32, 32)
    path.write_text("\n\n")
    with pytest.raises(FrameError, match="no frames"):
        read_drive_file(path, avatar, 32, 32)
    assert len(parse_lines([(1, "{}"), (2, "[]")][:1], avatar, 8, 8)) == 1
    with pytest.raises(FrameError, match="JSON object"):
        parse_lines([(1, "[1, 2]")], avatar, 8, 8)
