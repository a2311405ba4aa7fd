"""Lookup grids of LBS weights and displacement magnitudes around the neutral mesh (docs/method.md section 3).

The paper precomputes, on a 256^3 grid around M0 (its bounding box plus a small margin), the LBS weights [J] and
the per-blendshape displacement magnitudes d_k [K] of the surface point closest to each node, and gives any
Gaussian (densified, split or moved during training) the trilinear interpolation of the 8 grid nodes around it,
its position clamped to the grid. A dense 256^3 x (J + K) float32 grid is about 4 GB and 16.7M closest-point
queries, so :class:`LookupGrid` builds it lazily:

- the nodes are grouped in bricks of ``brick``^3 (default 2^3); a brick's node values are computed the first time a
  lookup needs one of its nodes (all missing bricks of a lookup in one batch) and kept, up to ``max_bytes``
  (beyond that the bricks the current lookup does not need are dropped; they are rebuilt when needed again, with
  the same values);
- a node's value is exactly :func:`.geometry.values_at` of its closest surface point (the value
  :func:`.geometry.surface_values` gives at the node), found by :func:`.geometry.closest_among` among candidates
  that provably contain the node's closest triangle: for a box of nodes with centre c and half-diagonal h, every
  node's closest triangle lies within D + 2h of c, D being c's distance to the surface
  (:meth:`.geometry.Triangles.near`). The candidates are narrowed in two levels (regions of ``REGION``^3 bricks
  from all triangles, then each brick from its region's), so a node tests a handful of triangles; a 2^3 brick
  near the surface of the open head takes about 0.15 ms.

:func:`lookup_grid` keeps the grids of the two face models used last in memory (keyed by the face model's content
digest and the grid's parameters), so the training runs of one process share the bricks they build.
"""

from __future__ import annotations

import hashlib
import threading
import time
from collections import OrderedDict

import torch
from torch import Tensor

from ..facemodel import FaceModel
from .geometry import Triangles, closest_among, values_at

RESOLUTION = 256
MARGIN = 0.05  # of the bounding box's largest side, on every side
BRICK = 2
REGION = 4  # bricks per axis of the regions that narrow the candidate triangles first
MAX_BYTES = 1 << 30
TESTS_PER_BATCH = 1 << 21  # (point, candidate triangle) pairs per test batch (bounds temporary memory)


def facemodel_digest(model: FaceModel) -> str:
    """SHA-256 of what the grid's values depend on: the template, faces, expression basis and LBS weights."""
    h = hashlib.sha256(model.name.encode())
    for t in (model.template, model.faces, model.expression_basis, model.lbs_weights):
        t = t.detach().cpu().contiguous()
        h.update(str((t.dtype, tuple(t.shape))).encode())
        h.update(t.numpy().tobytes())
    return h.hexdigest()


class LookupGrid:
    """A lazily built ``resolution``^3 grid of (LBS weights [J], d [K]) around a face model's neutral mesh.

    Node (i, j, k) sits at ``origin + (i, j, k) * spacing`` (float64); nodes 0 and ``resolution - 1`` of each axis
    lie ``margin`` x (the bounding box's largest side) outside the mesh's bounding box.

    Example::

        grid = LookupGrid(face_model, resolution=256)
        lbs, d = grid.lookup(points)  # [P, J], [K, P]
    """

    def __init__(self, model: FaceModel, resolution: int = RESOLUTION, *, margin: float = MARGIN,
                 brick: int = BRICK, max_bytes: int = MAX_BYTES):
        if resolution < 2:
            raise ValueError(f"grid resolution must be at least 2, got {resolution}")
        if brick < 1:
            raise ValueError(f"brick size must be at least 1, got {brick}")
        self.model = model
        self.resolution, self.brick, self.max_bytes = int(resolution), int(brick), int(max_bytes)
        self.num_joints, self.num_expressions = model.num_joints, model.num_expressions
        self.channels = self.num_joints + self.num_expressions
        v = model.template.detach().double().cpu()
        lo, hi = v.amin(0), v.amax(0)
        pad = margin * float((hi - lo).max())
        self.origin = lo - pad  # [3] float64
        self.spacing = ((hi - lo) + 2 * pad).clamp_min(1e-12) / (self.resolution - 1)  # [3] float64
        self.per_axis = -(-self.resolution // self.brick)  # bricks along each axis
        self._slot = torch.full((self.per_axis ** 3,), -1, dtype=torch.long)  # brick id -> pool slot
        self._pool = torch.zeros(0, self.brick ** 3, self.channels)  # [slots, brick^3, J + K] float32
        self._ids = torch.zeros(0, dtype=torch.long)  # pool slot -> brick id
        self._lock = threading.Lock()
        self._mesh = Triangles(v, model.faces)  # for the brick builds
        self.built = 0  # bricks computed so far (rebuilt ones included)
        self.build_seconds = 0.0

    # ------------------------------------------------------------------------------------------ geometry
    @property
    def cell(self) -> float:
        """The smallest node spacing (metres)."""
        return float(self.spacing.min())

    def node_positions(self, nodes: Tensor) -> Tensor:
        """World positions [P, 3] float64 of integer node coordinates [P, 3]."""
        return self.origin + nodes.double() * self.spacing

    def bricks(self) -> Tensor:
        """The ids of the bricks held now (sorted)."""
        return torch.sort(self._ids).values

    def brick_of(self, nodes: Tensor) -> Tensor:
        """Brick id of integer node coordinates [..., 3]."""
        b = nodes // self.brick
        return (b[..., 0] * self.per_axis + b[..., 1]) * self.per_axis + b[..., 2]

    def _brick_nodes(self, ids: Tensor) -> Tensor:
        """Node coordinates [U, brick^3, 3] of bricks ``ids`` (clamped to the grid where a brick overhangs it)."""
        s = self.brick
        bx = ids // (self.per_axis * self.per_axis)
        by = (ids // self.per_axis) % self.per_axis
        bz = ids % self.per_axis
        r = torch.arange(s)
        local = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)  # x slowest
        nodes = torch.stack([bx, by, bz], -1)[:, None] * s + local[None]
        return nodes.clamp(max=self.resolution - 1)

    # -------------------------------------------------------------------------------------------- values
    def node_values(self, nodes: Tensor) -> Tensor:
        """The values [P, J + K] (float32) of integer node coordinates [P, 3], building missing bricks."""
        nodes = nodes.long().reshape(-1, 3)
        if nodes.numel() and (int(nodes.min()) < 0 or int(nodes.max()) >= self.resolution):
            raise ValueError(f"node coordinates must be in [0, {self.resolution})")
        ids = self.brick_of(nodes)
        with self._lock:
            self._ensure(torch.unique(ids))
            s = self.brick
            local = ((nodes[:, 0] % s) * s + nodes[:, 1] % s) * s + nodes[:, 2] % s
            return self._pool[self._slot[ids], local]

    def lookup(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Trilinear interpolation of the 8 nodes around each point [P, 3], the point clamped to the grid.

        Returns:
            (LBS weights [P, J] float32, rows summing to 1; d [K, P] float32), on ``points``' device.
        """
        p = points.detach().double().cpu().reshape(-1, 3)
        u = ((p - self.origin) / self.spacing).clamp(0, self.resolution - 1)  # node units
        near = u.round()
        u = torch.where((u - near).abs() < 1e-6, near, u)  # exactly on a node: that node's value, exactly
        i0 = u.floor().clamp(max=self.resolution - 2).long()
        f = u - i0
        corners = torch.tensor([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)])  # [8, 3]
        nodes = i0[:, None] + corners[None]  # [P, 8, 3]
        w = torch.where(corners[None].bool(), f[:, None], 1 - f[:, None]).prod(-1)  # [P, 8]
        vals = self.node_values(nodes.reshape(-1, 3)).reshape(len(p), 8, self.channels).double()
        out = (vals * w[..., None]).sum(1)
        lbs = out[:, : self.num_joints]
        lbs = lbs / lbs.sum(1, keepdim=True).clamp_min(1e-30)
        d = out[:, self.num_joints:].t()
        return lbs.float().to(points.device), d.float().contiguous().to(points.device)

    # ------------------------------------------------------------------------------------------- builds
    def _ensure(self, ids: Tensor) -> None:
        missing = ids[self._slot[ids] < 0]
        if not len(missing):
            return
        brick_bytes = self.brick ** 3 * self.channels * 4
        if (len(self._ids) + len(missing)) * brick_bytes > self.max_bytes and len(self._ids):
            # Over budget: keep only the bricks this lookup needs (the others are rebuilt when needed).
            keep = self._slot[ids] >= 0
            kept_ids = ids[keep]
            kept = self._pool[self._slot[kept_ids]]
            self._slot[self._ids] = -1
            self._pool, self._ids = kept, kept_ids
            self._slot[kept_ids] = torch.arange(len(kept_ids))
        t0 = time.perf_counter()
        values = self._compute(missing)
        self.build_seconds += time.perf_counter() - t0
        self.built += len(missing)
        self._slot[missing] = torch.arange(len(self._ids), len(self._ids) + len(missing))
        self._pool = torch.cat([self._pool, values])
        self._ids = torch.cat([self._ids, missing])

    def _compute(self, ids: Tensor) -> Tensor:
        """Node values [U, brick^3, J + K] of bricks ``ids``: the closest surface point of every node.

        Candidate triangles are narrowed in two levels: regions of ``REGION``^3 bricks (from all triangles), then
        each brick (from its region's); then every node tests its brick's few candidates."""
        nodes = self._brick_nodes(ids)  # [U, n, 3]
        pos = self.node_positions(nodes)  # [U, n, 3]
        lo, hi = pos.amin(1), pos.amax(1)
        centre, half = (lo + hi) / 2, ((hi - lo) / 2).norm(dim=1)  # [U, 3], [U]
        _, inv = torch.unique(self.brick_of(nodes[:, 0] // (REGION * self.brick) * (REGION * self.brick)),
                              return_inverse=True)
        r = int(inv.max()) + 1
        idx = inv[:, None].expand(-1, 3)
        rlo = torch.full((r, 3), torch.inf, dtype=lo.dtype).scatter_reduce(0, idx, lo, "amin")
        rhi = torch.full((r, 3), -torch.inf, dtype=hi.dtype).scatter_reduce(0, idx, hi, "amax")
        region = [self._mesh.near((rlo[sl] + rhi[sl]) / 2, ((rhi[sl] - rlo[sl]) / 2).norm(dim=1))
                  for sl in torch.arange(r).split(64)]
        width = max(c.shape[1] for c, _ in region)
        rcand = torch.cat([torch.nn.functional.pad(c, (0, width - c.shape[1])) for c, _ in region])
        rvalid = torch.cat([torch.nn.functional.pad(v, (0, width - v.shape[1])) for _, v in region])
        # Bricks: from their region's candidates, in groups of similar counts.
        parts = []
        for group, w in _groups(rvalid.sum(1)[inv], 1, TESTS_PER_BATCH):
            c, v = self._mesh.refine(centre[group], half[group], rcand[inv[group], :w], rvalid[inv[group], :w])
            parts.append((group, c, v))
        width = max(c.shape[1] for _, c, _ in parts)
        cand = torch.zeros(len(ids), width, dtype=torch.long)
        valid = torch.zeros(len(ids), width, dtype=torch.bool)
        for group, c, v in parts:
            cand[group, : c.shape[1]], valid[group, : v.shape[1]] = c, v
        # Nodes: every node of a brick against the brick's candidates.
        n = nodes.shape[1]
        out = torch.empty(len(ids), n, self.channels)
        for group, w in _groups(valid.sum(1), n, TESTS_PER_BATCH):
            tri, bary, _ = closest_among(self._mesh, pos[group].reshape(-1, 3),
                                         cand[group, :w].repeat_interleave(n, 0),
                                         valid[group, :w].repeat_interleave(n, 0))
            lbs, d = values_at(self.model, tri, bary)
            out[group] = torch.cat([lbs, d.t()], 1).reshape(len(group), n, self.channels)
        return out


def _groups(counts: Tensor, per_row: int, budget: int):
    """Rows in groups of similar ``counts`` (ascending; the largest at most 5/4 of the smallest plus 2), each group's
    rows x its largest count x ``per_row`` within ``budget`` (or one row): yields (row indices, largest count)."""
    order = torch.argsort(counts, stable=True)
    sizes = counts[order].clamp_min(1).tolist()
    i = 0
    while i < len(order):
        j = i + 1
        while j < len(order) and (j - i + 1) * per_row * sizes[j] <= budget and sizes[j] <= sizes[i] * 5 // 4 + 2:
            j += 1
        yield order[i:j], sizes[j - 1]
        i = j


_GRIDS: OrderedDict[tuple, LookupGrid] = OrderedDict()
_GRIDS_LOCK = threading.Lock()
_GRIDS_KEPT = 2


def lookup_grid(model: FaceModel, resolution: int = RESOLUTION, *, margin: float = MARGIN, brick: int = BRICK,
                max_bytes: int = MAX_BYTES) -> LookupGrid:
    """The lookup grid of ``model`` at ``resolution`` (shared with earlier calls for the same face model content
    and parameters; the grids of the last two face models are kept)."""
    key = (facemodel_digest(model), int(resolution), float(margin), int(brick))
    with _GRIDS_LOCK:
        grid = _GRIDS.get(key)
        if grid is None:
            grid = LookupGrid(model, resolution, margin=margin, brick=brick, max_bytes=max_bytes)
            _GRIDS[key] = grid
            while len(_GRIDS) > _GRIDS_KEPT:
                _GRIDS.popitem(last=False)
        _GRIDS.move_to_end(key)
        return grid
