"""FLAME loader: small synthetic pickles laid out like FLAME 2020/2023 (chumpy and scipy objects, Python 2 byte
strings), FLAME's formulas written out in numpy, hostile files, and the face-model file round trip.

The fake ``chumpy.ch.Ch`` and ``scipy.sparse`` classes live in ``sys.modules`` only while pickling; loading runs
with those names blocked, so the loader must work without chumpy or scipy.
"""

from __future__ import annotations

import contextlib
import copyreg
import dataclasses
import hashlib
import io
import os
import pickle
import pickletools
import struct
import sys
import types

import numpy as np
import pytest
import torch

from render_core.errors import FaceModelError
from render_core.facemodel import read_facemodel, write_facemodel
from render_core.facemodel.flame import FLAME_LICENCE, flame_model_name, load_flame

V, F = 60, 100
PARENTS = [-1, 0, 1, 1, 1]
LIBRARIES = ("chumpy", "chumpy.ch", "scipy", "scipy.sparse", "scipy.sparse.csc", "scipy.sparse._csc",
             "scipy.sparse.csr", "scipy.sparse._csr")


# --- pickles as chumpy, scipy and Python 2 write them ----------------------------------------------------------


class Ch:
    """Pickles like ``chumpy.ch.Ch``: state = ``__dict__`` minus the weak-reference caches (chumpy's
    ``__getstate__``), restored by ``__setstate__``; the array is ``x``."""

    def __init__(self, x):
        self._dirty_vars = {"x"}
        self._itr = None
        self._parents = {}  # a WeakKeyDictionary in chumpy, dropped when pickling
        self._cache = {"r": None, "drs": {}}
        self._depends_on_deps = {}
        self._make_dense = False
        self._make_sparse = False
        self.x = np.asarray(x, np.float64)

    def __getstate__(self):
        state = dict(self.__dict__)
        del state["_parents"], state["_cache"]
        return state


Ch.__module__ = "chumpy.ch"


def sparse_class(module: str, fmt: str, old: bool) -> type:
    """A class pickling like scipy's ``{fmt}_matrix`` in ``module``: state = ``__dict__`` (data, indices, indptr,
    _shape, maxprint, and ``format`` in old scipy)."""

    def __init__(self, dense):
        a = dense if fmt == "csr" else dense.T
        major, minor = np.nonzero(a)
        self._shape = tuple(int(n) for n in dense.shape)
        self.maxprint = 50
        if old:
            self.format = fmt
        self.indices = minor.astype(np.int32)
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(major, minlength=a.shape[0]))]).astype(np.int32)
        self.data = a[major, minor]

    cls = type(f"{fmt}_matrix", (), {"__init__": __init__, "__module__": module})
    return cls


_ABSENT = object()


@contextlib.contextmanager
def fake_libraries(sparse_module: str = "scipy.sparse.csc", fmt: str = "csc", old: bool = True):
    """Fake chumpy and scipy modules in sys.modules (restored on exit); yields the sparse matrix class."""
    sparse = sparse_class(sparse_module, fmt, old)
    mods = {name: types.ModuleType(name) for name in ("chumpy", "chumpy.ch", "scipy", "scipy.sparse", sparse_module)}
    mods["chumpy.ch"].Ch = Ch
    setattr(mods[sparse_module], sparse.__name__, sparse)
    saved = {name: sys.modules.get(name, _ABSENT) for name in mods}
    sys.modules.update(mods)
    try:
        yield sparse
    finally:
        for name, mod in saved.items():
            if mod is _ABSENT:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = mod


class Py2Pickler(pickle._Pickler):
    """Writes str and bytes as Python 2 byte strings (SHORT_BINSTRING / BINSTRING), as FLAME 2020's Python 2
    pickle has them; they load as latin-1 str."""

    dispatch = pickle._Pickler.dispatch.copy()

    def save_py2_string(self, obj):
        data = obj.encode("latin1") if isinstance(obj, str) else obj
        if len(data) < 256:
            self.write(pickle.SHORT_BINSTRING + bytes([len(data)]) + data)
        else:
            self.write(pickle.BINSTRING + struct.pack("<i", len(data)) + data)
        self.memoize(obj)

    dispatch[bytes] = save_py2_string
    dispatch[str] = save_py2_string


def synthetic(n_shape: int = 8, n_exp: int = 6, seed: int = 0) -> dict:
    """FLAME-like arrays: V vertices, F faces, n_shape + n_exp shapedirs components, 5 joints."""
    rng = np.random.default_rng(seed)
    jreg = np.zeros((5, V))
    for j in range(5):
        idx = rng.choice(V, 8, replace=False)
        w = rng.random(8) + 0.1
        jreg[j, idx] = w / w.sum()
    return {
        "v_template": rng.normal(0, 0.1, (V, 3)),
        "f": rng.integers(0, V, (F, 3)).astype(np.uint32),
        "shapedirs": rng.normal(0, 0.01, (V, 3, n_shape + n_exp)),
        "posedirs": rng.normal(0, 0.01, (V, 3, 36)),
        "J_regressor": jreg,
        "weights": rng.dirichlet(np.full(5, 0.5), V),
        "kintree_table": np.array([[4294967295, 0, 1, 1, 1], [0, 1, 2, 3, 4]], np.int64),
        "bs_style": "lbs",
        "bs_type": "lrotmin",
    }


def pickle_flame(arrays: dict, variant: str = "2020", protocol: int = 2, regressor: str = "csc") -> bytes:
    """Pickle ``arrays`` as a FLAME file: shapedirs (and J, and posedirs for 2023) as chumpy arrays, J_regressor
    a scipy sparse matrix. "2020": Python 2 style (byte strings, numpy.core, scipy.sparse.csc, old scipy state);
    "2023": Python 3 pickle of ``protocol`` (numpy._core, scipy.sparse._csc, new scipy state)."""
    fmt = "csr" if regressor == "csr" else "csc"
    module = f"scipy.sparse.{fmt}" if variant == "2020" else f"scipy.sparse._{fmt}"
    with fake_libraries(module, fmt, old=variant == "2020") as sparse:
        d = dict(arrays)
        d["shapedirs"] = Ch(arrays["shapedirs"])
        d["J"] = Ch(np.zeros((5, 3)))  # ignored by the loader
        if variant == "2023":
            if "posedirs" in d:
                d["posedirs"] = Ch(arrays["posedirs"])
            d["kintree_table"] = np.array(arrays["kintree_table"])
            d["kintree_table"][0, 0] = -1  # stored signed here, 2**32 - 1 in the 2020-like file
        if "J_regressor" in d:
            d["J_regressor"] = {"csc": sparse, "csr": sparse, "dense": np.asarray, "ch": Ch}[regressor](
                arrays["J_regressor"])
        buf = io.BytesIO()
        if variant == "2020":
            Py2Pickler(buf, protocol=2).dump(d)
            return buf.getvalue().replace(b"cnumpy._core.multiarray\n", b"cnumpy.core.multiarray\n")
        pickle.dump(d, buf, protocol=protocol)
        return buf.getvalue()


@pytest.fixture
def no_libraries(monkeypatch):
    """chumpy and scipy cannot be imported (None in sys.modules makes an import fail)."""
    for name in LIBRARIES:
        monkeypatch.setitem(sys.modules, name, None)


def write(tmp_path, data: bytes, name: str = "generic_model.pkl"):
    path = tmp_path / name
    path.write_bytes(data)
    return path


# --- FLAME, written out in numpy ---------------------------------------------------------------------------------


def rodrigues(aa: np.ndarray) -> np.ndarray:
    theta = np.linalg.norm(aa)
    k = aa / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * kx + (1 - np.cos(theta)) * kx @ kx


def flame_numpy(a: dict, s0: int, beta, psi, rots):
    """One FLAME frame: v_shaped = T + S beta; J = J_reg v_shaped; v_posed = v_shaped + E psi + P feats with
    feats = (R_j - I) of joints 1..4 raveled; G_k = G_parent [R_k | J_k - J_parent]; A_k = G_k [I | -J_k];
    v = sum_k w_k A_k v_posed, with J regressed after adding E psi, as FLAME does."""
    shapedirs = a["shapedirs"]
    v_shaped = a["v_template"] + shapedirs[:, :, : len(beta)] @ beta
    exp = shapedirs[:, :, s0 : s0 + len(psi)] @ psi
    joints = a["J_regressor"] @ (v_shaped + exp)
    feats = np.concatenate([(rots[j] - np.eye(3)).ravel() for j in range(1, 5)])
    v_posed = v_shaped + exp + a["posedirs"] @ feats
    g = []
    for k, p in enumerate(PARENTS):
        local = np.eye(4)
        local[:3, :3] = rots[k]
        local[:3, 3] = joints[k] - (joints[p] if p >= 0 else 0)
        g.append(local if p < 0 else g[p] @ local)
    rest = np.tile(np.eye(4), (5, 1, 1))
    rest[:, :3, 3] = -joints
    a_k = np.stack(g) @ rest  # [5, 4, 4]
    per_vertex = np.einsum("vk,kij->vij", a["weights"], a_k)
    posed = np.einsum("vij,vj->vi", per_vertex, np.concatenate([v_posed, np.ones((V, 1))], 1))[:, :3]
    return posed, a_k[:, :3]


def random_frames(rng, batch: int, n_exp: int):
    psi = rng.normal(0, 1.0, (batch, n_exp))
    rots = np.stack([[rodrigues(rng.normal(0, 0.4, 3)) for _ in range(5)] for _ in range(batch)])
    return psi, rots


def evaluate(model, psi, rots, beta):
    posed, transforms = model.evaluate(torch.from_numpy(psi), torch.from_numpy(rots), shape=torch.from_numpy(beta))
    return posed.numpy(), transforms.numpy()


# --- loading ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("variant", ["2020", "2023"])
def test_loads_flame_layout(tmp_path, no_libraries, variant):
    arrays = synthetic(8, 6 if variant == "2020" else 10)
    name = "generic_model.pkl" if variant == "2020" else "flame2023.pkl"
    path = write(tmp_path, pickle_flame(arrays, variant), name)
    m = load_flame(path, n_expression=5, n_shape=8, shape_components=8)
    assert m.name == f"flame-{variant}"
    assert m.joint_names == ["root", "neck", "jaw", "eye_l", "eye_r"] and m.joint_parents == PARENTS
    assert m.expression_names == ["exp_00", "exp_01", "exp_02", "exp_03", "exp_04"]
    assert m.skull_joint == "neck" and m.eyelid_basis is None and m.vertex_groups == {}
    assert m.licence == FLAME_LICENCE
    sd = arrays["shapedirs"]
    np.testing.assert_allclose(m.template.numpy(), arrays["v_template"], rtol=1e-6)
    assert m.faces.dtype == torch.int64 and np.array_equal(m.faces.numpy(), arrays["f"])
    np.testing.assert_allclose(m.expression_basis.numpy(), sd[:, :, 8:13].transpose(2, 0, 1), rtol=1e-6)
    np.testing.assert_allclose(m.shape_basis.numpy(), sd[:, :, :8].transpose(2, 0, 1), rtol=1e-6)
    np.testing.assert_allclose(m.joint_regressor.numpy(), arrays["J_regressor"], rtol=1e-6)
    np.testing.assert_allclose(m.joint_positions.numpy(), arrays["J_regressor"] @ arrays["v_template"], atol=1e-7)
    np.testing.assert_allclose(m.lbs_weights.numpy(), arrays["weights"], rtol=1e-6)
    np.testing.assert_allclose(m.pose_correctives.numpy()[7], arrays["posedirs"][:, :, 7], rtol=1e-6)
    meta = m.metadata
    assert meta["source"] == name and meta["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    assert (meta["vertices"], meta["faces"], meta["expression_components_in_file"]) == (V, F, sd.shape[2] - 8)
    assert meta["chumpy_arrays"] == (["shapedirs"] if variant == "2020" else ["posedirs", "shapedirs"])
    assert meta["ignored_keys"] == ["J", "bs_style", "bs_type"]
    assert not any(sys.modules.get(name) for name in LIBRARIES)


def test_same_model_from_every_pickle_form(tmp_path, no_libraries):
    """Python 2 protocol 2, Python 3 protocols 0-5 (copyreg._reconstructor, _codecs.encode, numpy _frombuffer),
    and J_regressor as csc, csr, dense or chumpy: all give the same model."""
    arrays = synthetic()
    forms = [("2020", 2, "csc")] + [("2023", p, "csc") for p in range(6)] + [
        ("2020", 2, "csr"), ("2023", 4, "csr"), ("2023", 2, "dense"), ("2020", 2, "ch")]
    models = []
    for i, (variant, protocol, regressor) in enumerate(forms):
        data = pickle_flame(arrays, variant, protocol, regressor)
        models.append(load_flame(write(tmp_path, data, f"m{i}.pkl"), n_expression=6, n_shape=8, shape_components=8))
    for m in models[1:]:
        for field in ("template", "faces", "expression_basis", "shape_basis", "joint_regressor", "joint_positions",
                      "lbs_weights", "pose_correctives"):
            assert torch.equal(getattr(m, field), getattr(models[0], field)), field


def test_model_names():
    assert flame_model_name("/x/generic_model.pkl") == "flame-2020"
    assert flame_model_name("/x/FLAME2020/male_model.pkl") == "flame-2020"
    assert flame_model_name("/x/flame2023.pkl") == "flame-2023"
    assert flame_model_name("/x/FLAME2023/flame2023_no_jaw.pkl") == "flame-2023"
    assert flame_model_name("/x/head.pkl") == "flame"


# --- evaluation against FLAME's formulas -------------------------------------------------------------------------


@pytest.mark.parametrize("variant, n_shape, n_exp", [("2020", 8, 6), ("2023", 3, 4)])
def test_evaluate_equals_numpy_flame(tmp_path, no_libraries, variant, n_shape, n_exp):
    """FaceModel.evaluate of the loaded model = FLAME in numpy (from the file's float64 arrays), for random
    rotations of every joint, random shape and expression: this fixes the posedirs/shapedirs layouts."""
    arrays = synthetic(8, 6)
    model = load_flame(write(tmp_path, pickle_flame(arrays, variant)), n_expression=n_exp, n_shape=n_shape,
                       shape_components=8)
    rng = np.random.default_rng(1)
    beta = rng.normal(0, 1.0, n_shape)
    psi, rots = random_frames(rng, 4, n_exp)
    posed, transforms = evaluate(model, psi, rots, beta)
    for b in range(4):
        want, want_a = flame_numpy(arrays, 8, beta, psi[b], rots[b])
        assert np.abs(posed[b] - want).max() < 1e-5
        assert np.abs(transforms[b] - want_a).max() < 1e-5
    # The frames exercise the pose correctives: without them the result is far off.
    bare = dataclasses.replace(model, pose_correctives=None)
    assert np.abs(evaluate(bare, psi, rots, beta)[0] - posed).max() > 1e-3


def test_other_posedirs_layouts_are_caught(tmp_path, no_libraries):
    """The equality above would fail for a wrong posedirs reading: a raw reshape to [36, V, 3], or features of
    (R - I) transposed (column-major)."""
    arrays = synthetic()
    model = load_flame(write(tmp_path, pickle_flame(arrays)), n_expression=6, n_shape=8, shape_components=8)
    rng = np.random.default_rng(2)
    beta = rng.normal(0, 1.0, 8)
    psi, rots = random_frames(rng, 2, 6)
    want = np.stack([flame_numpy(arrays, 8, beta, psi[b], rots[b])[0] for b in range(2)])
    pc = torch.from_numpy(arrays["posedirs"]).float()
    wrong = [
        pc.reshape(36, V, 3),
        pc.permute(2, 0, 1).reshape(4, 3, 3, V, 3).transpose(1, 2).reshape(36, V, 3),
    ]
    for pose_correctives in wrong:
        got = evaluate(dataclasses.replace(model, pose_correctives=pose_correctives), psi, rots, beta)[0]
        assert np.abs(got - want).max() > 1e-3


def test_evaluate_regresses_joints_after_expression_like_flame(tmp_path, no_libraries):
    arrays = synthetic()
    model = load_flame(write(tmp_path, pickle_flame(arrays)), n_expression=6, n_shape=8, shape_components=8)
    rng = np.random.default_rng(3)
    beta = rng.normal(0, 1.0, 8)
    psi, rots = random_frames(rng, 1, 6)
    want = flame_numpy(arrays, 8, beta, psi[0], rots[0])[0]
    assert np.abs(evaluate(model, psi, rots, beta)[0][0] - want).max() < 1e-5


def test_round_trip_through_facemodel_file(tmp_path, no_libraries):
    model = load_flame(write(tmp_path, pickle_flame(synthetic())), n_expression=6, n_shape=8, shape_components=8)
    back = read_facemodel(write_facemodel(model, tmp_path / "flame.facemodel"))
    assert (back.name, back.licence, back.metadata) == (model.name, model.licence, model.metadata)
    assert back.joint_names == model.joint_names and back.joint_parents == model.joint_parents
    rng = np.random.default_rng(4)
    beta = rng.normal(0, 1.0, 8)
    psi, rots = random_frames(rng, 3, 6)
    for dtype in (torch.float32, torch.float64):
        args = (torch.from_numpy(psi).to(dtype), torch.from_numpy(rots).to(dtype))
        a = model.evaluate(*args, shape=torch.from_numpy(beta))
        b = back.evaluate(*args, shape=torch.from_numpy(beta))
        assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


def test_requested_counts_are_checked(tmp_path, no_libraries):
    path = write(tmp_path, pickle_flame(synthetic()))
    with pytest.raises(FaceModelError, match="n_expression: 7 requested; the file has 6"):
        load_flame(path, n_expression=7, n_shape=8, shape_components=8)
    with pytest.raises(FaceModelError, match="n_shape"):
        load_flame(path, n_expression=6, n_shape=9, shape_components=8)
    with pytest.raises(FaceModelError, match="shapedirs: 14 components, but 300 shape components"):
        load_flame(path)
    assert load_flame(path, n_expression=0, n_shape=0, shape_components=8).shape_basis is None


# --- hostile and broken files ------------------------------------------------------------------------------------


def global_opcode(module: str, name: str) -> bytes:
    return b"c" + module.encode() + b"\n" + name.encode() + b"\n"


def test_refuses_os_system_and_does_not_run_it(tmp_path):
    marker = tmp_path / "pwned"
    payload = global_opcode("os", "system") + f"(S'touch {marker}'\ntR.".encode()
    assert [op.name for op, _, _ in pickletools.genops(payload)] == ["GLOBAL", "MARK", "STRING", "TUPLE", "REDUCE",
                                                                      "STOP"]
    with pytest.raises(FaceModelError, match=r"refusing to load global 'os\.system'") as e:
        load_flame(write(tmp_path, payload))
    assert e.value.field == "pickle"
    assert not marker.exists()


def test_refuses_reduce_payload_among_flame_arrays(tmp_path):
    marker = tmp_path / "pwned"

    class Payload:
        def __reduce__(self):
            return os.system, (f"touch {marker}",)

    live = tmp_path / "live"

    class Live:
        def __reduce__(self):
            return os.system, (f"touch {live}",)

    pickle.loads(pickle.dumps(Live(), protocol=2))  # the payload form is live under a plain unpickler
    assert live.exists()
    arrays = synthetic()
    arrays["weights"] = Payload()
    with pytest.raises(FaceModelError, match=rf"refusing to load global '{os.system.__module__}\.system'"):
        load_flame(write(tmp_path, pickle.dumps(arrays, protocol=2)))
    assert not marker.exists()


def test_refuses_eval(tmp_path):
    marker = tmp_path / "pwned"
    code = f"__import__('pathlib').Path({str(marker)!r}).touch()"
    py2 = global_opcode("__builtin__", "eval") + f"(S{code!r}\ntR.".encode()
    with pytest.raises(FaceModelError, match=r"refusing to load global '__builtin__\.eval'"):
        load_flame(write(tmp_path, py2))

    class Payload:
        def __reduce__(self):
            return eval, (code,)

    with pytest.raises(FaceModelError, match=r"refusing to load global 'builtins\.eval'"):
        load_flame(write(tmp_path, pickle.dumps({"v_template": Payload()}, protocol=4)))
    assert not marker.exists()


@pytest.mark.parametrize("module, name", [
    ("builtins", "exec"), ("builtins", "getattr"), ("builtins", "__import__"), ("subprocess", "Popen"),
    ("posix", "system"), ("torch", "load"), ("torch._utils", "_rebuild_tensor_v2"), ("numpy", "load"),
    ("numpy.lib.npyio", "load"), ("chumpy.ch_ops", "add"), ("chumpy.reordering", "Select"),
    ("scipy.sparse._coo", "coo_matrix"), ("copyreg", "__newobj__"), ("pickle", "loads"), ("io", "open"),
])
def test_refuses_every_other_global(tmp_path, module, name):
    with pytest.raises(FaceModelError, match=rf"refusing to load global '{module}\.{name}'"):
        load_flame(write(tmp_path, b"\x80\x02" + global_opcode(module, name) + b"."))


@pytest.mark.parametrize("payload", [
    global_opcode("numpy", "ndarray") + b"((I3\ntp0\ntR.",  # ndarray called directly
    global_opcode("_codecs", "encode") + b"(Vabc\nVzlib_codec\ntR.",
    global_opcode("copy_reg", "_reconstructor") + b"(" + global_opcode("__builtin__", "set") + global_opcode(
        "__builtin__", "object") + b"NtR.",  # only chumpy/scipy stand-ins may be reconstructed
    global_opcode("numpy", "dtype") + b"(Vf8,i4\nI0\nI1\ntR.",  # not a plain dtype code
    global_opcode("__builtin__", "set") + b"((lp0\n" + global_opcode("__builtin__", "object") + b"atR.",
    global_opcode("numpy.core.multiarray", "_reconstruct") + b"(" + global_opcode("chumpy.ch", "Ch")
    + b"(I0\ntVb\ntR.",
    global_opcode("numpy", "dtype") + b"(S'fn'\np0\nI1\ndb.",  # BUILD cannot alter what a global resolves to
    global_opcode("chumpy.ch", "Ch") + b"(S'x'\np0\nI1\ndb.",
])
def test_allowed_globals_check_their_arguments(tmp_path, payload):
    with pytest.raises(FaceModelError) as e:
        load_flame(write(tmp_path, payload))
    assert e.value.field == "pickle"


def test_refuses_object_arrays(tmp_path, no_libraries):
    arrays = synthetic()
    arrays["v_template"] = np.array([[0.1, "a", None]] * V, dtype=object)
    data = pickle_flame(arrays, "2023")
    with pytest.raises(FaceModelError, match="v_template: object arrays are refused"):
        load_flame(write(tmp_path, data))
    arrays = synthetic()
    with fake_libraries("scipy.sparse._csc", "csc", False) as sparse:
        d = dict(arrays, J_regressor=sparse(arrays["J_regressor"]))
        bad = Ch(arrays["shapedirs"])
        bad.x = arrays["shapedirs"].astype(object)
        d["shapedirs"] = bad
        data = pickle.dumps(d, protocol=2)
    with pytest.raises(FaceModelError, match="shapedirs: object arrays are refused"):
        load_flame(write(tmp_path, data))


def broken(arrays: dict, key: str, value) -> dict:
    arrays = dict(arrays)
    if value is None:
        del arrays[key]
    else:
        arrays[key] = value
    return arrays


@pytest.mark.parametrize("key, value, message", [
    ("posedirs", None, "posedirs: missing"),
    ("J_regressor", None, "J_regressor: missing"),
    ("weights", np.full((V, 4), 0.25), r"weights: expected shape \[60, 5\], got \[60, 4\]"),
    ("posedirs", np.zeros((V, 3, 35)), r"posedirs: expected shape \[60, 3, 36\]"),
    ("shapedirs", np.zeros((V, 2, 14)), r"shapedirs: expected shape \[60, 3, 14\]"),
    ("f", np.zeros((F, 4), np.int64), r"f: expected shape \[100, 3\]"),
    ("f", np.full((F, 3), V, np.int64), r"f: expected integer vertex indices in \[0, 60\)"),
    ("v_template", np.full((V, 3), np.nan), "v_template: contains non-finite values"),
    ("shapedirs", np.full((V, 3, 14), np.inf), "shapedirs: contains non-finite values"),
    ("J_regressor", np.full((5, V), np.nan), "J_regressor: contains non-finite values"),
    ("J_regressor", np.zeros((5, V - 1)), r"J_regressor: expected shape \[5, 60\], got \[5, 59\]"),
    ("weights", np.full((V, 5), 0.5), "weights: skinning weights do not sum to 1"),
    ("kintree_table", np.array([[-1, 0, 1, 2, 1], [0, 1, 2, 3, 4]]), "kintree_table: not FLAME's joint tree"),
    ("kintree_table", np.zeros((2, 6), np.int64), r"kintree_table: expected shape \[2, 5\]"),
    ("v_template", np.array(["a"] * V), "v_template: expected numbers"),
    ("v_template", [[0.0, 0.0, 0.0]] * V, "v_template: expected an array, got list"),
])
def test_rejects_malformed_flame_dicts(tmp_path, no_libraries, key, value, message):
    arrays = synthetic()
    data = pickle_flame(broken(arrays, key, value), "2023", regressor="dense")
    with pytest.raises(FaceModelError, match=message):
        load_flame(write(tmp_path, data), n_expression=6, n_shape=8, shape_components=8)


def test_rejects_malformed_sparse_regressor(tmp_path, no_libraries):
    arrays = synthetic()
    with fake_libraries("scipy.sparse.csc") as sparse:
        m = sparse(arrays["J_regressor"])
        m.indices = m.indices + V  # out of range
        data = Py2Pickler_dumps(dict(arrays, J_regressor=m))
    with pytest.raises(FaceModelError, match="J_regressor: sparse matrix index out of range"):
        load_flame(write(tmp_path, data), n_expression=6, n_shape=8, shape_components=8)


def test_rejects_chumpy_object_without_state(tmp_path, no_libraries):
    arrays = synthetic()
    bare = Ch(arrays["posedirs"])

    class Pickler(Py2Pickler):
        def reducer_override(self, obj):  # the Ch is created by NEWOBJ but never given its state (no BUILD)
            return (copyreg.__newobj__, (Ch,)) if obj is bare else NotImplemented

    with fake_libraries() as sparse:
        buf = io.BytesIO()
        Pickler(buf, protocol=2).dump(dict(arrays, J_regressor=sparse(arrays["J_regressor"]), posedirs=bare))
        data = buf.getvalue()
    with pytest.raises(FaceModelError, match="posedirs: chumpy object without an 'x' array"):
        load_flame(write(tmp_path, data), n_expression=6, n_shape=8, shape_components=8)


def Py2Pickler_dumps(obj) -> bytes:  # noqa: N802 - named after the class
    buf = io.BytesIO()
    Py2Pickler(buf, protocol=2).dump(obj)
    return buf.getvalue()


def test_rejects_truncated_and_non_pickle_files(tmp_path, no_libraries):
    data = pickle_flame(synthetic())
    for cut in (0, 1, 50, len(data) // 3, len(data) // 2, len(data) - 1):
        with pytest.raises(FaceModelError) as e:
            load_flame(write(tmp_path, data[:cut]))
        assert e.value.field == "pickle" and ("truncated" in str(e.value) or "not a readable" in str(e.value))
    for junk in (b"hello, world\n", b"PK\x03\x04" + bytes(100), b"\x89PNG\r\n\x1a\n" + bytes(64),
                 np.random.default_rng(0).bytes(4096)):
        with pytest.raises(FaceModelError) as e:
            load_flame(write(tmp_path, junk))
        assert e.value.field == "pickle"
    with pytest.raises(FaceModelError, match="pickle: expected a dict of FLAME arrays, got list"):
        load_flame(write(tmp_path, pickle.dumps([1, 2, 3])))
    with pytest.raises(FaceModelError, match="path: no such file"):
        load_flame(tmp_path / "absent.pkl")
