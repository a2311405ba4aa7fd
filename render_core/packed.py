"""The packed avatar layout: what a schema-2 bundle stores and the native pipeline reads, byte for byte.

One layout serves the file, the native renderer and the cuda path, so loading a bundle is a memory map (no
repacking) and every consumer reads the same sparse blendshapes (docs/architecture.md, "Avatar bundle").

Gaussian rows (``rows [N + M, R]``, float32, face Gaussians then mouth Gaussians), ``R = 16 + ceil16(3C)``::

    0..2 position   3..6 quaternion (wxyz)   7..9 log-scale   10 opacity logit   11..15 unused (zero)
    16..16+3C SH coefficients, coefficient-major and channel-minor (c * 3 + channel)   then unused (zero)

Blendshapes, sparse (:class:`SparseDeltas`): only the (Gaussian, blendshape) pairs that change something, in two
CSR tables over the N face Gaussians (the mouth has no blendshapes), because expressions move Gaussians far more
often than they recolour them (an initialised avatar has no colour deltas at all):

- ``geometry``: rows of 11 values (position, quaternion, log-scale and opacity deltas);
- ``color``: rows of 3C values (SH deltas).

Each table is ``row_ptr [N + 1]`` int32 (the pairs of Gaussian n are ``row_ptr[n] .. row_ptr[n + 1]``), ``col
[P]`` uint16 (the blendshape of each pair, strictly increasing within a Gaussian) and ``values`` (flat: P rows of
``length`` values, fp16 or fp32, then ``ceil16(length) - length`` zeros, so the kernels' 16-value loads of the
last row stay inside the array). Values beyond a row's length are never used.

Pose correctives are stored ``[N, 3, ceil16(9 (J - 1))]`` (one zero-padded row of features per coordinate) and
eyelid offsets ``[N, 2, 3]`` float32; the avatar sees them as ``[9 (J - 1), N, 3]`` and ``[2, N, 3]`` views.

``pack_*`` functions return the stored form of an avatar's tensors, without copying when the tensors already are
views of that form (an avatar read from a schema-2 bundle); ``unpack_*`` give the avatar's views of stored tensors.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .errors import ShapeError
from .gaussians import Gaussians

GEOMETRY_LENGTH = 11  # position 3, quaternion 4, log-scale 3, opacity logit 1
SH_OFFSET = 16  # where the SH coefficients start in a Gaussian row
_CHECK_CHUNK = 1 << 16  # pairs per step of Pairs.check
_GEOMETRY_PROPS = (("means", 3), ("quats", 4), ("log_scales", 3), ("opacity_logits", 1))


def ceil16(x: int) -> int:
    return (x + 15) // 16 * 16


def row_width(c: int) -> int:
    """Floats per Gaussian row for C SH coefficients per channel."""
    return SH_OFFSET + ceil16(3 * c)


def corrective_width(j: int) -> int:
    """Stored pose-corrective features per coordinate for J joints: 9 (J - 1), padded to a multiple of 16."""
    return ceil16(9 * (j - 1))


@dataclass
class Pairs:
    """One CSR table of (Gaussian, blendshape) pairs: ``row_ptr [N + 1]`` int32, ``col [P]`` uint16, ``values``
    flat ``[P * length + ceil16(length) - length]`` (fp16 or fp32)."""

    row_ptr: Tensor
    col: Tensor
    values: Tensor
    length: int

    @property
    def count(self) -> int:
        return int(self.col.numel())

    @property
    def padding(self) -> int:
        return ceil16(self.length) - self.length

    def matrix(self) -> Tensor:
        """The values as ``[P, length]`` (a view)."""
        return self.values[: self.count * self.length].view(self.count, self.length)

    def rows(self) -> Tensor:
        """The Gaussian of every pair, ``[P]`` int64 (computed)."""
        counts = (self.row_ptr[1:] - self.row_ptr[:-1]).long()
        return torch.repeat_interleave(torch.arange(counts.numel(), device=counts.device), counts)

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Pairs:
        """Moved to ``device``, values cast to ``dtype``; pairs whose values all become zero in the cast are
        dropped (as :meth:`from_dense` would not store them)."""
        moved = Pairs(self.row_ptr.to(device), self.col.to(device), self.values.to(device=device, dtype=dtype),
                      self.length)
        if dtype is None or dtype == self.values.dtype or not self.count:
            return moved
        keep = moved.matrix().ne(0).any(1)
        if bool(keep.all()):
            return moved
        counts = torch.zeros(self.row_ptr.numel() - 1, dtype=torch.int64, device=keep.device)
        counts.index_add_(0, moved.rows()[keep], torch.ones(int(keep.sum()), dtype=torch.int64, device=keep.device))
        row_ptr = torch.zeros_like(moved.row_ptr, dtype=torch.int64)
        row_ptr[1:] = counts.cumsum(0)
        values = torch.cat([moved.matrix()[keep].reshape(-1), moved.values.new_zeros(self.padding)])
        return Pairs(row_ptr.to(torch.int32), moved.col[keep], values, self.length)

    @staticmethod
    def from_dense(x: Tensor) -> Pairs:
        """The pairs of ``x [K, N, length]`` with any non-zero value, Gaussian-major and blendshape-minor."""
        k, n, length = x.shape
        stored = x.ne(0).any(-1).transpose(0, 1)  # [N, K]
        ns, ks = stored.nonzero(as_tuple=True)  # sorted by Gaussian, then blendshape
        if ks.numel() and k > 65536:
            raise ShapeError(f"at most 65536 blendshapes are stored sparsely, got {k}", field="deltas")
        counts = stored.sum(1)
        row_ptr = torch.zeros(n + 1, dtype=torch.int64)
        row_ptr[1:] = counts.cumsum(0)
        if int(row_ptr[-1]) >= 2**31:
            raise ShapeError(f"{int(row_ptr[-1])} blendshape pairs; at most 2^31 - 1 are stored", field="deltas")
        pad = ceil16(length) - length
        values = torch.cat([x[ks, ns].reshape(-1), x.new_zeros(pad)])
        return Pairs(row_ptr.to(torch.int32), ks.to(torch.int32).to(torch.uint16), values, length)

    def check(self, field: str, n: int, k: int) -> None:
        """Raise ShapeError naming ``field.<part>`` unless this is a well-formed table over n Gaussians and k
        blendshapes (the structure the kernels rely on; values are not scanned)."""
        rp, col = self.row_ptr, self.col
        if rp.dtype != torch.int32 or tuple(rp.shape) != (n + 1,):
            raise ShapeError(f"expected int32 [{n + 1}], got {rp.dtype} {list(rp.shape)}", field=f"{field}.row_ptr")
        if col.dtype != torch.uint16 or col.dim() != 1:
            raise ShapeError(f"expected uint16 [P], got {col.dtype} {list(col.shape)}", field=f"{field}.col")
        p = col.numel()
        if int(rp[0]) != 0:
            raise ShapeError(f"must start at 0, got {int(rp[0])}", field=f"{field}.row_ptr")
        steps = rp[1:].long() - rp[:-1].long()  # int64: an int32 difference could wrap a drop into a step
        if bool((steps < 0).any()):
            at = int((steps < 0).nonzero()[0])
            raise ShapeError(f"decreases at Gaussian {at} ({int(rp[at])} -> {int(rp[at + 1])})",
                             field=f"{field}.row_ptr")
        if int(rp[-1]) != p:
            raise ShapeError(f"ends at {int(rp[-1])} pairs but col holds {p}", field=f"{field}.row_ptr")
        want = p * self.length + self.padding
        if self.values.dim() != 1 or self.values.numel() != want:
            raise ShapeError(f"expected [{want}] ({p} pairs x {self.length} values + {self.padding} padding), got "
                             f"{list(self.values.shape)}", field=f"{field}.values")
        # Column range and order in chunks of pairs: bounded temporaries, whatever the avatar's size.
        starts = rp.long()
        for a in range(0, p, _CHECK_CHUNK):
            b = min(p, a + _CHECK_CHUNK + 1)  # one pair of overlap: the order across chunk borders
            c = col[a:b].to(torch.int32)
            if int(c.max()) >= k:
                at = a + int((c >= k).nonzero()[0])
                raise ShapeError(f"pair {at} names blendshape {int(col[at])}; the avatar has {k}",
                                 field=f"{field}.col")
            ok = c[1:] > c[:-1]
            new_row = starts[(starts > a) & (starts < b)] - a  # a Gaussian's first pair may name any blendshape
            ok[new_row - 1] = True
            if not bool(ok.all()):
                at = a + int((~ok).nonzero()[0])
                raise ShapeError(f"pairs {at} and {at + 1} of one Gaussian are unsorted or duplicate (blendshapes "
                                 f"{int(col[at])}, {int(col[at + 1])})", field=f"{field}.col")


@dataclass
class SparseDeltas:
    """The K blendshapes of N face Gaussians as two :class:`Pairs` tables (module docstring): the compact form of
    :class:`Gaussians` ``[K, N, ...]`` deltas, which an avatar may hold instead (``Avatar.deltas``)."""

    geometry: Pairs
    color: Pairs
    num_expressions: int
    num_gaussians: int
    sh_coeffs: int

    @property
    def count(self) -> int:
        return self.num_gaussians

    @property
    def dtype(self) -> torch.dtype:
        return self.geometry.values.dtype

    @property
    def device(self) -> torch.device:
        return self.geometry.values.device

    def tensors(self) -> dict[str, Tensor]:
        return {f"{name}.{part}": getattr(getattr(self, name), part)
                for name in ("geometry", "color") for part in ("row_ptr", "col", "values")}

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> SparseDeltas:
        """Moved to ``device``, values cast to ``dtype`` (indices keep theirs)."""
        return SparseDeltas(self.geometry.to(device, dtype), self.color.to(device, dtype), self.num_expressions,
                            self.num_gaussians, self.sh_coeffs)

    @staticmethod
    def from_dense(deltas: Gaussians, dtype: torch.dtype | None = None) -> SparseDeltas:
        """The sparse form of dense ``deltas`` (Gaussians ``[K, N, ...]``) stored in ``dtype`` (default theirs).
        A pair is kept when one of its values is non-zero after the cast."""
        k, n = deltas.means.shape[:2]
        c = deltas.sh.shape[-2]
        dtype = dtype or deltas.means.dtype
        geometry = torch.cat([getattr(deltas, p).detach().to("cpu", dtype).reshape(k, n, w)
                              for p, w in _GEOMETRY_PROPS], -1)
        color = deltas.sh.detach().to("cpu", dtype).reshape(k, n, 3 * c)
        return SparseDeltas(Pairs.from_dense(geometry), Pairs.from_dense(color), k, n, c)

    def to_dense(self, dtype: torch.dtype | None = None) -> Gaussians:
        """Dense Gaussians ``[K, N, ...]`` deltas (zeros where no pair is stored)."""
        k, n, c = self.num_expressions, self.num_gaussians, self.sh_coeffs
        dtype = dtype or self.dtype
        parts = []
        for pairs in (self.geometry, self.color):
            dense = torch.zeros(k, n, pairs.length, dtype=dtype, device=self.device)
            dense[pairs.col.long(), pairs.rows()] = pairs.matrix().to(dtype)
            parts.append(dense)
        g = parts[0].split([w for _, w in _GEOMETRY_PROPS], -1)
        return Gaussians(means=g[0], quats=g[1], log_scales=g[2], opacity_logits=g[3][..., 0],
                         sh=parts[1].reshape(k, n, c, 3))

    def blend(self, expression: Tensor, dtype: torch.dtype = torch.float32) -> tuple[Tensor, Tensor]:
        """sum_k psi_k dB_k for B frames, multiplying only the stored pairs: geometry ``[B, N, 11]`` and SH
        ``[B, N, 3C]`` sums in ``dtype``, on the deltas' device (the cuda path's blend; any device runs it)."""
        b = expression.shape[0]
        psi = expression.to(device=self.device, dtype=dtype)
        out = []
        for pairs in (self.geometry, self.color):
            total = torch.zeros(b, self.num_gaussians, pairs.length, dtype=dtype, device=self.device)
            if pairs.count:
                w = psi[:, pairs.col.long()]  # [B, P]
                total.index_add_(1, pairs.rows(), w[..., None] * pairs.matrix().to(dtype))
            out.append(total)
        return out[0], out[1]

    def check(self, n: int, k: int, c: int) -> None:
        """Raise ShapeError unless these are well-formed deltas of n Gaussians, k blendshapes, c SH coefficients."""
        if (self.num_gaussians, self.num_expressions, self.sh_coeffs) != (n, k, c):
            raise ShapeError(f"expected deltas of N={n}, K={k}, C={c}, got N={self.num_gaussians}, "
                             f"K={self.num_expressions}, C={self.sh_coeffs}", field="deltas")
        if self.geometry.length != GEOMETRY_LENGTH or self.color.length != 3 * c:
            raise ShapeError(f"rows of {GEOMETRY_LENGTH} and {3 * c} values expected", field="deltas")
        if self.geometry.values.dtype != self.color.values.dtype:
            raise ShapeError("geometry and color values must share one dtype", field="deltas")
        self.geometry.check("deltas.geometry", n, k)
        self.color.check("deltas.color", n, k)


# ------------------------------------------------------------------------------------------------ Gaussian rows


def pack_rows(neutral: Gaussians, mouth: Gaussians) -> Tensor:
    """The ``[N + M, R]`` float32 Gaussian rows of face and mouth Gaussians (module docstring): the tensor they
    are views of when they were unpacked from one, else a new one."""
    c = neutral.sh.shape[-2]
    width = row_width(c)
    view = _rows_behind(neutral, mouth, width)
    if view is not None:
        return view
    n, m = neutral.count, mouth.count
    rows = torch.zeros(n + m, width, dtype=torch.float32)
    for i, g in enumerate((neutral, mouth)):
        block = rows[i * n : n + i * m]
        start = 0
        for prop, w in _GEOMETRY_PROPS:
            block[:, start : start + w] = getattr(g, prop).detach().to("cpu", torch.float32).reshape(-1, w)
            start += w
        block[:, SH_OFFSET : SH_OFFSET + 3 * c] = g.sh.detach().to("cpu", torch.float32).reshape(-1, 3 * c)
    return rows


def unpack_rows(rows: Tensor, n: int, c: int) -> tuple[Gaussians, Gaussians]:
    """Face and mouth Gaussians as views of ``rows [N + M, R]``."""

    def views(block: Tensor) -> Gaussians:
        return Gaussians(means=block[:, 0:3], quats=block[:, 3:7], log_scales=block[:, 7:10],
                         opacity_logits=block[:, 10], sh=block[:, SH_OFFSET : SH_OFFSET + 3 * c].unflatten(1, (c, 3)))

    return views(rows[:n]), views(rows[n:])


def _rows_behind(neutral: Gaussians, mouth: Gaussians, width: int) -> Tensor | None:
    """The rows tensor that ``neutral`` and ``mouth`` are views of (as :func:`unpack_rows` makes them), or None."""
    first = neutral.means
    if first.dtype != torch.float32 or first.device.type != "cpu" or first.dim() != 2:
        return None
    base, ptr = first.storage_offset(), first.untyped_storage().data_ptr()
    n, c = neutral.count, neutral.sh.shape[-2]
    for i, g in enumerate((neutral, mouth)):
        start = base + i * n * width
        want = {"means": (start, (width, 1)), "quats": (start + 3, (width, 1)),
                "log_scales": (start + 7, (width, 1)), "opacity_logits": (start + 10, (width,)),
                "sh": (start + SH_OFFSET, (width, 3, 1))}
        for prop, (offset, stride) in want.items():
            t = getattr(g, prop)
            if (t.dtype != torch.float32 or t.untyped_storage().data_ptr() != ptr or t.storage_offset() != offset
                    or (t.shape[0] > 1 and t.stride() != stride) or (prop == "sh" and t.shape[-2] != c)):
                return None
    total = n + mouth.count
    if (base + total * width) * 4 > first.untyped_storage().nbytes():
        return None
    return torch.as_strided(first, (total, width), (width, 1), base)


# ------------------------------------------------------------------------------------- correctives and eyelids


def pack_correctives(pc: Tensor, dtype: torch.dtype) -> Tensor:
    """``[9 (J - 1), N, 3]`` pose correctives as stored, ``[N, 3, ceil16(9 (J - 1))]`` in ``dtype``."""
    p, n, _ = pc.shape
    width = ceil16(p)
    t = pc.permute(1, 2, 0)
    if (t.dtype == dtype and t.device.type == "cpu" and (n <= 1 or t.stride()[0] == 3 * width)
            and t.stride()[1:] == (width, 1)):
        return torch.as_strided(t, (n, 3, width), (3 * width, width, 1), t.storage_offset())
    return torch.nn.functional.pad(t.detach().to("cpu", torch.float32), (0, width - p)).to(dtype).contiguous()


def unpack_correctives(stored: Tensor, j: int) -> Tensor:
    return stored[:, :, : 9 * (j - 1)].permute(2, 0, 1)


def pack_eyelids(eyelids: Tensor) -> Tensor:
    """``[2, N, 3]`` eyelid offsets as stored, ``[N, 2, 3]`` float32 (no copy when already that memory)."""
    return eyelids.detach().to("cpu", torch.float32).permute(1, 0, 2).contiguous()


def unpack_eyelids(stored: Tensor) -> Tensor:
    return stored.permute(1, 0, 2)
