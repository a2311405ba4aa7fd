"""The mesh rasterizer against analytic coverage, depth order, perspective-correct interpolation and areas."""

import math

import numpy as np
import pytest
import torch

from render_core.camera import Cameras, intrinsics, orbit
from render_core.data.meshraster import icosphere, rasterize, rasterize_mesh, vertex_normals

W, H, F = 40, 30, 25.0


def _camera(width=W, height=H, focal=F, batch=1) -> Cameras:
    """Identity extrinsics: world = camera space (x right, y down, z forward)."""
    K = intrinsics(width, height, focal)[None].expand(batch, 3, 3).clone()
    return Cameras(K, torch.eye(3).expand(batch, 3, 3).clone(), torch.zeros(batch, 3), width, height)


def _unproject(uv, z, focal=F, width=W, height=H):
    """World points (identity camera) at pixel coordinates uv [N, 2] and depth z [N]."""
    uv = np.asarray(uv, dtype=np.float64)
    x = (uv[:, 0] - width / 2) / focal * z
    y = (uv[:, 1] - height / 2) / focal * z
    return np.stack([x, y, np.broadcast_to(z, x.shape)], -1)


def _analytic_coverage(uv, width=W, height=H):
    """Inclusive edge test of every pixel centre against the screen triangle uv [3, 2], in float64 numpy.

    Returns (covered [H, W] bool, margin [H, W]: the smallest |edge function| / edge length, in pixels)."""
    ys, xs = np.mgrid[0:height, 0:width] + 0.5
    uv = np.asarray(uv, dtype=np.float64)
    area = (uv[1, 0] - uv[0, 0]) * (uv[2, 1] - uv[0, 1]) - (uv[1, 1] - uv[0, 1]) * (uv[2, 0] - uv[0, 0])
    inside = np.ones((height, width), bool)
    margin = np.full((height, width), np.inf)
    for i in range(3):
        a, b = uv[i], uv[(i + 1) % 3]
        e = ((b[0] - a[0]) * (ys - a[1]) - (b[1] - a[1]) * (xs - a[0])) * np.sign(area)
        inside &= e >= 0
        margin = np.minimum(margin, np.abs(e) / np.hypot(*(b - a)))
    return inside, margin


@pytest.mark.parametrize("uv", [
    [(5.3, 4.1), (33.7, 9.2), (12.2, 26.6)],  # clockwise as seen on screen (y down): a back face
    [(5.3, 4.1), (12.2, 26.6), (33.7, 9.2)],  # the same triangle, counter-clockwise: a front face
    [(1.1, 14.9), (38.6, 15.2), (20.4, 16.3)],  # a sliver
])
def test_single_triangle_coverage_matches_analytic_edge_tests(uv):
    verts = torch.tensor(_unproject(uv, np.array([2.0, 3.0, 2.5])), dtype=torch.float32)[None]
    _, mask, depth, face_id = rasterize_mesh(verts, torch.tensor([[0, 1, 2]]), _camera())
    # The rasterizer projects float32 world points: compare where the centre is not within 1e-4 px of an edge.
    uv_f = (verts[0].double() / verts[0, :, 2:].double() * F)[:, :2].numpy() + [W / 2, H / 2]
    want, margin = _analytic_coverage(uv_f)
    sure = margin > 1e-4
    assert want.sum() > 5
    np.testing.assert_array_equal(mask[0].numpy()[sure], want[sure])
    assert (face_id[0][mask[0]] == 0).all() and (face_id[0][~mask[0]] == -1).all()
    assert (depth[0][mask[0]] >= 2.0 - 1e-5).all() and (depth[0][mask[0]] <= 3.0 + 1e-5).all()
    assert (depth[0][~mask[0]] == 0).all()


def test_backface_culling_drops_triangles_facing_away_from_the_camera():
    uv = [(5.3, 4.1), (33.7, 9.2), (12.2, 26.6)]
    for order in ([0, 1, 2], [0, 2, 1]):
        world = _unproject([uv[i] for i in order], np.array([2.0, 2.4, 2.2]))
        normal = np.cross(world[1] - world[0], world[2] - world[0])  # right-hand rule
        facing = float(normal @ (0 - world[0])) > 0  # towards the camera centre (the origin)
        verts = torch.tensor(world, dtype=torch.float32)[None]
        _, culled, _, _ = rasterize_mesh(verts, torch.tensor([[0, 1, 2]]), _camera(), cull_backfaces=True)
        _, kept, _, _ = rasterize_mesh(verts, torch.tensor([[0, 1, 2]]), _camera())
        assert kept.any() and bool(culled.any()) == facing


@pytest.mark.parametrize("near_first", [True, False])
def test_nearer_of_two_overlapping_triangles_wins(near_first):
    far = _unproject([(2, 2), (38, 3), (20, 28)], np.array(3.0))
    near = _unproject([(10, 1), (30, 20), (5, 25)], np.array([1.5, 2.0, 1.8]))
    verts = torch.tensor(np.concatenate([near, far] if near_first else [far, near]), dtype=torch.float32)[None]
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
    colour = torch.tensor([[1.0], [1.0], [1.0], [2.0], [2.0], [2.0]])[None]  # the first triangle 1, the second 2
    image, mask, depth, face_id = rasterize_mesh(verts, faces, _camera(), colour)
    near_id = 0 if near_first else 1
    near_cov, m1 = _analytic_coverage(near[:, :2] / near[:, 2:] * F + [W / 2, H / 2])
    far_cov, m2 = _analytic_coverage(far[:, :2] / far[:, 2:] * F + [W / 2, H / 2])
    sure = (m1 > 1e-4) & (m2 > 1e-4)
    both = near_cov & far_cov & sure
    assert both.sum() > 20
    assert (face_id[0].numpy()[both] == near_id).all()
    assert (image[0, ..., 0].numpy()[both] == near_id + 1).all()
    assert (depth[0].numpy()[both] < 2.0 + 1e-5).all()
    only_far = far_cov & ~near_cov & sure
    assert (face_id[0].numpy()[only_far] == 1 - near_id).all()
    np.testing.assert_allclose(depth[0].numpy()[only_far], 3.0, rtol=1e-6)
    np.testing.assert_array_equal(mask[0].numpy()[sure], (near_cov | far_cov)[sure])


def test_exact_depth_ties_go_to_the_lower_face_index():
    tri = _unproject([(2, 2), (38, 3), (20, 28)], np.array(2.0))
    verts = torch.tensor(np.concatenate([tri, tri]), dtype=torch.float32)[None]
    _, mask, _, face_id = rasterize_mesh(verts, torch.tensor([[3, 4, 5], [0, 1, 2]]), _camera())
    assert mask.any() and (face_id[mask] == 0).all()


def test_perspective_correct_interpolation_recovers_a_linear_attribute_on_a_slanted_plane():
    # A quad on the plane z = 2 + 0.9 x (about 42 degrees to the image plane), seen by the identity camera.
    plane = lambda x, y: 2.0 + 0.9 * x  # noqa: E731
    corners = np.array([[-1.0, -0.8], [0.9, -0.8], [0.9, 0.8], [-1.0, 0.8]])
    quad = np.array([[x, y, plane(x, y)] for x, y in corners])
    verts = torch.tensor(quad, dtype=torch.float64)[None]
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    a = np.array([[0.7, -1.3, 2.1], [0.2, 0.5, -0.4]])
    bias = np.array([0.3, -1.0])
    attr = torch.tensor(quad @ a.T + bias)[None]  # two attributes, each linear in the world position
    image, mask, depth, face_id = rasterize_mesh(verts, faces, _camera(), attr)
    assert mask.sum() > 300
    ys, xs = np.nonzero(mask[0].numpy())
    # The exact surface point on each covered pixel's ray: (u - cx) z / f with z on the plane.
    dx, dy = (xs + 0.5 - W / 2) / F, (ys + 0.5 - H / 2) / F
    z = 2.0 / (1.0 - 0.9 * dx)
    world = np.stack([dx * z, dy * z, z], -1)
    np.testing.assert_allclose(depth[0].numpy()[ys, xs], z, rtol=1e-9)
    np.testing.assert_allclose(image[0].numpy()[ys, xs], world @ a.T + bias, rtol=1e-9, atol=1e-9)
    # Screen-space (affine) interpolation would be visibly wrong: within one triangle the truth is far from any
    # affine function of the pixel coordinates, so the test tells the two apart.
    one = (face_id[0].numpy()[ys, xs] == 0)
    design = np.stack([xs[one], ys[one], np.ones(one.sum())], -1)
    target = (world @ a.T + bias)[one, 0]
    residual = target - design @ np.linalg.lstsq(design, target, rcond=None)[0]
    assert np.abs(residual).max() > 0.05


def test_triangle_crossing_the_image_border_and_near_plane():
    uv = [(-15.0, -10.0), (25.0, 12.0), (8.0, 45.0)]  # two corners outside the image
    verts = torch.tensor(_unproject(uv, np.array([2.0, 2.5, 3.0])), dtype=torch.float32)[None]
    _, mask, _, _ = rasterize_mesh(verts, torch.tensor([[0, 1, 2]]), _camera())
    uv_f = (verts[0].double() / verts[0, :, 2:].double() * F)[:, :2].numpy() + [W / 2, H / 2]
    want, margin = _analytic_coverage(uv_f)
    sure = margin > 1e-4
    assert want[:, 0].any() and want[0].any()  # the coverage really touches the left and top borders
    np.testing.assert_array_equal(mask[0].numpy()[sure], want[sure])
    # A vertex behind the near plane drops the whole triangle (no clipping).
    behind = verts.clone()
    behind[0, 2, 2] = -1.0
    _, mask, _, face_id = rasterize_mesh(behind, torch.tensor([[0, 1, 2]]), _camera())
    assert not mask.any() and (face_id == -1).all()


def test_empty_scene():
    verts = torch.zeros(2, 3, 3)
    cams = _camera(batch=2)
    for faces in (torch.zeros(0, 3, dtype=torch.int64), torch.tensor([[0, 1, 2]])):  # none, degenerate
        image, mask, depth, face_id = rasterize_mesh(verts, faces, cams, torch.ones(1, 3, 4))
        assert image.shape == (2, H, W, 4) and (image == 0).all()
        assert mask.shape == (2, H, W) and not mask.any()
        assert (depth == 0).all() and (face_id == -1).all()


def test_icosphere_mask_area_matches_its_projected_disc():
    radius, distance = 0.1, 0.6
    verts, faces = icosphere(4, radius)
    cams = orbit([0.0, 70.0], [0.0, -20.0], width=192, height=160, distance=distance)
    _, mask, depth, _ = rasterize_mesh(verts[None].expand(2, -1, -1), faces, cams)
    f = float(cams.K[0, 0, 0])
    disc = math.pi * (f * radius / math.sqrt(distance**2 - radius**2)) ** 2  # the silhouette cone's cross-section
    for b in range(2):
        assert abs(float(mask[b].sum()) / disc - 1) < 0.01
    assert depth[mask].min() >= distance - radius - 1e-4 and depth[mask].max() <= distance + 1e-4  # front half


def test_chunking_and_batching_do_not_change_the_result():
    verts, faces = icosphere(3, 0.1)
    verts = verts + 0.01 * torch.randn(verts.shape, generator=torch.Generator().manual_seed(1))
    cams = orbit([10.0, -35.0], [5.0, 0.0], width=96, height=80, distance=0.5)
    batch = verts[None].expand(2, -1, -1)
    a = rasterize(batch, faces, cams)
    b = rasterize(batch, faces, cams, chunk_pairs=97)
    single = rasterize(batch[1:], faces, cams.index(1))
    assert torch.equal(a.face_id, b.face_id) and torch.equal(a.depth, b.depth) and torch.equal(a.bary, b.bary)
    assert torch.equal(a.face_id[1:], single.face_id) and torch.equal(a.bary[1:], single.bary)
    bsum = a.bary.sum(-1)[a.mask]
    assert torch.allclose(bsum, torch.ones_like(bsum)) and (a.bary[a.mask] >= -1e-12).all()


def test_vertex_normals_of_a_sphere_point_outwards():
    verts, faces = icosphere(2, 0.3)
    n = vertex_normals(verts[None], faces)[0]
    assert torch.allclose(n, verts / 0.3, atol=0.03)
    assert torch.allclose(n.norm(dim=-1), torch.ones(len(n)))
