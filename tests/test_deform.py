import dataclasses

import pytest
import torch

from render_core.deform import Frame, Splats, blend, deform, joint_transforms, pose_features, shade, skin
from render_core.errors import FrameError
from render_core.rotation import axis_angle_to_matrix, matrix_to_rot6d, quat_to_matrix
from render_core.sh import eval_sh

PROPS = ("means", "quats", "log_scales", "opacity_logits", "sh")


def _rand_joints(avatar, b, scale=0.3):
    return {name: torch.randn(b, 3) * scale for name in avatar.joint_names}


def _assert_splats_close(a: Splats, b: Splats, atol=1e-6):
    for name in ("means", "quats", "scales", "opacities", "sh", "sh_rotations"):
        x, y = getattr(a, name), getattr(b, name)
        if x is None or y is None:
            assert x is None and y is None, name
            continue
        torch.testing.assert_close(x, y, rtol=0, atol=atol, msg=name)
    assert a.sh_degree == b.sh_degree


def _rotate_about(points, rot, centre):
    return (points - centre) @ rot.T + centre


# ---------------------------------------------------------------------------------------------- blend (Eq. 1)


def test_one_hot_reproduces_each_blendshape_exactly(avatar):
    k = avatar.num_expressions
    out = blend(avatar, torch.eye(k))  # frame i has psi = e_i
    for prop in PROPS:
        got = getattr(out, prop)
        base = getattr(avatar.neutral, prop).float()
        delta = getattr(avatar.deltas, prop).float()
        assert got.dtype == torch.float32
        for i in range(k):
            assert torch.equal(got[i], base + delta[i]), (prop, i)


def test_zero_coefficients_give_neutral(avatar):
    out = blend(avatar, torch.zeros(2, avatar.num_expressions))
    for prop in PROPS:
        for i in range(2):
            assert torch.equal(getattr(out, prop)[i], getattr(avatar.neutral, prop)), prop


def test_blend_is_linear_and_casts_fp16_and_keeps_float64(avatar):
    psi = torch.randn(3, avatar.num_expressions)
    out = blend(avatar, psi)
    want = avatar.neutral.means + torch.einsum("bk,knc->bnc", psi, avatar.deltas.means)
    torch.testing.assert_close(out.means, want, rtol=0, atol=1e-6)
    half = blend(avatar.to(torch.float16), psi)
    assert half.sh.dtype == torch.float32
    torch.testing.assert_close(half.means, want, rtol=0, atol=2e-3)
    assert blend(avatar, psi.double()).sh.dtype == torch.float64


# ------------------------------------------------------------------------------------------------ kinematics


def test_joint_transforms_identity_is_exact(avatar):
    eye = torch.eye(3).expand(2, avatar.num_joints, 3, 3)
    a = joint_transforms(avatar, eye)
    assert a.shape == (2, avatar.num_joints, 3, 4)
    assert torch.equal(a, torch.eye(3, 4).expand_as(a))


def test_joint_transforms_match_forward_kinematics_definition(avatar):
    rots = axis_angle_to_matrix(torch.randn(avatar.num_joints, 3, dtype=torch.float64))
    pos = avatar.joint_positions.double()

    def h(r, t):
        m = torch.eye(4, dtype=torch.float64)
        m[:3, :3], m[:3, 3] = r, t
        return m

    g = []
    for j, parent in enumerate(avatar.joint_parents):
        local = h(rots[j], pos[j] - (pos[parent] if parent >= 0 else 0))
        g.append(local if parent < 0 else g[parent] @ local)
    want = torch.stack([g[j] @ h(torch.eye(3, dtype=torch.float64), -pos[j]) for j in range(len(g))])[:, :3]
    got = joint_transforms(avatar.to(torch.float64), rots[None])[0]
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)


def test_pose_features_layout():
    rots = torch.eye(3).expand(2, 5, 3, 3).clone()
    r = axis_angle_to_matrix(torch.tensor([0.3, -0.2, 0.1]))
    rots[1, 2] = r  # jaw of frame 1 (third joint = second non-root joint)
    f = pose_features(rots)
    assert f.shape == (2, 36)
    assert torch.equal(f[0], torch.zeros(36))
    assert torch.equal(f[1, 9:18], (r - torch.eye(3)).reshape(9))
    assert torch.equal(f[1, :9], torch.zeros(9)) and torch.equal(f[1, 18:], torch.zeros(18))


# ------------------------------------------------------------------------------------------------- deform


def test_identity_pose_keeps_rest_state(avatar):
    s = deform(avatar, Frame.neutral(avatar))
    n = avatar.num_gaussians
    assert s.means.shape == (1, n + avatar.num_mouth, 3)
    assert torch.equal(s.means[0, :n], avatar.neutral.means)
    assert torch.equal(s.means[0, n:], avatar.mouth.means)
    quats = torch.cat([avatar.neutral.quats, avatar.mouth.quats])
    torch.testing.assert_close(s.quats[0], torch.nn.functional.normalize(quats, dim=-1), rtol=0, atol=1e-6)
    log_scales = torch.cat([avatar.neutral.log_scales, avatar.mouth.log_scales])
    logits = torch.cat([avatar.neutral.opacity_logits, avatar.mouth.opacity_logits])
    torch.testing.assert_close(s.scales[0], log_scales.exp())
    torch.testing.assert_close(s.opacities[0], torch.sigmoid(logits))
    assert torch.equal(s.sh[0], torch.cat([avatar.neutral.sh, avatar.mouth.sh]))
    assert torch.equal(s.sh_rotations[0], torch.eye(3).expand(n + avatar.num_mouth, 3, 3))
    assert s.sh_degree == avatar.sh_degree


def test_batched_frames_equal_frame_by_frame(avatar):
    b = 4
    frame = Frame.from_params(avatar, expression=torch.randn(b, avatar.num_expressions),
                              joints=_rand_joints(avatar, b), eyelids=torch.rand(b, 2))
    batched = deform(avatar, frame)
    for i in range(b):
        single = Frame(frame.expression[i:i + 1], frame.joint_rotations[i:i + 1], frame.eyelids[i:i + 1])
        one = deform(avatar, single)
        _assert_splats_close(Splats(**{f.name: (v[i:i + 1] if torch.is_tensor(v) else v)
                                       for f in dataclasses.fields(batched)
                                       for v in [getattr(batched, f.name)]}), one)
    # Frame.stack gives the same batch.
    stacked = Frame.stack([Frame(frame.expression[i:i + 1], frame.joint_rotations[i:i + 1],
                                 frame.eyelids[i:i + 1]) for i in range(b)])
    _assert_splats_close(deform(avatar, stacked), batched, atol=0)


def test_root_rotation_is_rigid_about_root_joint(avatar):
    aa = torch.tensor([0.4, -0.7, 0.25])
    rot = axis_angle_to_matrix(aa)
    s = deform(avatar, Frame.from_params(avatar, joints={"root": aa}))
    centre = avatar.joint_positions[0]
    rest_means = torch.cat([avatar.neutral.means, avatar.mouth.means])
    torch.testing.assert_close(s.means[0], _rotate_about(rest_means, rot, centre), rtol=0, atol=1e-6)
    rest_rot = quat_to_matrix(torch.cat([avatar.neutral.quats, avatar.mouth.quats]))
    torch.testing.assert_close(quat_to_matrix(s.quats[0]), rot @ rest_rot, rtol=0, atol=1e-5)
    torch.testing.assert_close(s.sh_rotations[0], rot.expand_as(s.sh_rotations[0]), rtol=0, atol=1e-6)


def test_jaw_moves_lower_teeth_and_chin_not_upper_teeth_or_forehead(avatar):
    rest = deform(avatar, Frame.neutral(avatar))
    s = deform(avatar, Frame.from_params(avatar, joints={"jaw": torch.tensor([0.35, 0.0, 0.0])}))
    n = avatar.num_gaussians
    mouth_move = (s.means[0, n:] - rest.means[0, n:]).norm(dim=-1)
    upper, lower = avatar.mouth_group == 0, avatar.mouth_group == 1
    assert upper.any() and lower.any()
    assert torch.equal(s.means[0, n:][upper], rest.means[0, n:][upper])
    assert (mouth_move[lower] > 1e-3).all()
    # Lower teeth rotate rigidly about the jaw joint.
    want = _rotate_about(avatar.mouth.means[lower], axis_angle_to_matrix(torch.tensor([0.35, 0.0, 0.0])),
                         avatar.joint_positions[avatar.joint_index("jaw")])
    torch.testing.assert_close(s.means[0, n:][lower], want, rtol=0, atol=1e-6)
    face_move = (s.means[0, :n] - rest.means[0, :n]).norm(dim=-1)
    w_jaw = avatar.lbs_weights[:, avatar.joint_index("jaw")]
    jaw_region = w_jaw > 0.5
    forehead = (avatar.neutral.means[:, 1] > 0.05) & (w_jaw < 0.1)
    assert jaw_region.sum() > 5 and forehead.sum() > 5
    assert face_move[jaw_region].mean() > 3 * face_move[forehead].mean()


def test_6d_and_axis_angle_give_same_splats(avatar):
    joints = _rand_joints(avatar, 2, scale=0.5)
    r6 = {name: matrix_to_rot6d(axis_angle_to_matrix(v)) for name, v in joints.items()}
    psi = torch.randn(2, avatar.num_expressions)
    a = deform(avatar, Frame.from_params(avatar, expression=psi, joints=joints))
    b = deform(avatar, Frame.from_params(avatar, expression=psi, joints=r6))
    _assert_splats_close(a, b, atol=1e-5)
    full = torch.stack([joints[name] for name in avatar.joint_names], dim=1)  # [B, J, 3]
    _assert_splats_close(a, deform(avatar, Frame.from_params(avatar, expression=psi, joints=full)), atol=0)


def test_sh_paths_agree_under_head_pose(avatar):
    frame = Frame.from_params(avatar, expression=torch.randn(3, avatar.num_expressions),
                              joints=_rand_joints(avatar, 3, scale=0.6))
    local = deform(avatar, frame, rotate_sh=False)
    world = deform(avatar, frame, rotate_sh=True)
    assert local.sh_rotations is not None and world.sh_rotations is None
    cams = torch.tensor([[0.0, 0.0, 0.6], [0.4, 0.1, 0.3], [-0.3, -0.2, 0.5]])
    c_local, c_world = shade(local, cams), shade(world, cams)
    assert c_local.shape == (3, local.count, 3)
    torch.testing.assert_close(c_local, c_world, rtol=0, atol=1e-5)
    # The pose matters: evaluating the rest-frame SH with world directions differs.
    d = torch.nn.functional.normalize(local.means - cams[:, None], dim=-1)
    naive = (eval_sh(local.sh, d) + 0.5).clamp_min(0)
    assert (naive - c_local).abs().max() > 1e-3


def test_shade_broadcasts_one_frame_to_many_cameras(avatar):
    s = deform(avatar, Frame.from_params(avatar, joints={"neck": torch.tensor([0.1, 0.5, 0.0])}))
    cams = torch.tensor([[0.0, 0.0, 0.6], [0.5, 0.0, 0.4]])
    out = shade(s, cams)
    assert out.shape == (2, s.count, 3) and (out >= 0).all()
    torch.testing.assert_close(out[1:], shade(s, cams[1]), rtol=0, atol=0)


def test_pose_correctives_apply_only_for_non_root_joints(avatar):
    assert avatar.pose_correctives is not None
    plain = dataclasses.replace(avatar, pose_correctives=None)
    root = Frame.from_params(avatar, joints={"root": torch.tensor([0.3, 0.2, -0.1])})
    assert torch.equal(deform(avatar, root).means, deform(plain, root).means)
    neck = Frame.from_params(avatar, joints={"neck": torch.tensor([0.3, 0.2, -0.1])})
    n = avatar.num_gaussians
    diff = (deform(avatar, neck).means - deform(plain, neck).means)[0]
    assert diff[:n].abs().max() > 1e-5
    assert torch.equal(diff[n:], torch.zeros_like(diff[n:]))  # mouth has no correctives


def test_eyelids_move_only_gaussians_with_offsets_and_follow_the_head(avatar):
    n = avatar.num_gaussians
    off = avatar.eyelid_offsets[0]  # left eyelid [N, 3]
    has_offset = off.abs().amax(-1) > 0
    base = deform(avatar, Frame.neutral(avatar))
    s = deform(avatar, Frame.from_params(avatar, eyelids=torch.tensor([0.7, 0.0])))
    moved = (s.means[0] != base.means[0]).any(-1)
    assert moved[:n].sum() > 5 and not moved[n:].any()
    assert not (moved[:n] & ~has_offset).any()
    torch.testing.assert_close(s.means[0, :n], avatar.neutral.means + 0.7 * off, rtol=0, atol=1e-7)
    # With the head turned the eyelid displacement turns with it (applied before LBS).
    aa = torch.tensor([0.0, 0.8, 0.0])
    turned = deform(avatar, Frame.from_params(avatar, joints={"root": aa}))
    lid = deform(avatar, Frame.from_params(avatar, joints={"root": aa}, eyelids=torch.tensor([0.7, 0.0])))
    want = 0.7 * off @ axis_angle_to_matrix(aa).T
    torch.testing.assert_close((lid.means - turned.means)[0, :n], want, rtol=0, atol=1e-7)


def test_gradients_flow_to_expression(avatar):
    psi = torch.randn(2, avatar.num_expressions, requires_grad=True)
    frame = Frame(psi, axis_angle_to_matrix(torch.randn(2, avatar.num_joints, 3) * 0.2))
    deform(avatar, frame).means.square().sum().backward()
    assert psi.grad is not None and torch.isfinite(psi.grad).all() and (psi.grad.abs() > 0).all()


def test_gradcheck_float64(avatar):
    a64 = avatar.to(torch.float64)
    rots = axis_angle_to_matrix(torch.randn(1, avatar.num_joints, 3, dtype=torch.float64) * 0.3)
    weights = torch.randn(1, a64.num_gaussians + a64.num_mouth, 3, dtype=torch.float64)

    def f(psi):
        s = deform(a64, Frame(psi, rots, torch.tensor([[0.2, 0.4]], dtype=torch.float64)))
        return (s.means * weights).sum() + s.quats.sum() + s.scales.sum()

    psi = torch.randn(1, a64.num_expressions, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(f, (psi,))


def test_skin_accepts_custom_blend(avatar):
    frame = Frame.neutral(avatar, batch=2)
    s = skin(avatar, blend(avatar, frame.expression), frame, rotate_sh=True)
    assert s.sh_rotations is None and s.means.shape[0] == 2


# -------------------------------------------------------------------------------------------------- frames


def test_frame_from_params_by_name_and_broadcast(avatar):
    names = avatar.expression_names
    f = Frame.from_params(avatar, expression={names[1]: 0.5, names[3]: torch.tensor([1.0, 2.0])},
                          joints={"jaw": torch.tensor([0.2, 0.0, 0.0])})
    assert f.batch_size == 2 and f.eyelids is None
    want = torch.zeros(2, avatar.num_expressions)
    want[:, 1], want[:, 3] = 0.5, torch.tensor([1.0, 2.0])
    assert torch.equal(f.expression, want)
    jaw = avatar.joint_index("jaw")
    assert torch.equal(f.joint_rotations[1, jaw], axis_angle_to_matrix(torch.tensor([0.2, 0.0, 0.0])))
    assert torch.equal(f.joint_rotations[:, 0], torch.eye(3).expand(2, 3, 3))
    assert f.to(torch.float64).expression.dtype == torch.float64
    # A [3, 3] value under a joint name is three axis-angle rows (B = 3), not a matrix.
    aa = torch.randn(3, 3) * 0.3
    g = Frame.from_params(avatar, joints={"neck": aa})
    assert torch.equal(g.joint_rotations[:, avatar.joint_index("neck")], axis_angle_to_matrix(aa))


def test_named_joints_of_mixed_kinds_equal_their_one_by_one_conversions(avatar):
    g = torch.Generator().manual_seed(3)
    aa = torch.randn(2, 3, generator=g) * 0.4
    m6 = axis_angle_to_matrix(torch.randn(2, 3, generator=g) * 0.4)
    mat = axis_angle_to_matrix(torch.randn(2, 3, generator=g) * 0.4)
    aa2 = torch.randn(3, generator=g) * 0.4  # batch 1: broadcast
    names = avatar.joint_names
    f = Frame.from_params(avatar, joints={names[2]: aa, names[1]: matrix_to_rot6d(m6), names[0]: mat,
                                          names[-1]: aa2})
    got = f.joint_rotations
    assert torch.allclose(got[:, 2], axis_angle_to_matrix(aa), atol=0)
    assert torch.allclose(got[:, 1], m6, atol=1e-6)
    assert torch.equal(got[:, 0], mat)
    assert torch.allclose(got[:, -1], axis_angle_to_matrix(aa2).expand(2, 3, 3), atol=0)
    for j in range(3, avatar.num_joints - 1):
        assert torch.equal(got[:, j], torch.eye(3).expand(2, 3, 3))


def test_a_non_finite_named_joint_is_refused_by_its_name(avatar):
    name = avatar.joint_names[-1]
    with pytest.raises(FrameError, match="finite") as info:
        Frame.from_params(avatar, joints={avatar.joint_names[0]: torch.zeros(3),
                                          name: torch.tensor([0.0, float("nan"), 0.0])})
    assert info.value.field == f"joints.{name}"


def test_frame_errors(avatar):
    k = avatar.num_expressions
    with pytest.raises(FrameError, match=rf"expected {k} expression coefficients.*name") as info:
        Frame.from_params(avatar, expression=torch.zeros(1, k + 1))
    assert info.value.field == "expression"
    with pytest.raises(FrameError, match=str(k)):
        deform(avatar, Frame(torch.zeros(1, k - 1), torch.eye(3).expand(1, avatar.num_joints, 3, 3)))
    bad = torch.zeros(1, k)
    bad[0, 2] = float("nan")
    with pytest.raises(FrameError, match="expression"):
        Frame.from_params(avatar, expression=bad)
    with pytest.raises(FrameError, match="expression"):
        deform(avatar, Frame(bad, torch.eye(3).expand(1, avatar.num_joints, 3, 3)))
    with pytest.raises(FrameError) as info:
        Frame.from_params(avatar, joints={"jaww": torch.zeros(3)})
    for name in avatar.joint_names:
        assert name in str(info.value)
    with pytest.raises(FrameError, match="unknown expression"):
        Frame.from_params(avatar, expression={"nope": 1.0})
    with pytest.raises(FrameError, match="joint_rotations"):
        Frame(torch.zeros(1, k), torch.eye(3).expand(1, avatar.num_joints - 1, 3, 3)).check(avatar)
    with pytest.raises(FrameError, match="eyelids"):
        Frame.from_params(avatar, eyelids=torch.tensor([float("inf"), 0.0]))
    with pytest.raises(FrameError, match="rotation"):
        Frame(torch.zeros(1, k), 2 * torch.eye(3).expand(1, avatar.num_joints, 3, 3)).check(avatar)
    with pytest.raises(FrameError, match="batch"):
        Frame.from_params(avatar, expression=torch.zeros(2, k), eyelids=torch.zeros(3, 2))
