"""Avatar initialisation from a face model (docs/method.md section 3, per Gaussian)."""

from __future__ import annotations

import math

import pytest
import torch

from render_core.deform import Frame, blend
from render_core.facemodel import FaceModel
from render_core.raster import native
from render_core.renderer import AvatarRenderer
from render_core.rotation import axis_angle_to_matrix, matrix_to_quat, quat_multiply
from render_core.train.geometry import closest_points
from render_core.train.initialize import init_avatar, poisson_disk


@pytest.fixture(scope="module")
def avatar(head):
    return init_avatar(head, gaussians=4000, mouth=200, seed=1)


def test_counts_weights_and_layout(avatar, head):
    assert avatar.num_gaussians == 4000 and avatar.num_mouth == 200
    assert avatar.expression_names == head.expression_names and avatar.joint_names == head.joint_names
    assert avatar.mouth_joint_names == ("head", "jaw") and avatar.face_model == head.name
    torch.testing.assert_close(avatar.lbs_weights.sum(1), torch.ones(4000))
    assert float(avatar.neutral.opacity_logits.sigmoid().mean()) == pytest.approx(0.1, abs=1e-6)


def test_poisson_disk_samples_lie_on_the_mesh_and_keep_their_distance(head):
    """Exactly N points on the surface, none closer than 0.6 x the spacing of N samples in hexagonal packing on
    the mesh's area (2 sqrt(A / (2 sqrt(3) N))). Independent uniform samples, or the earlier grid thinning, have
    their closest pair below 0.1 of it."""
    v, f = head.template.double(), head.faces
    tri = v[f]
    area = float(0.5 * torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=1).sum())
    n = 3000
    t, bary = poisson_disk(v, f, n, torch.Generator().manual_seed(3))
    assert t.shape == (n,) and bary.shape == (n, 3)
    assert float(bary.min()) >= 0 and torch.allclose(bary.sum(1), torch.ones(n, dtype=bary.dtype))
    x = (tri[t] * bary[..., None]).sum(1)
    on_t, on_b = closest_points(v, f, x)
    assert float(((v[f[on_t]] * on_b[..., None]).sum(1) - x).norm(dim=1).max()) < 1e-9
    spacing = 2 * math.sqrt(area / (2 * math.sqrt(3) * n))
    nearest = (torch.cdist(x, x) + torch.eye(n) * 1e9).min(1).values
    assert float(nearest.min()) >= 0.6 * spacing
    assert float(nearest.median()) >= 0.7 * spacing
    uniform = (tri[t] * torch.distributions.Dirichlet(torch.ones(3)).sample((n,)).double()[..., None]).sum(1)
    assert float((torch.cdist(uniform, uniform) + torch.eye(n) * 1e9).min()) < 0.1 * spacing
    # Deterministic for a generator state; another seed gives other samples.
    again = poisson_disk(v, f, n, torch.Generator().manual_seed(3))
    assert torch.equal(again[0], t) and torch.equal(again[1], bary)
    assert not torch.equal(poisson_disk(v, f, n, torch.Generator().manual_seed(4))[0], t)


def test_one_hot_blend_lands_on_the_posed_surface(avatar, head):
    """psi = e_k moves every Gaussian exactly with the surface point it was sampled at."""
    k = head.expression_names.index("jawOpen")
    psi = torch.zeros(1, head.num_expressions)
    psi[0, k] = 1.0
    moved = blend(avatar, psi).means[0]
    rest = avatar.neutral.means
    # Reconstruct each Gaussian's surface point on M_k: same barycentric combination of the moved vertices.
    v_k, _ = head.evaluate(psi, head.neutral_rotations(1))
    offset = moved - rest
    assert float(offset.norm(dim=1).max()) > 0.005  # the jaw really opens
    nearest = torch.cdist(rest, head.template).argmin(1)
    err = (offset - (v_k[0] - head.template)[nearest]).norm(dim=1)
    assert float(err.median()) < 5e-4  # the delta follows the nearby vertices' motion


def test_untouched_regions_store_no_pairs(avatar, head):
    k = head.expression_names.index("eyeBlinkLeft")
    moving = (avatar.deltas.means[k].abs().sum(1) > 0) | (avatar.deltas.quats[k].abs().sum(1) > 0)
    far = avatar.neutral.means[:, 0] < -0.04  # the right side of the face and head
    assert not bool(moving[far].any())
    stats = native.NativeAvatar(avatar).stats
    assert 0.02 < stats.stored_fraction < 0.5


def tetra_model() -> tuple[FaceModel, torch.Tensor]:
    """A tetrahedron face model whose one blendshape rotates it rigidly by 30 degrees about z; and that rotation."""
    t = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]) * 0.1
    faces = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    r = axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.pi / 6]))
    model = FaceModel(name="tetra", template=t, faces=faces, expression_names=["turn"],
                      expression_basis=(t @ r.T - t)[None], joint_names=["root", "jaw"], joint_parents=[-1, 0],
                      joint_positions=torch.zeros(2, 3), lbs_weights=torch.tensor([[1.0, 0.0]] * 4),
                      skull_joint="root")
    return model, r


def test_rotation_delta_is_the_deformation_rotation():
    """A blendshape that rotates a whole mesh rigidly by 30 degrees about z rotates every Gaussian the same way."""
    model, r = tetra_model()
    av = init_avatar(model, gaussians=200, mouth=2, seed=0)
    q0 = av.neutral.quats
    q1 = torch.nn.functional.normalize(q0 + av.deltas.quats[0], dim=-1)
    want = quat_multiply(matrix_to_quat(r).expand_as(q0), q0)
    assert float(torch.minimum((q1 - want).norm(dim=1), (q1 + want).norm(dim=1)).max()) < 1e-5
    torch.testing.assert_close(av.neutral.means + av.deltas.means[0], av.neutral.means @ r.T, atol=1e-6, rtol=0)


def test_initialised_avatar_renders_and_opens_its_mouth(head):
    av = init_avatar(head, gaussians=3000, mouth=100, opacity=0.9, seed=2)
    renderer = AvatarRenderer(av)
    cams = av.default_camera and __import__("render_core.drive", fromlist=["default_camera"]).default_camera(
        av, 64, 64)
    neutral = renderer.render(Frame.neutral(av), cams)
    jaw = renderer.render(Frame.from_params(av, expression={"jawOpen": 1.0}), cams)
    assert 0.1 < float(neutral.alpha.mean()) < 0.9
    assert float((neutral.rgb - jaw.rgb).abs().max()) > 0.05
