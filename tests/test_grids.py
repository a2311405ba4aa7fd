"""Lookup grids of LBS weights and displacement magnitudes (render_core.train.grids, docs/method.md section 3)."""

from __future__ import annotations

import math

import pytest
import torch

from render_core.facemodel import FaceModel
from render_core.train.geometry import Triangles, closest_among, surface_values, values_at
from render_core.train.grids import LookupGrid, lookup_grid

CORNERS = [(a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1)]


def blob_model(seed: int = 0) -> FaceModel:
    """A jittered icosahedron with random LBS weights over 3 joints and 2 random blendshapes."""
    g = torch.Generator().manual_seed(seed)
    phi = (1 + math.sqrt(5)) / 2
    v = torch.tensor([[-1, phi, 0], [1, phi, 0], [-1, -phi, 0], [1, -phi, 0], [0, -1, phi], [0, 1, phi],
                      [0, -1, -phi], [0, 1, -phi], [phi, 0, -1], [phi, 0, 1], [-phi, 0, -1], [-phi, 0, 1]])
    v = v / v.norm(dim=1, keepdim=True) * 0.05 * (1 + 0.2 * torch.rand(12, 1, generator=g))
    f = torch.tensor([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                      [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
                      [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    w = torch.rand(12, 3, generator=g)
    return FaceModel(name="blob", template=v.float(), faces=f, expression_names=["a", "b"],
                     expression_basis=0.01 * torch.randn(2, 12, 3, generator=g), joint_names=["root", "neck", "jaw"],
                     joint_parents=[-1, 0, 1], joint_positions=torch.zeros(3, 3),
                     lbs_weights=w / w.sum(1, keepdim=True), skull_joint="neck")


@pytest.fixture(scope="module")
def blob() -> FaceModel:
    return blob_model()


def test_grid_lookup_at_grid_nodes_equals_the_direct_closest_point_values(blob):
    grid = LookupGrid(blob, resolution=9, brick=2)  # 5 bricks per axis: the last ones overhang the grid
    r = torch.arange(9)
    nodes = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    x = grid.node_positions(nodes)
    lbs, d = grid.lookup(x)
    want_lbs, want_d = surface_values(blob, x)
    torch.testing.assert_close(lbs, want_lbs, atol=1e-6, rtol=0)
    torch.testing.assert_close(d, want_d, atol=1e-7, rtol=0)
    torch.testing.assert_close(lbs.sum(1), torch.ones(len(x)))
    # The nodes hold every node's true closest point (a brute-force search over all triangles agrees).
    mesh = Triangles(blob.template, blob.faces)
    tri, bary, _ = closest_among(mesh, x, torch.arange(len(mesh)).expand(len(x), -1))
    torch.testing.assert_close(grid.node_values(nodes)[:, 3:], values_at(blob, tri, bary)[1].t(), atol=1e-7, rtol=0)


def test_grid_nodes_near_the_open_head_equal_the_direct_values(head):
    grid = LookupGrid(head, 256)
    g = torch.Generator().manual_seed(0)
    tri = torch.randint(len(head.faces), (40,), generator=g)
    x = head.template[head.faces[tri]].mean(1)
    u = ((x.double() - grid.origin) / grid.spacing).floor().long()
    nodes = (u[:, None] + torch.tensor(CORNERS)[None]).reshape(-1, 3)
    lbs, d = surface_values(head, grid.node_positions(nodes))
    got = grid.node_values(nodes)
    torch.testing.assert_close(got[:, : head.num_joints], lbs, atol=1e-6, rtol=0)
    torch.testing.assert_close(got[:, head.num_joints:], d.t(), atol=1e-7, rtol=0)
    assert grid.built <= 8 * 40


def test_lookup_between_nodes_is_trilinear(blob):
    grid = LookupGrid(blob, resolution=7)
    g = torch.Generator().manual_seed(1)
    i0 = torch.randint(0, 6, (50, 3), generator=g)
    frac = torch.rand(50, 3, generator=g, dtype=torch.float64)
    x = grid.node_positions(i0) + frac * grid.spacing
    lbs, d = grid.lookup(x)
    want = torch.zeros(50, 5, dtype=torch.float64)
    for corner in CORNERS:
        c = torch.tensor(corner)
        w = torch.where(c.bool(), frac, 1 - frac).prod(1)
        want += w[:, None] * grid.node_values(i0 + c).double()
    torch.testing.assert_close(d, want[:, 3:].t().float(), atol=1e-7, rtol=0)
    torch.testing.assert_close(lbs, (want[:, :3] / want[:, :3].sum(1, keepdim=True)).float(), atol=1e-6, rtol=0)
    # The centre of a cell: the mean of its 8 nodes.
    centre = grid.node_positions(torch.tensor([[2, 3, 4]])) + 0.5 * grid.spacing
    mean = grid.node_values(torch.tensor([[2, 3, 4]]) + torch.tensor(CORNERS)).double().mean(0)
    torch.testing.assert_close(grid.lookup(centre)[1][:, 0], mean[3:].float(), atol=1e-7, rtol=0)


def test_lookup_clamps_to_the_grid_border(blob):
    grid = LookupGrid(blob, resolution=6)
    lo, hi = grid.node_positions(torch.zeros(1, 3)), grid.node_positions(torch.full((1, 3), 5))
    inside = lo + torch.tensor([[0.3, 0.6, 0.1]]) * (hi - lo)
    outside = torch.cat([inside + torch.tensor([[1.0, 0, 0]]), inside - torch.tensor([[0, 2.0, 0]]), hi + 5, lo - 5])
    clamped = torch.maximum(torch.minimum(outside, hi), lo)
    for got, want in zip(grid.lookup(outside), grid.lookup(clamped), strict=True):
        torch.testing.assert_close(got, want, atol=0, rtol=0)
    torch.testing.assert_close(grid.lookup(hi + 5)[1], grid.node_values(torch.full((1, 3), 5))[:, 3:].t())


def test_only_the_touched_bricks_are_built(blob):
    grid = LookupGrid(blob, resolution=16, brick=4)
    assert grid.built == 0 and len(grid.bricks()) == 0
    x = grid.node_positions(torch.tensor([[3, 5, 8]])) + 0.5 * grid.spacing  # the cell (3..4, 5..6, 8..9)
    grid.lookup(x)
    want = torch.unique(grid.brick_of(torch.tensor([[3, 5, 8]]) + torch.tensor(CORNERS)))
    assert len(want) == 2 and torch.equal(grid.bricks(), want)  # x crosses one brick border (3 -> 4)
    assert grid.built == 2
    grid.lookup(x)  # no rebuild
    assert grid.built == 2
    grid.lookup(grid.node_positions(torch.tensor([[0, 0, 0]])))
    assert grid.built == 3 and len(grid.bricks()) == 3


def test_a_memory_bound_drops_bricks_without_changing_values(blob):
    x = blob.template.double() * torch.tensor([1.1, 0.9, 1.05], dtype=torch.float64)
    full = LookupGrid(blob, resolution=12, brick=2)
    small = LookupGrid(blob, resolution=12, brick=2, max_bytes=2 * 8 * 5 * 4)  # two bricks
    want = full.lookup(x)
    for p in list(range(len(x))) * 2:  # the second pass rebuilds dropped bricks
        got = small.lookup(x[p:p + 1])
        torch.testing.assert_close(got[0], want[0][p:p + 1], atol=0, rtol=0)
        torch.testing.assert_close(got[1], want[1][:, p:p + 1], atol=0, rtol=0)
        assert len(small.bricks()) <= 8  # what one lookup needs, at most
    assert small.built > len(full.bricks())


def test_grids_are_shared_per_face_model_content(blob):
    a = lookup_grid(blob, 8)
    assert lookup_grid(blob_model(), 8) is a  # same content, another object
    assert lookup_grid(blob, 9) is not a and lookup_grid(blob_model(seed=1), 8) is not a
