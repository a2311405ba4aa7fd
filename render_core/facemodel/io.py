"""Face-model files: our own format, a safetensors file whose header carries a JSON manifest.

Tensors: ``template``, ``faces`` (I64), ``expression_basis``, ``joint_positions``, ``lbs_weights`` and, when the
model has them, ``shape_basis``, ``joint_regressor``, ``pose_correctives``, ``eyelid_basis`` and
``group.<name>`` (I64 vertex indices). Manifest (``__metadata__["blendsplat.facemodel"]``): format
("blendsplat-facemodel"), version, name, expression_names, joint_names, joint_parents, skull_joint, licence,
metadata. Nothing is pickled; loading validates every shape and value (FaceModelError names the field).
"""

from __future__ import annotations

import gzip
import json
import os
from pathlib import Path

import numpy as np
import safetensors
import safetensors.numpy
import torch

from ..atomic import atomic_path
from ..errors import FaceModelError
from .model import FaceModel

FORMAT = "blendsplat-facemodel"
VERSION = 1
KEY = "blendsplat.facemodel"
_OPTIONAL = ("shape_basis", "joint_regressor", "pose_correctives", "eyelid_basis")


def write_facemodel(model: FaceModel, path: str | os.PathLike) -> Path:
    """Write ``model`` to exactly ``path``, atomically, mode 0644; gzip-compressed when ``path`` ends in ``.gz``."""
    model.validate()
    path = Path(path)
    arrays = {
        "template": model.template, "faces": model.faces.to(torch.int64), "expression_basis": model.expression_basis,
        "joint_positions": model.joint_positions, "lbs_weights": model.lbs_weights,
        **{name: getattr(model, name) for name in _OPTIONAL if getattr(model, name) is not None},
        **{f"group.{name}": idx.to(torch.int64) for name, idx in model.vertex_groups.items()},
    }
    arrays = {k: np.ascontiguousarray(v.detach().cpu().numpy().astype(np.int64 if k == "faces" or k.startswith(
        "group.") else np.float32)) for k, v in arrays.items()}
    manifest = {"format": FORMAT, "version": VERSION, "name": model.name, "expression_names": model.expression_names,
                "joint_names": model.joint_names, "joint_parents": model.joint_parents,
                "skull_joint": model.skull_joint, "licence": model.licence, "metadata": model.metadata}
    data = safetensors.numpy.save(arrays, metadata={KEY: json.dumps(manifest)})
    if path.suffix == ".gz":
        data = gzip.compress(data, compresslevel=9, mtime=0)  # mtime 0: the same model gives the same bytes
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


def read_facemodel(path: str | os.PathLike) -> FaceModel:
    """Load and validate a face-model file written by :func:`write_facemodel`."""
    path = Path(path)
    if not path.is_file():
        raise FaceModelError(f"no such file: {path}", field="path")
    try:
        if path.suffix == ".gz":  # the shipped open head: gzip around the same safetensors bytes
            meta, arrays = _load_bytes(gzip.decompress(path.read_bytes()))
        else:
            with safetensors.safe_open(str(path), framework="numpy") as f:
                meta = f.metadata() or {}
                arrays = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118 - safe_open has no __iter__
    except (OSError, EOFError, ValueError, safetensors.SafetensorError) as e:  # BadGzipFile is an OSError
        raise FaceModelError(f"not a face-model file ({e})", field="path") from None
    try:
        m = json.loads(meta[KEY])
    except (KeyError, ValueError):
        raise FaceModelError("no blendsplat face-model manifest in the header", field="manifest") from None
    if not isinstance(m, dict) or m.get("format") != FORMAT:
        raise FaceModelError(f"format is not {FORMAT!r}", field="manifest.format")
    if m.get("version") != VERSION:
        raise FaceModelError(f"version {m.get('version')!r}; this build reads version {VERSION}",
                             field="manifest.version")
    for key in ("template", "faces", "expression_basis", "joint_positions", "lbs_weights"):
        if key not in arrays:
            raise FaceModelError("missing", field=key)
    t = {k: torch.from_numpy(np.array(v)) for k, v in arrays.items()}
    try:
        model = FaceModel(
            name=str(m["name"]), template=t["template"].float(), faces=t["faces"].long(),
            expression_names=list(m["expression_names"]), expression_basis=t["expression_basis"].float(),
            joint_names=list(m["joint_names"]), joint_parents=[int(p) for p in m["joint_parents"]],
            joint_positions=t["joint_positions"].float(), lbs_weights=t["lbs_weights"].float(),
            **{k: t[k].float() for k in _OPTIONAL if k in t},
            vertex_groups={k[6:]: v.long() for k, v in t.items() if k.startswith("group.")},
            skull_joint=str(m.get("skull_joint", "neck")), licence=str(m.get("licence", "")),
            metadata=dict(m.get("metadata", {})),
        )
    except (KeyError, TypeError, ValueError) as e:
        raise FaceModelError(f"malformed manifest ({e})", field="manifest") from None
    model.validate()
    return model


def _load_bytes(data: bytes) -> tuple[dict[str, str], dict[str, np.ndarray]]:
    """(header metadata, arrays) of safetensors bytes held in memory."""
    arrays = safetensors.numpy.load(data)  # validates the header and the offsets
    header = json.loads(data[8:8 + int.from_bytes(data[:8], "little")])
    return header.get("__metadata__") or {}, arrays
