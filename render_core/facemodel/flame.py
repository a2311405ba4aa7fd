"""FLAME ``generic_model.pkl`` (FLAME 2020, FLAME 2023) -> :class:`FaceModel`, safely and without chumpy or scipy.

The file is a pickle (FLAME 2020 was written by Python 2 with chumpy and scipy objects; it is read with
``encoding="latin1"``) of a dict: ``v_template`` [V, 3], ``f`` [F, 3], ``shapedirs`` [V, 3, C] (the first
``shape_components`` = 300 are identity, the rest expression), ``posedirs`` [V, 3, 36], ``J_regressor`` [5, V]
(a scipy sparse matrix), ``weights`` [V, 5] and ``kintree_table`` [2, 5]; other keys (``J``, ``bs_style``,
``bs_type``, ...) are ignored and listed in ``metadata["ignored_keys"]``.

Safety: :class:`_RestrictedUnpickler` resolves only the globals such files name, each to a stand-in of ours that
checks its arguments: numpy's array and scalar reconstruction, ``scipy.sparse`` csc/csr matrices (a stand-in that
keeps data/indices/indptr/shape and densifies with numpy), ``chumpy.ch.Ch`` (a stand-in whose value is its
pickled ``x``), and ``copyreg._reconstructor``/``object``/``set``/``_codecs.encode`` that protocol 0/1 and
Python 3 protocol 2 pickles use. Any other global raises :class:`FaceModelError` naming it, before anything is
called. Nothing from the file is executed; scipy and chumpy are never imported.

Conventions of the result (docs/method.md sections 8 and 11): joints root, neck, jaw, eye_l, eye_r with parents
-1, 0, 1, 1, 1; ``expression_basis[k] = shapedirs[:, :, S + k]``, ``shape_basis[s] = shapedirs[:, :, s]``;
``pose_correctives[p] = posedirs[:, :, p]``, where p indexes the flattened (R_j - I) of joints 1..4, joint-major
and row-major, which is :func:`render_core.deform.pose_features`' order (FLAME: v += posedirs @ features).
Tensors are float32 (faces int64). ``eyelid_basis`` is None: neither FLAME 2020 nor FLAME 2023 pickles carry
eyelid blendshapes (extra keys, eyelid ones included, are ignored and listed).
"""

from __future__ import annotations

import hashlib
import io
import os
import pickle
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..errors import FaceModelError
from .model import FaceModel

__all__ = ["FLAME_JOINT_NAMES", "FLAME_JOINT_PARENTS", "FLAME_LICENCE", "flame_model_name", "load_flame"]

FLAME_JOINT_NAMES = ["root", "neck", "jaw", "eye_l", "eye_r"]
FLAME_JOINT_PARENTS = [-1, 0, 1, 1, 1]
FLAME_SHAPE_COMPONENTS = 300  # shapedirs holds 300 identity components before the expression ones
FLAME_LICENCE = ("FLAME model supplied by the user; licence: https://flame.is.tue.mpg.de (non-commercial). "
                 "Not redistributable.")
REQUIRED_KEYS = ("v_template", "f", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table")


# ---------------------------------------------------------------------------------------------------------------
# Restricted unpickling


class _Allowed:
    """What an allowed global resolves to: a named callable of ours that checks its arguments.

    ``__setstate__`` refuses, so a BUILD opcode aimed at it cannot change it.
    """

    __slots__ = ("name", "fn")

    def __init__(self, name: str, fn):
        object.__setattr__(self, "name", name)
        object.__setattr__(self, "fn", fn)

    def __call__(self, *args):
        return self.fn(*args)

    def __setstate__(self, state):
        raise pickle.UnpicklingError(f"cannot set the state of {self.name}")

    def __repr__(self) -> str:
        return f"<allowed {self.name}>"


def _refuse(name: str):
    def fn(*args):
        raise pickle.UnpicklingError(f"{name} may not be called directly")
    return _Allowed(name, fn)


class _StandIn:
    """Base of the stand-ins for chumpy and scipy objects: they only keep their pickled state."""

    __slots__ = ("state",)

    def __setstate__(self, state):
        object.__setattr__(self, "state", state)


class _ChumpyArray(_StandIn):
    """Stand-in for ``chumpy.ch.Ch``; chumpy pickles ``__dict__`` minus its caches, whose ``x`` is the array."""

    __slots__ = ()


class _SparseMatrix(_StandIn):
    """Stand-in for a scipy compressed sparse matrix; the state is its ``__dict__`` (data, indices, indptr, shape
    as ``_shape`` or ``shape``)."""

    __slots__ = ()
    fmt = ""

    def dense(self, key: str, want: tuple[int, int]) -> np.ndarray:
        """The matrix as a dense float64 array, after checking it is a well-formed ``want``-shaped matrix."""
        s = getattr(self, "state", None)  # None when the pickle never set it
        if not isinstance(s, dict):
            raise FaceModelError(f"malformed scipy {self.fmt} matrix (state is {type(s).__name__})", field=key)
        if s.get("format", self.fmt) != self.fmt:
            raise FaceModelError(f"scipy {self.fmt}_matrix with format {s.get('format')!r}", field=key)
        shape = s.get("_shape", s.get("shape"))
        if not (isinstance(shape, tuple) and len(shape) == 2 and all(isinstance(n, int | np.integer) for n in shape)):
            raise FaceModelError(f"malformed sparse matrix shape {shape!r}", field=key)
        shape = (int(shape[0]), int(shape[1]))
        if shape != want:
            raise FaceModelError(f"expected shape {list(want)}, got {list(shape)}", field=key)
        arrays = {}
        for name in ("data", "indices", "indptr"):
            a = s.get(name)
            if not isinstance(a, np.ndarray) or a.ndim != 1 or a.dtype.hasobject:
                raise FaceModelError(f"sparse matrix {name} is not a 1-D numeric array", field=key)
            arrays[name] = a
        data, indices, indptr = arrays["data"], arrays["indices"], arrays["indptr"]
        major, minor = (shape[1], shape[0]) if self.fmt == "csc" else shape
        if indices.dtype.kind not in "iu" or indptr.dtype.kind not in "iu" or data.dtype.kind not in "biuf":
            raise FaceModelError("sparse matrix has non-integer indices or non-numeric data", field=key)
        indptr = indptr.astype(np.int64)
        if (len(indptr) != major + 1 or indptr[0] != 0 or np.any(np.diff(indptr) < 0)
                or indptr[-1] != len(indices) or len(data) != len(indices)):
            raise FaceModelError("malformed sparse matrix (indptr, indices and data disagree)", field=key)
        if len(indices) and (indices.min() < 0 or indices.max() >= minor):
            raise FaceModelError("sparse matrix index out of range", field=key)
        out = np.zeros(shape, np.float64)
        majors = np.repeat(np.arange(major), np.diff(indptr))
        rows, cols = (indices, majors) if self.fmt == "csc" else (majors, indices)
        np.add.at(out, (rows, cols), data.astype(np.float64))  # scipy sums duplicate entries too
        return out


class _CscMatrix(_SparseMatrix):
    __slots__ = ()
    fmt = "csc"


class _CsrMatrix(_SparseMatrix):
    __slots__ = ()
    fmt = "csr"


_STANDINS = (_ChumpyArray, _CscMatrix, _CsrMatrix)
_np_reconstruct = np.ndarray.__reduce__(np.zeros(1))[0]  # numpy's _reconstruct, whatever its module is called
_np_scalar = np.float64(0).__reduce__()[0]
_NDARRAY = _refuse("numpy.ndarray")
_OBJECT = _refuse("object")


def _reconstruct(subtype, shape, dtype):
    # numpy pickles arrays as _reconstruct(ndarray, (0,), b'b') followed by BUILD with the real shape and data.
    if subtype is not _NDARRAY or shape != (0,) or dtype not in ("b", b"b"):
        raise pickle.UnpicklingError("numpy _reconstruct with unexpected arguments")
    return _np_reconstruct(np.ndarray, (0,), b"b")


def _dtype(spec, align=False, copy=False):
    if not isinstance(spec, str) or not re.fullmatch(r"[<>=|]?[A-Za-z]\d{0,2}", spec):
        raise pickle.UnpicklingError(f"numpy dtype {spec!r} is not a plain dtype code")
    return np.dtype(spec, bool(align), bool(copy))


def _scalar(dtype, data=None):
    if not isinstance(dtype, np.dtype) or dtype.hasobject or not isinstance(data, bytes | str):
        raise pickle.UnpicklingError("numpy scalar with unexpected arguments")
    return _np_scalar(dtype, data.encode("latin1") if isinstance(data, str) else data)


def _frombuffer(buf, dtype, shape, order):
    # numpy's protocol-5 form (in-band buffers only: no out-of-band buffers are passed to the unpickler).
    if (not isinstance(buf, bytes | bytearray) or not isinstance(dtype, np.dtype) or dtype.hasobject
            or not isinstance(shape, tuple) or not all(isinstance(n, int) for n in shape) or order not in ("C", "F")):
        raise pickle.UnpicklingError("numpy _frombuffer with unexpected arguments")
    return np.frombuffer(buf, dtype=dtype).reshape(shape, order=order).copy()


def _encode(text, encoding="utf-8"):
    # Python 3 pickles bytes for protocol < 3 as _codecs.encode(text, 'latin1').
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1"):
        raise pickle.UnpicklingError("_codecs.encode with unexpected arguments")
    return text.encode("latin1")


def _set(items=()):
    if not isinstance(items, list | tuple) or not all(isinstance(i, str | int) for i in items):
        raise pickle.UnpicklingError("set of unexpected items")
    return set(items)


def _reconstructor(cls, base, state):
    # copyreg._reconstructor(cls, object, None): protocol 0/1 pickles of chumpy/scipy objects.
    if cls not in _STANDINS or base is not _OBJECT or state is not None:
        raise pickle.UnpicklingError("copyreg._reconstructor with unexpected arguments")
    return object.__new__(cls)


def _globals() -> dict[tuple[str, str], Any]:
    table: dict[tuple[str, str], Any] = {("numpy", "ndarray"): _NDARRAY}
    table[("numpy", "dtype")] = _Allowed("numpy.dtype", _dtype)
    for core in ("numpy.core", "numpy._core"):
        table[(f"{core}.multiarray", "_reconstruct")] = _Allowed("numpy._reconstruct", _reconstruct)
        table[(f"{core}.multiarray", "scalar")] = _Allowed("numpy.scalar", _scalar)
        table[(f"{core}.numeric", "_frombuffer")] = _Allowed("numpy._frombuffer", _frombuffer)
    for fmt, cls in (("csc", _CscMatrix), ("csr", _CsrMatrix)):
        table[(f"scipy.sparse.{fmt}", f"{fmt}_matrix")] = cls  # scipy < 1.8
        table[(f"scipy.sparse._{fmt}", f"{fmt}_matrix")] = cls
    table[("chumpy.ch", "Ch")] = _ChumpyArray
    for mod in ("copy_reg", "copyreg"):
        table[(mod, "_reconstructor")] = _Allowed("copyreg._reconstructor", _reconstructor)
    for mod in ("__builtin__", "builtins"):
        table[(mod, "object")] = _OBJECT
        table[(mod, "set")] = _Allowed("set", _set)
    table[("_codecs", "encode")] = _Allowed("_codecs.encode", _encode)
    return table


_GLOBALS = _globals()


class _RestrictedUnpickler(pickle.Unpickler):
    """An unpickler that resolves only the globals in ``_GLOBALS``; anything else is a FaceModelError."""

    def find_class(self, module: str, name: str):
        try:
            return _GLOBALS[(module, name)]
        except KeyError:
            raise FaceModelError(
                f"refusing to load global '{module}.{name}': a FLAME model file holds only numpy arrays, scipy "
                "sparse matrices and chumpy arrays, and nothing in it is executed", field="pickle") from None

    def persistent_load(self, pid):
        raise FaceModelError("refusing persistent ids", field="pickle")


def _unpickle(data: bytes) -> Any:
    try:
        return _RestrictedUnpickler(io.BytesIO(data), encoding="latin1").load()
    except FaceModelError:
        raise
    except EOFError:
        raise FaceModelError("truncated pickle (unexpected end of file)", field="pickle") from None
    except (pickle.UnpicklingError, ValueError, TypeError, AttributeError, IndexError, KeyError, MemoryError,
            OverflowError, UnicodeError, RecursionError) as e:
        raise FaceModelError(f"not a readable FLAME pickle ({type(e).__name__}: {e})", field="pickle") from None


# ---------------------------------------------------------------------------------------------------------------
# Arrays


def _array(key: str, value: Any, ndim: int) -> np.ndarray:
    """A numeric numpy array from an ndarray or a chumpy stand-in; object arrays and non-numbers are refused."""
    for _ in range(4):  # a Ch's x may itself be a Ch
        if not isinstance(value, _ChumpyArray):
            break
        state = getattr(value, "state", None)  # None when the pickle never set it
        if not isinstance(state, dict) or "x" not in state:
            raise FaceModelError("chumpy object without an 'x' array (only plain chumpy arrays are read)", field=key)
        value = state["x"]
    if isinstance(value, np.generic):
        value = np.asarray(value)
    if not isinstance(value, np.ndarray):
        raise FaceModelError(f"expected an array, got {type(value).__name__}", field=key)
    if value.dtype.hasobject:
        raise FaceModelError("object arrays are refused (an array of numbers is expected)", field=key)
    if value.dtype.kind not in "biuf":
        raise FaceModelError(f"expected numbers, got dtype {value.dtype}", field=key)
    if value.ndim != ndim:
        raise FaceModelError(f"expected {ndim} dimensions, got shape {list(value.shape)}", field=key)
    if value.dtype.kind == "f" and not np.isfinite(value).all():
        raise FaceModelError("contains non-finite values (NaN or Inf)", field=key)
    return value


def _expect(key: str, a: np.ndarray, want: tuple[int, ...]) -> np.ndarray:
    if a.shape != want:
        raise FaceModelError(f"expected shape {list(want)}, got {list(a.shape)}", field=key)
    return a


def _regressor(value: Any, want: tuple[int, int]) -> np.ndarray:
    if isinstance(value, _SparseMatrix):
        return value.dense("J_regressor", want)
    return _expect("J_regressor", _array("J_regressor", value, 2), want).astype(np.float64)


def flame_model_name(path: str | os.PathLike) -> str:
    """The release a FLAME file is taken to be, from its name (the pickles themselves carry no version).

    A "2023" or "2020" in the file name, else in its folder's name (FLAME2020.zip unpacks to ``FLAME2020/``),
    gives "flame-2023" or "flame-2020"; else ``generic_model.pkl`` (the neutral model's name in FLAME 2020; FLAME
    2023 calls it ``flame2023.pkl``) is "flame-2020"; anything else is "flame". Both releases hold 400 shapedirs
    components (300 shape + 100 expression), so the arrays cannot tell them apart.
    """
    p = Path(path)
    for part in (p.name, p.parent.name):
        for year in ("2023", "2020"):
            if year in part:
                return f"flame-{year}"
    return "flame-2020" if p.name == "generic_model.pkl" else "flame"


def load_flame(path: str | os.PathLike, n_expression: int = 50, n_shape: int = 300, *,
               shape_components: int = FLAME_SHAPE_COMPONENTS, name: str | None = None) -> FaceModel:
    """Read a user-supplied FLAME pickle (FLAME 2020 or 2023 ``generic_model.pkl``/``flame2023.pkl``).

    Args:
        path: the pickle file.
        n_expression: K, the expression components kept (the first K after the shape ones), named exp_00...
        n_shape: identity components kept (the first ``n_shape``; 0 keeps none).
        shape_components: how many of shapedirs' components are identity in the file (FLAME: 300); the
            expression components follow them.
        name: the model's name; default :func:`flame_model_name` of ``path``.

    Returns:
        A validated FaceModel (float32 tensors), metadata: source file name, sha256, counts, the keys that were
        chumpy arrays and the keys ignored.

    Raises:
        FaceModelError: unreadable, truncated or hostile files (a refused global is named), not a dict, missing
            keys, wrong shapes, object arrays, NaN/Inf, a joint tree that is not FLAME's (``field`` names the key).
    """
    path = Path(path)
    if not path.is_file():
        raise FaceModelError(f"no such file: {path}", field="path")
    raw = path.read_bytes()
    d = _unpickle(raw)
    if not isinstance(d, dict):
        raise FaceModelError(f"expected a dict of FLAME arrays, got {type(d).__name__}", field="pickle")
    for key in REQUIRED_KEYS:
        if key not in d:
            raise FaceModelError(f"missing (a FLAME file has {', '.join(REQUIRED_KEYS)})", field=key)

    v_template = _array("v_template", d["v_template"], 2)
    v = v_template.shape[0]
    _expect("v_template", v_template, (v, 3))
    if v == 0:
        raise FaceModelError("no vertices", field="v_template")
    f = _array("f", d["f"], 2)
    _expect("f", f, (f.shape[0], 3))
    if f.dtype.kind not in "iu" or (f.size and (f.min() < 0 or f.max() >= v)):
        raise FaceModelError(f"expected integer vertex indices in [0, {v})", field="f")
    shapedirs = _array("shapedirs", d["shapedirs"], 3)
    c = shapedirs.shape[2]
    _expect("shapedirs", shapedirs, (v, 3, c))
    if c <= shape_components:
        raise FaceModelError(f"{c} components, but {shape_components} shape components should precede the "
                             "expression ones", field="shapedirs")
    if not 0 <= n_shape <= shape_components:
        raise FaceModelError(f"{n_shape} requested; the file has {shape_components}", field="n_shape")
    if not 0 <= n_expression <= c - shape_components:
        raise FaceModelError(f"{n_expression} requested; the file has {c - shape_components}", field="n_expression")
    j = len(FLAME_JOINT_NAMES)
    posedirs = _expect("posedirs", _array("posedirs", d["posedirs"], 3), (v, 3, 9 * (j - 1)))
    weights = _expect("weights", _array("weights", d["weights"], 2), (v, j))
    if not np.allclose(weights.sum(1), 1.0, atol=1e-3):
        raise FaceModelError("skinning weights do not sum to 1 per vertex", field="weights")
    kintree = _expect("kintree_table", _array("kintree_table", d["kintree_table"], 2), (2, j))
    if kintree.dtype.kind not in "iu":
        raise FaceModelError("expected integers", field="kintree_table")
    ids = [int(x) for x in kintree[1]]
    # The root's parent is -1, or 2**32 - 1 where the table was stored unsigned (SMPL-family files).
    parents = [p if 0 <= p < j else -1 for p in (int(x) for x in kintree[0])]
    if ids != list(range(j)) or parents != FLAME_JOINT_PARENTS:
        raise FaceModelError(f"not FLAME's joint tree (parents {FLAME_JOINT_PARENTS} for joints "
                             f"{FLAME_JOINT_NAMES}); got ids {ids}, parents {parents}", field="kintree_table")
    regressor = _regressor(d["J_regressor"], (j, v))
    if not np.isfinite(regressor).all():
        raise FaceModelError("contains non-finite values (NaN or Inf)", field="J_regressor")

    s0, k = shape_components, n_expression

    def t(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))

    model = FaceModel(
        name=name or flame_model_name(path),
        template=t(v_template),
        faces=torch.from_numpy(f.astype(np.int64)),
        expression_names=[f"exp_{i:02d}" for i in range(k)],
        expression_basis=t(shapedirs[:, :, s0:s0 + k].transpose(2, 0, 1)),  # [K, V, 3]
        joint_names=list(FLAME_JOINT_NAMES),
        joint_parents=list(FLAME_JOINT_PARENTS),
        joint_positions=t(regressor @ v_template.astype(np.float64)),
        lbs_weights=t(weights),
        shape_basis=t(shapedirs[:, :, :n_shape].transpose(2, 0, 1)) if n_shape else None,  # [S, V, 3]
        joint_regressor=t(regressor),
        pose_correctives=t(posedirs.transpose(2, 0, 1)),  # [36, V, 3]: entry p multiplies pose feature p
        eyelid_basis=None,
        skull_joint="neck",
        licence=FLAME_LICENCE,
        metadata={
            "source": path.name, "sha256": hashlib.sha256(raw).hexdigest(), "vertices": v,
            "faces": int(f.shape[0]), "shapedirs_components": c, "shape_components_in_file": s0,
            "expression_components_in_file": c - s0, "shape_components": n_shape, "expressions": k,
            "pose_correctives": int(posedirs.shape[2]),
            "chumpy_arrays": sorted(str(key) for key in REQUIRED_KEYS if isinstance(d[key], _ChumpyArray)),
            "ignored_keys": sorted(str(key) for key in d if key not in REQUIRED_KEYS),
        },
    )
    model.validate()
    return model
