"""Fitting an adapter: the linear map from source coefficients to target coefficients (docs/method.md section 12).

Every source input i (an expression coefficient, or one axis-angle component of a source joint such as FLAME's
jaw pose) has a displacement field d_i on the source mesh: its expression basis vector, or the linearised rotation
of the joint's skinned vertices, W_v (e_a x (x_v - p_j)). Carried to the target's vertices (directly for the same
topology, else through :func:`~render_core.adapters.register.register`), the d_i are matched by the target's own
fields b_k (its expression basis and, for targets with jaw/eye joints, the same linearised rotations):

    A = argmin sum_i |B^T A[:, i] - D_i|^2 = (B B^T + lambda I)^-1 B D^T           B: [T + 3J, 3V], D: [S, 3V]

over the target vertices whose correspondence is trusted. The adapter then computes t = A s (+ b, here 0) per frame
and clamps the expression part to the target's coefficient range ([0, 1] for ARKit names, [-3, 3] otherwise).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..facemodel.model import FaceModel
from .manifest import AXES, AdapterError, AdapterManifest, convention_of, joint_component
from .register import Correspondence, register

ROTATION_JOINTS = ("jaw", "eye_l", "eye_r")
ARKIT_RANGE = (0.0, 1.0)
DEFAULT_RANGE = (-3.0, 3.0)


@dataclass
class Fit:
    """A fitted linear adapter: expression = clamp(W_e s + b_e), joints = (W_j s + b_j) reshaped [J, 3]."""

    manifest: AdapterManifest
    weights: np.ndarray  # [T + 3J, S] float64
    bias: np.ndarray  # [T + 3J]
    stats: dict[str, Any] = field(default_factory=dict)

    @property
    def expression_weights(self) -> np.ndarray:
        return self.weights[: self.manifest.num_expressions]

    def apply(self, source: np.ndarray, clamp: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Reference evaluation in numpy: source [B, S] -> (expression [B, T], joints [B, J, 3])."""
        y = np.asarray(source, np.float64) @ self.weights.T + self.bias
        t = self.manifest.num_expressions
        e = y[:, :t]
        m = self.manifest
        if clamp and m.expression_min is not None:
            e = np.maximum(e, m.expression_min)
        if clamp and m.expression_max is not None:
            e = np.minimum(e, m.expression_max)
        return e, y[:, t:].reshape(len(y), -1, 3)


def _is_arkit(model: FaceModel) -> bool:
    return convention_of(model.expression_names) == "arkit-52"


def default_source_joints(model: FaceModel) -> list[str]:
    """Joints whose rotations a stream of this model's convention carries as coefficients: FLAME-like models'
    jaw and eyes; none for ARKit (its blendshapes include jaw and eye motion)."""
    return [] if _is_arkit(model) else [j for j in ROTATION_JOINTS if j in model.joint_names]


def default_target_joints(model: FaceModel) -> list[str]:
    """Joints an adapter drives on this model: jaw and eyes where the model has them and its expression basis is
    not ARKit's (an ARKit basis opens the jaw and turns the eyes itself)."""
    return default_source_joints(model)


def coefficient_range(model: FaceModel) -> tuple[float, float]:
    return ARKIT_RANGE if _is_arkit(model) else DEFAULT_RANGE


def rotation_fields(model: FaceModel, joints: list[str]) -> np.ndarray:
    """Linearised joint rotations as displacement fields [3 J, V, 3]: rotating joint j by a small axis-angle w
    moves vertex v by W_v (w x (x_v - p_j)), W_v the skinning weight of j and its descendants."""
    x = model.template.double().numpy()
    w = model.lbs_weights.double().numpy()
    out = np.zeros((3 * len(joints), len(x), 3))
    for n, name in enumerate(joints):
        if name not in model.joint_names:
            raise AdapterError(f"{model.name} has no joint {name!r}; joints: {', '.join(model.joint_names)}",
                               field="joints")
        j = model.joint_names.index(name)
        below = {j}
        for k, p in enumerate(model.joint_parents):
            if p in below:
                below.add(k)
        weight = w[:, sorted(below)].sum(1)
        r = x - model.joint_positions[j].double().numpy()
        for a in range(3):
            e = np.eye(3)[a]
            out[3 * n + a] = weight[:, None] * np.cross(e, r)
    return out


def source_fields(model: FaceModel, names: list[str]) -> np.ndarray:
    """Displacement fields [S, V, 3] of source inputs by name: expressions, and "<joint>.x|y|z" components."""
    out = np.zeros((len(names), model.num_vertices, 3))
    basis = model.expression_basis.double().numpy()
    for i, name in enumerate(names):
        if name in model.expression_names:
            out[i] = basis[model.expression_names.index(name)]
        elif (jc := joint_component(name)) is not None and jc[0] in model.joint_names:
            out[i] = rotation_fields(model, [jc[0]])[jc[1]]
        else:
            raise AdapterError(f"{name!r} is neither an expression of {model.name} nor '<joint>.x|y|z' of one of its "
                               f"joints", field="source_names")
    return out


def same_topology(a: FaceModel, b: FaceModel) -> bool:
    return a.num_vertices == b.num_vertices and a.faces.shape == b.faces.shape and bool((a.faces == b.faces).all())


def direct(model: FaceModel) -> Correspondence:
    """The identity correspondence of a model with itself (same topology)."""
    n = model.num_vertices
    faces = model.faces.numpy()
    # each vertex is corner 0 of some triangle, or any triangle containing it: weight 1 on that corner
    tri = np.zeros(n, np.int64)
    corner = np.zeros(n, np.int64)
    for c in range(3):
        tri[faces[:, c]] = np.arange(len(faces))
        corner[faces[:, c]] = c
    weights = np.eye(3)[corner]
    return Correspondence(triangles=tri, vertices=faces[tri], weights=weights, distance=np.zeros(n),
                          valid=np.ones(n, bool), rotation=np.eye(3), scale=1.0, shift=np.zeros(3))


def fit(source: FaceModel, target: FaceModel, *, adapter_id: str = "adapter", source_names: list[str] | None = None,
        target_joints: list[str] | None = None, clamp: bool = True, ridge: float = 1e-6,
        correspondence: Correspondence | None = None) -> Fit:
    """Fit the linear adapter from ``source``'s coefficients to ``target``'s (module docstring).

    Args:
        source_names: the inputs (default: the source's expression names, then the axis-angle components of its
            jaw/eye joints for FLAME-like models).
        target_joints: target joints the adapter outputs (default :func:`default_target_joints`).
        clamp: clamp the target expression coefficients to :func:`coefficient_range`.
        ridge: Tikhonov weight, relative to the mean diagonal of B B^T (keeps collinear target fields solvable).
        correspondence: a registration to reuse; default direct for the same topology, else :func:`register`.
    """
    start = time.perf_counter()
    if source_names is None:
        source_names = list(source.expression_names) + [f"{j}.{a}" for j in default_source_joints(source)
                                                        for a in AXES]
    target_joints = default_target_joints(target) if target_joints is None else list(target_joints)
    if correspondence is None:
        correspondence = direct(target) if same_topology(source, target) else register(source, target)
    method = "direct" if same_topology(source, target) and correspondence.valid.all() else "registration"
    d = correspondence.transfer(source_fields(source, source_names))  # [S, Vt, 3]
    b = np.concatenate([target.expression_basis.double().numpy(), rotation_fields(target, target_joints)])
    valid = correspondence.valid
    if valid.sum() < 3:
        raise AdapterError("no target vertex found a trusted match on the source surface", field="target")
    bm = b[:, valid].reshape(len(b), -1)
    dm = d[:, valid].reshape(len(d), -1)
    gram = bm @ bm.T
    lam = ridge * float(np.trace(gram)) / max(len(gram), 1)
    weights = np.linalg.solve(gram + lam * np.eye(len(gram)), bm @ dm.T)  # [T + 3J, S]
    residual = np.linalg.norm(weights.T @ bm - dm, axis=1) / np.maximum(np.linalg.norm(dm, axis=1), 1e-20)
    lo, hi = coefficient_range(target)
    t = target.num_expressions
    manifest = AdapterManifest(
        id=adapter_id, source_names=list(source_names), source_convention=convention_of(list(source_names)),
        source_face_model=source.name, target_face_model=target.name,
        target_expression_names=list(target.expression_names), target_joint_names=list(target_joints),
        expression_min=[lo] * t if clamp else None, expression_max=[hi] * t if clamp else None,
        provenance={"tool": "blendsplat adapter fit", "method": f"linear least squares ({method})",
                    "source_model": source.name, "target_model": target.name,
                    "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())})
    stats = {"method": method, "valid_fraction": float(valid.mean()),
             "median_distance_m": float(np.median(correspondence.distance)),
             "relative_residual_mean": float(residual[np.linalg.norm(dm, axis=1) > 0].mean()) if (
                 np.linalg.norm(dm, axis=1) > 0).any() else 0.0,
             "ridge": lam, "seconds": round(time.perf_counter() - start, 3)}
    manifest.provenance["fit"] = stats
    return Fit(manifest=manifest, weights=weights, bias=np.zeros(len(weights)), stats=stats)
