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
``length`` values, fp16, fp32 or int8, then ``ceil16(length) - length`` zeros, so the kernels' 16-value loads of
the last row stay inside the array). Values beyond a row's length are never used.

int8 tables (symmetric quantisation, :meth:`Pairs.quantize`) also hold ``scale [K, ceil16(length)]`` float32: for
blendshape k and column d, the largest ``|value[d]|`` of k's stored pairs over 127 (0 where that column is all
zero; columns past ``length`` are 0). Positions set the error (a blendshape moves its largest Gaussian centimetres,
and 1/254 of that is a tenth of a pixel at 512 px), so the geometry table also holds ``position_residual [P * 3 +
13]`` int8: a second byte of each pair's position columns 0..2, in 256ths of a step (13 zeros at the end, as the
values' spare). A stored value is, in float32 (the sum is exact, then one rounding)::

    value[d] = (q[d] + residual[j, d] / 256) * scale[k, d]   for the geometry's columns d < 3
    value[d] = q[d] * scale[k, d]                            otherwise

with ``q`` and ``residual`` in [-127, 127]: ``|x - value| <= scale / 2`` for every value and ``<= scale / 256``
for the positions. A pair whose q and residuals all round to zero is not stored.

``pack_*`` functions return the stored form of an avatar's tensors, without copying when the tensors already are
views of that form (an avatar read from a schema-2 bundle); ``unpack_*`` give the avatar's views of stored tensors.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch
from torch import Tensor

from .errors import OptionError, ShapeError
from .gaussians import Gaussians

GEOMETRY_LENGTH = 11  # position 3, quaternion 4, log-scale 3, opacity logit 1
POSITION_COLUMNS = 3  # the geometry columns that int8 tables store with a residual byte
INT8_LEVELS = 127  # int8 values (and residuals) are in [-127, 127]
RESIDUAL_STEPS = 256  # a residual counts 256ths of its value's step
RESIDUAL_PADDING = 13  # ceil16(3) - 3: the residuals' 16-byte loads of the last pair stay inside the array
SH_OFFSET = 16  # where the SH coefficients start in a Gaussian row
_CHUNK = 1 << 16  # pairs per step of Pairs.check and dequantized (bounded temporaries)
_STEP = 1 << 12  # pairs per step of Pairs.quantize (its temporaries stay in cache)
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
    flat ``[P * length + ceil16(length) - length]`` (fp16, fp32 or int8); an int8 table also holds ``scale [K,
    ceil16(length)]`` float32 and, for the geometry, ``position_residual [P * 3 + 13]`` int8 (module docstring)."""

    row_ptr: Tensor
    col: Tensor
    values: Tensor
    length: int
    scale: Tensor | None = None
    position_residual: Tensor | None = None

    @property
    def count(self) -> int:
        return int(self.col.numel())

    @property
    def padding(self) -> int:
        return ceil16(self.length) - self.length

    @property
    def quantized(self) -> bool:
        """Whether the values are int8 (times their scales)."""
        return self.values.dtype == torch.int8

    def tensors(self) -> dict[str, Tensor]:
        """The stored tensors by name: row_ptr, col, values, and an int8 table's scale (and position_residual)."""
        out = {"row_ptr": self.row_ptr, "col": self.col, "values": self.values}
        out.update({name: t for name in ("scale", "position_residual") if (t := getattr(self, name)) is not None})
        return out

    def matrix(self) -> Tensor:
        """The values as ``[P, length]`` (a view; int8 values unscaled: :meth:`dequantized` scales them)."""
        return self.values[: self.count * self.length].view(self.count, self.length)

    def residuals(self) -> Tensor:
        """An int8 geometry table's position residuals as ``[P, 3]`` (a view)."""
        return self.position_residual[: self.count * POSITION_COLUMNS].view(self.count, POSITION_COLUMNS)

    def rows(self) -> Tensor:
        """The Gaussian of every pair, ``[P]`` int64 (computed)."""
        counts = (self.row_ptr[1:] - self.row_ptr[:-1]).long()
        return torch.repeat_interleave(torch.arange(counts.numel(), device=counts.device), counts)

    def steps(self, a: int = 0, b: int | None = None) -> Tensor:
        """An int8 table's values of pairs ``a .. b`` in steps of their scales, ``[b - a, length]`` float32 (exact):
        ``q``, plus ``residual / 256`` in the position columns."""
        s = self.matrix()[a:b].float()
        if self.position_residual is not None:
            s[:, :POSITION_COLUMNS] += self.residuals()[a:b].float() / RESIDUAL_STEPS
        return s

    def dequantized(self, dtype: torch.dtype = torch.float32) -> Tensor:
        """The values as ``[P, length]`` in ``dtype``: int8 ones :meth:`steps` times ``scale[k]`` (one float32
        product, as the native kernels form it; then cast), others cast."""
        if not self.quantized:
            return self.matrix().to(dtype)
        out = torch.empty(self.count, self.length, dtype=dtype, device=self.values.device)
        for a in range(0, self.count, _CHUNK):  # bounded float32 temporaries
            out[a : a + _CHUNK] = self.steps(a, a + _CHUNK) * self.scale[self.col[a : a + _CHUNK].long(), : self.length]
        return out

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Pairs:
        """Moved to ``device``, values stored as the float ``dtype`` (int8 values dequantised: :meth:`dequantized`;
        int8 storage is :meth:`quantize`'s); pairs whose values all become zero are dropped (as :meth:`from_dense`
        would not store them)."""
        moved = Pairs(*(None if t is None else t.to(device) for t in (self.row_ptr, self.col, self.values)),
                      self.length, *(None if t is None else t.to(device) for t in (self.scale, self.position_residual)))
        if dtype is None or dtype == self.values.dtype:
            return moved
        if dtype == torch.int8:
            raise OptionError("int8 tables are made by Pairs.quantize (it needs the blendshape count)", field="dtype")
        if moved.quantized:
            pad = torch.zeros(self.padding, dtype=dtype, device=moved.values.device)
            values = torch.cat([moved.dequantized(dtype).reshape(-1), pad])
        else:
            values = moved.values.to(dtype)
        return moved._nonzero(values)

    def quantize(self, blendshapes: int, position: bool = False) -> Pairs:
        """This table in int8 (module docstring): a float32 scale per (blendshape, column) over the stored pairs
        and, with ``position`` (the geometry table), the position columns' residuals; pairs whose values all
        round to zero are dropped. ``|x - value| <= scale / 2`` for every value ``x`` (``scale / 256`` for the
        positions; scales below float32's normal range are flushed to 0)."""
        if self.quantized:
            return self
        p, length = self.count, self.length
        x, col = self.matrix(), self.col.long()
        dev = self.values.device
        amax = torch.zeros(blendshapes, length, dtype=torch.float32, device=dev)
        with warnings.catch_warnings():  # index_reduce_ is "beta"; scatter_reduce_ is 8x slower here
            warnings.simplefilter("ignore", UserWarning)
            for a in range(0, p, _STEP):
                amax.index_reduce_(0, col[a : a + _STEP], x[a : a + _STEP].float().abs(), "amax")
        scale = torch.zeros(blendshapes, ceil16(length), dtype=torch.float32, device=dev)
        scale[:, :length] = amax / INT8_LEVELS
        scale[scale < torch.finfo(torch.float32).tiny] = 0.0  # and 1 / scale is finite
        inverse = torch.where(scale > 0, 1.0 / scale, 0.0)[:, :length].contiguous()
        residual = torch.zeros(p * POSITION_COLUMNS + RESIDUAL_PADDING, dtype=torch.int8, device=dev)
        out = Pairs(self.row_ptr, self.col, torch.zeros(p * length + self.padding, dtype=torch.int8, device=dev),
                    length, scale, residual if position else None)
        q = out.matrix()
        for a in range(0, p, _STEP):
            steps = x[a : a + _STEP].float() * inverse.index_select(0, col[a : a + _STEP])  # not in place: x
            q[a : a + _STEP] = (rounded := steps.round()).clamp_(-INT8_LEVELS, INT8_LEVELS)
            if position:  # the positions' second byte: what rounding to q left, in 256ths of a step
                rest = (steps[:, :POSITION_COLUMNS] - rounded[:, :POSITION_COLUMNS]).mul_(RESIDUAL_STEPS)
                out.residuals()[a : a + _STEP] = rest.round_().clamp_(-INT8_LEVELS, INT8_LEVELS)
        return out._nonzero(out.values, scale, out.position_residual)

    def _nonzero(self, values: Tensor, scale: Tensor | None = None, residual: Tensor | None = None) -> Pairs:
        """This table's pairs holding ``values`` (flat, as stored; int8 ones with ``scale`` and ``residual``)
        without the pairs whose values (and residuals) are all zero."""
        out = Pairs(self.row_ptr, self.col, values, self.length, scale, residual)
        keep = out.matrix().ne(0).any(1)
        if residual is not None:
            keep |= out.residuals().ne(0).any(1)
        if bool(keep.all()):
            return out
        counts = torch.zeros(self.row_ptr.numel() - 1, dtype=torch.int64, device=keep.device)
        counts.index_add_(0, self.rows(), keep.long())
        row_ptr = torch.zeros_like(self.row_ptr, dtype=torch.int64)
        row_ptr[1:] = counts.cumsum(0)
        kept = torch.cat([out.matrix()[keep].reshape(-1), values.new_zeros(self.padding)])
        if residual is not None:
            residual = torch.cat([out.residuals()[keep].reshape(-1), residual.new_zeros(RESIDUAL_PADDING)])
        return Pairs(row_ptr.to(torch.int32), self.col[keep], kept, self.length, scale, residual)

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
        for a in range(0, p, _CHUNK):
            b = min(p, a + _CHUNK + 1)  # one pair of overlap: the order across chunk borders
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

    @property
    def quantized(self) -> bool:
        """Whether the values are int8 (times their scales: module docstring)."""
        return self.geometry.quantized

    def tensors(self) -> dict[str, Tensor]:
        """The stored tensors by name (``geometry.row_ptr``, ..., ``color.values``; int8: the scales too)."""
        return {f"{name}.{part}": t for name in ("geometry", "color")
                for part, t in getattr(self, name).tensors().items()}

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> SparseDeltas:
        """Moved to ``device``, values stored as ``dtype`` (indices keep theirs): float values cast or quantised
        (int8: :meth:`Pairs.quantize`), int8 values dequantised (float dtypes: :meth:`Pairs.dequantized`)."""
        if dtype == torch.int8 and not self.quantized:
            moved = self.to(device)
            return SparseDeltas(moved.geometry.quantize(self.num_expressions, position=True),
                                moved.color.quantize(self.num_expressions), self.num_expressions,
                                self.num_gaussians, self.sh_coeffs)
        return SparseDeltas(self.geometry.to(device, dtype), self.color.to(device, dtype), self.num_expressions,
                            self.num_gaussians, self.sh_coeffs)

    @staticmethod
    def from_dense(deltas: Gaussians, dtype: torch.dtype | None = None) -> SparseDeltas:
        """The sparse form of dense ``deltas`` (Gaussians ``[K, N, ...]``) stored in ``dtype`` (default theirs;
        int8: quantised from float32). A pair is kept when one of its values is non-zero after the cast."""
        k, n = deltas.means.shape[:2]
        c = deltas.sh.shape[-2]
        dtype = dtype or deltas.means.dtype
        if dtype == torch.int8:
            return SparseDeltas.from_dense(deltas, torch.float32).to(dtype=torch.int8)
        geometry = torch.cat([getattr(deltas, p).detach().to("cpu", dtype).reshape(k, n, w)
                              for p, w in _GEOMETRY_PROPS], -1)
        color = deltas.sh.detach().to("cpu", dtype).reshape(k, n, 3 * c)
        return SparseDeltas(Pairs.from_dense(geometry), Pairs.from_dense(color), k, n, c)

    def to_dense(self, dtype: torch.dtype | None = None) -> Gaussians:
        """Dense Gaussians ``[K, N, ...]`` deltas (zeros where no pair is stored), in ``dtype`` (default the
        values'; float32 for int8 values, dequantised)."""
        k, n, c = self.num_expressions, self.num_gaussians, self.sh_coeffs
        dtype = dtype or (torch.float32 if self.quantized else self.dtype)
        parts = []
        for pairs in (self.geometry, self.color):
            dense = torch.zeros(k, n, pairs.length, dtype=dtype, device=self.device)
            dense[pairs.col.long(), pairs.rows()] = pairs.dequantized(dtype)
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
                total.index_add_(1, pairs.rows(), w[..., None] * pairs.dequantized(dtype))
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
        for name in ("geometry", "color"):
            self._check_scales(name, k)

    def _check_scales(self, name: str, k: int) -> None:
        """ShapeError naming ``deltas.<name>.<tensor>`` unless an int8 table has its scale (float32 ``[K,
        ceil16(length)]``, finite and not negative) and, the geometry, its position_residual (int8 ``[P * 3 +
        13]``), and no other table has either."""
        pairs = getattr(self, name)
        residual = (pairs.count * POSITION_COLUMNS + RESIDUAL_PADDING,) if name == "geometry" else None
        want = {"scale": (torch.float32, (k, ceil16(pairs.length))), "position_residual": (torch.int8, residual)}
        for part, (dtype, shape) in want.items():
            t, field = getattr(pairs, part), f"deltas.{name}.{part}"
            if not pairs.quantized or shape is None:
                if t is not None:
                    raise ShapeError(f"not part of a {pairs.values.dtype} {name} table", field=field)
                continue
            if t is None:
                raise ShapeError(f"int8 values need it ({dtype} {list(shape)})", field=field)
            if t.dtype != dtype or tuple(t.shape) != shape:
                raise ShapeError(f"expected {dtype} {list(shape)}, got {t.dtype} {list(t.shape)}", field=field)
            bad = ~torch.isfinite(t) | (t < 0) if t.is_floating_point() else None
            if bad is not None and bool(bad.any()):
                at = tuple(int(i) for i in bad.nonzero()[0])
                raise ShapeError(f"scales must be finite and not negative; {int(bad.sum())} are not (the first, at "
                                 f"{list(at)}, is {float(t[at])})", field=field)


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
