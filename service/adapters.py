"""Retargeting adapters in the service (issue 19): the adapter store, loaded runtimes, and what sessions do with
them. The engine's hooks are small: :meth:`Adapters.for_session` at ``open``, :meth:`SessionAdapter.prepare` when
a frame arrives, :func:`resolve_frames` at the start of a render call.

- Store: ``<data_dir>/adapters/<id>.onnx`` beside ``<id>.json`` (the record: the manifest, the owner ``tenant`` (None
  for now: the deployment's own; tenants' ownership checks apply to it like to avatars), the model's size and
  SHA-256), written by :mod:`render_core.adapters.files`. Uploads (``PUT /v1/adapters/{id}``) are validated like
  bundles before anything is stored: the size limit :data:`MAX_ADAPTER_BYTES`, the manifest, and the model
  (:func:`render_core.adapters.validate.validate_model`: opsets, operator domains and allow-list, no external
  data, names and shapes matching the manifest, a static cost bound by shape inference before anything runs
  (:mod:`render_core.adapters.cost`), then loads and runs in onnxruntime); a refusal is INVALID_ARGUMENT naming the
  reason's field (``model.external_data``, ``model.graph.node``, ``model`` with "cost" in the message...).
- Sessions: ``open`` names an ``adapter``, or declares ``source_names`` and the service picks a stored adapter
  whose source names include them and whose target is the avatar's face model. The session then takes source
  coefficients (by position in its source order, or by name), the adapter's source joints from ``joints``
  (axis-angle), and passes the avatar's other joints and eyelids through. Optional One Euro smoothing
  (``smoothing`` in ``open``) filters the coefficients per session, with or without an adapter.
- Running: the frames of one render call are mapped together, one onnxruntime call per adapter for all the
  sessions in the call; a frame whose adapter output is not finite gets its own error (INVALID_ARGUMENT naming
  ``adapter``) and is never rendered; the others render. A run that takes more CPU time than the adapter budget
  (the setting ``adapter_budget_ms``: :attr:`Adapters.budget_ms`) has its frames refused (RESOURCE_EXHAUSTED naming
  ``adapter``, the adapter and the budget), and the adapter is logged as over budget once.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from blendsplat.v1 import render_pb2 as pb
from render_core.adapters import files
from render_core.adapters.manifest import AdapterError, AdapterManifest, joint_component
from render_core.adapters.smoothing import OneEuroFilter
from render_core.avatar import Avatar
from render_core.deform import Frame
from render_core.rotation import axis_angle_to_matrix

from . import params
from .errors import InvalidArgument, NotFound, PermissionDenied, ResourceExhausted, some
from .settings import Settings

log = logging.getLogger(__name__)

MAX_ADAPTER_BYTES = 16 << 20  # an adapter's ONNX model
MAX_MANIFEST_BYTES = 1 << 20
ADAPTER_BUDGET_MS: float = Settings.model_fields["adapter_budget_ms"].default  # the setting's default
MayUse = Callable[[str | None], bool]  # may the caller use an adapter of this tenant (None: the deployment's)?


def _anyone(tenant: str | None) -> bool:
    return True


@dataclass
class Loaded:
    """A stored adapter, loaded: its manifest, record and onnxruntime session."""

    id: str
    manifest: AdapterManifest
    record: dict[str, Any]
    runtime: Any  # render_core.adapters.runtime.AdapterRuntime
    digest: str
    budget_ms: float = ADAPTER_BUDGET_MS  # CPU time one run may take (adapter_budget_ms)
    over_budget: bool = False  # a run has passed the budget (logged once)


class Adapters:
    """The engine's adapters: the store folder and the runtimes loaded from it (one per adapter and digest).
    ``budget_ms``: the CPU time one run of an adapter may take (the setting ``adapter_budget_ms``; its default when
    left out), given to the adapters loaded from then on."""

    def __init__(self, root: str | Path, budget_ms: float | None = None):
        self.root = Path(root)
        self.budget_ms = ADAPTER_BUDGET_MS if budget_ms is None else float(budget_ms)
        self._loaded: dict[str, Loaded] = {}
        self._lock = threading.Lock()

    # ------------------------------------------------------------------------------------------------ store
    def info(self, adapter_id: str) -> dict[str, Any]:
        """The record of one adapter as the API shows it (NotFound naming ``adapter``)."""
        record, m = self._record(adapter_id)
        return {"id": adapter_id, "tenant": record.get("tenant"), "model_bytes": record.get("model_bytes"),
                "model_sha256": record.get("model_sha256"), "manifest": m.to_dict()}

    def list(self) -> list[dict[str, Any]]:
        out = []
        for adapter_id in files.adapter_ids(self.root):
            try:
                out.append(self.info(adapter_id))
            except Exception as e:  # noqa: BLE001 - one broken record must not hide the others
                log.warning("adapter %s unreadable: %s", adapter_id, e)
        return out

    def put(self, adapter_id: str, model: bytes, manifest: Any, tenant: str | None = None) -> dict[str, Any]:
        """Validate and store an uploaded adapter (``manifest``: its JSON text or object; its ``id`` may be left out
        and must otherwise be ``adapter_id``). Nothing is stored unless every check passes (blocking: onnxruntime
        loads the model; transports call it off the event loop)."""
        files.check_adapter_id(adapter_id, field="id")
        if len(model) > MAX_ADAPTER_BYTES:
            raise InvalidArgument(f"the model is {len(model)} bytes; the limit is {MAX_ADAPTER_BYTES}",
                                  field="model.size")
        if isinstance(manifest, bytes | str):
            if len(manifest) > MAX_MANIFEST_BYTES:
                raise InvalidArgument(f"the manifest is over {MAX_MANIFEST_BYTES} bytes", field="manifest")
            try:
                manifest = json.loads(manifest)
            except (ValueError, UnicodeDecodeError) as e:
                raise InvalidArgument(f"not JSON ({str(e)[:100]})", field="manifest") from None
        if isinstance(manifest, dict):
            if manifest.get("id", adapter_id) != adapter_id:
                raise InvalidArgument(f"the manifest's id {str(manifest.get('id'))[:60]!r} is not the adapter id "
                                      f"{adapter_id!r}", field="manifest.id")
            manifest = {**manifest, "id": adapter_id}
        m = AdapterManifest.from_dict(manifest)
        from render_core.adapters.validate import validate_model

        validate_model(model, m, MAX_ADAPTER_BYTES)
        files.write_adapter(self.root, model, m, tenant=tenant)
        with self._lock:
            self._loaded.pop(adapter_id, None)
        return self.info(adapter_id)

    def delete(self, adapter_id: str) -> dict[str, Any]:
        info = self.info(adapter_id)
        files.delete_adapter(self.root, adapter_id)
        with self._lock:
            self._loaded.pop(adapter_id, None)
        return info

    def _record(self, adapter_id: str) -> tuple[dict[str, Any], AdapterManifest]:
        files.check_adapter_id(adapter_id, field="adapter")
        if not files.paths(self.root, adapter_id)[1].is_file():
            # never a listing of the store: it would show other tenants' ids (GET /v1/adapters lists the caller's)
            raise NotFound(f"no adapter {adapter_id!r} (GET /v1/adapters lists the adapters this key may use)",
                           field="adapter")
        return files.read_record(self.root, adapter_id)

    def load(self, adapter_id: str) -> Loaded:
        """The adapter's runtime, loaded once per digest (a replaced adapter is loaded again)."""
        record, manifest = self._record(adapter_id)
        digest = str(record.get("model_sha256"))
        with self._lock:
            hit = self._loaded.get(adapter_id)
            if hit is not None and hit.digest == digest:
                return hit
        from render_core.adapters.runtime import AdapterRuntime

        model, manifest, record = files.read_adapter(self.root, adapter_id)
        loaded = Loaded(adapter_id, manifest, record, AdapterRuntime(model, manifest), digest, self.budget_ms)
        with self._lock:
            self._loaded[adapter_id] = loaded
        return loaded

    # --------------------------------------------------------------------------------------------- sessions
    def pick(self, avatar: Avatar, source_names: list[str], may_use: MayUse = _anyone) -> str:
        """The stored adapter that maps ``source_names`` to ``avatar``'s face model, among those ``may_use`` allows
        (the caller's visibility rule on the adapter's owning tenant): its source names include them, its target is
        the avatar's face model with names the avatar has; an exact match of the names first, then the fewest
        extra inputs, then the id."""
        wanted = set(source_names)
        found = []
        for adapter_id in files.adapter_ids(self.root):
            try:
                record, m = files.read_record(self.root, adapter_id)
            except AdapterError:
                continue
            if not may_use(record.get("tenant")):
                continue  # another tenant's: never picked, never named
            expressions = {n for n in m.source_names if joint_component(n) is None}
            if wanted <= expressions and _fits(m, avatar) is None:
                found.append((len(expressions - wanted), adapter_id))
        if not found:
            raise InvalidArgument(f"no stored adapter maps these {len(source_names)} source names "
                                  f"({some(source_names, 5)}) to face model {avatar.face_model!r}; fit one with "
                                  "'blendsplat adapter fit' or upload one (PUT /v1/adapters/{id})",
                                  field="source_names")
        return min(found)[1]

    def for_session(self, avatar: Avatar, config: pb.SessionConfig, order: list[str],
                    may_use: MayUse = _anyone) -> SessionAdapter | None:
        """What ``open`` asked for: an adapter (named, or picked from ``source_names``), smoothing, or neither.
        ``may_use``: whether the caller may use an adapter of a tenant (None: the deployment's); a named adapter it
        may not use is PermissionDenied, and :meth:`pick` never chooses one."""
        smoothing = _smoothing(config) if config.HasField("smoothing") else None
        source_names = list(config.source_names)
        adapter_id = config.adapter
        if not adapter_id and source_names and not set(source_names) <= set(avatar.expression_names):
            adapter_id = self.pick(avatar, source_names, may_use)
        if not adapter_id:
            if not source_names and smoothing is None:
                return None
            own = source_names or order  # the avatar's own names: smoothing only (or just an order)
            return SessionAdapter(None, avatar, params.expression_order(avatar, own), smoothing)
        if config.expression_names:
            raise InvalidArgument("with an adapter the coefficients' order is source_names, not expression_names",
                                  field="expression_names")
        loaded = self.load(adapter_id)
        if not may_use(loaded.record.get("tenant")):  # checked on the record loaded, whatever checked it before
            raise PermissionDenied(f"adapter {adapter_id!r} belongs to another tenant", field="adapter")
        problem = _fits(loaded.manifest, avatar)
        if problem is not None:
            raise InvalidArgument(f"adapter {adapter_id!r} does not fit this avatar: {problem}", field="adapter")
        m = loaded.manifest
        expressions = [n for n in m.source_names if joint_component(n) is None]
        if source_names:
            params.checked_order(source_names, expressions, "source names", f"adapter {adapter_id!r} takes",
                                 "source_names")
        return SessionAdapter(loaded, avatar, source_names or expressions, smoothing)


def _fits(m: AdapterManifest, avatar: Avatar) -> str | None:
    """Why an adapter's outputs do not fit an avatar (None: they do)."""
    if m.target_face_model != avatar.face_model:
        return f"its target face model is {m.target_face_model!r}, the avatar's is {avatar.face_model!r}"
    missing = [n for n in m.target_expression_names if n not in avatar.expression_names]
    if missing:
        return f"the avatar has no expressions {some(missing)}"
    missing = [n for n in m.target_joint_names if n not in avatar.joint_names]
    if missing:
        return f"the avatar has no joints {some(missing)}"
    return None


def _smoothing(config: pb.SessionConfig) -> OneEuroFilter:
    s = config.smoothing
    try:
        return OneEuroFilter(min_cutoff=s.min_cutoff or 1.0, beta=s.beta, d_cutoff=s.d_cutoff or 1.0,
                             default_rate=config.fps_hint or 30.0)
    except AdapterError as e:
        raise InvalidArgument(e.detail, field=e.field) from None


@dataclass(eq=False)
class Drive:
    """A frame waiting for its adapter: the source vector and the avatar frame of everything else."""

    adapter: SessionAdapter
    source: np.ndarray  # [S] float32 (smoothed)
    base: Frame  # batch of 1: passed-through joints and eyelids, zero expression


class SessionAdapter:
    """One session's mapping: source coefficients (in ``order``, or by name) and source joints -> the adapter
    (or, with ``loaded`` None, the avatar's own coefficients, for smoothing) -> the avatar's frame."""

    def __init__(self, loaded: Loaded | None, avatar: Avatar, order: list[str], smoothing: OneEuroFilter | None):
        self.loaded, self.avatar, self.order, self.smoothing = loaded, avatar, list(order), smoothing
        names = loaded.manifest.source_names if loaded is not None else list(avatar.expression_names)
        self.index = {n: i for i, n in enumerate(names)}  # source name -> slot of the source vector
        self.size = len(names)
        self.source_joints: dict[str, list[int]] = {}
        for n, i in self.index.items():
            jc = joint_component(n) if loaded is not None else None
            if jc is not None:
                self.source_joints.setdefault(jc[0], [0, 0, 0])[jc[1]] = i
        if loaded is not None:
            m = loaded.manifest
            self.expression_slots = torch.tensor([avatar.expression_names.index(n) for n in m.target_expression_names])
            self.joint_slots = [avatar.joint_names.index(n) for n in m.target_joint_names]

    @property
    def adapter_id(self) -> str:
        return self.loaded.id if self.loaded is not None else ""

    @property
    def source_names(self) -> list[str]:
        return self.order if self.loaded is not None else []

    def prepare(self, msg: pb.FrameParams) -> Drive:
        """Validate one frame message and build its source vector (smoothed); typed errors name the field."""
        source = np.zeros(self.size, np.float64)
        if msg.coefficients and msg.named_coefficients:
            raise InvalidArgument("give coefficients by position or by name, not both", field="coefficients")
        if msg.coefficients:
            if len(msg.coefficients) != len(self.order):
                raise InvalidArgument(f"expected {len(self.order)} coefficients in the order {some(self.order, 10)}; "
                                      f"got {len(msg.coefficients)} (or give them by name in named_coefficients)",
                                      field="coefficients")
            for name, v in zip(self.order, msg.coefficients, strict=True):
                source[self.index[name]] = v
        for name, v in msg.named_coefficients.items():
            if name not in self.index or joint_component(name) is not None and self.loaded is not None:
                raise InvalidArgument(f"unknown source name {some([name])}; this stream's names: "
                                      f"{some(self.order, 10)}", field="named_coefficients")
            source[self.index[name]] = v
        passed: dict[str, pb.Rotation] = {}
        for name, rot in msg.joints.items():
            if name in self.source_joints:
                values = list(rot.values)
                if len(values) != 3:
                    raise InvalidArgument(f"a source joint of adapter {self.adapter_id!r} takes axis-angle (3 "
                                          f"values), got {len(values)}", field=f"joints.{name}")
                for slot, v in zip(self.source_joints[name], values, strict=True):
                    source[slot] = v
            else:
                passed[name] = rot
        if not np.isfinite(source).all():
            raise InvalidArgument("values must be finite (no NaN or Infinity)", field="coefficients")
        base = params.frame(self.avatar, pb.FrameParams(joints=passed, eyelids=msg.eyelids), self.order
                            if self.loaded is None else list(self.avatar.expression_names))
        if self.smoothing is not None:
            t = msg.client_time_us / 1e6 if msg.client_time_us > 0 else time.monotonic()
            source = self.smoothing(source, t)
        return Drive(self, source.astype(np.float32), base)


def _over_budget(loaded: Loaded, cpu_ms: float, frames: int) -> ResourceExhausted:
    """The error of the frames of a run over the adapter budget; the adapter is logged the first time."""
    if not loaded.over_budget:
        loaded.over_budget = True
        log.warning("adapter %s is over the adapter budget: a run of %d frame(s) took %.1f ms of CPU, the budget "
                    "is %g ms (adapter_budget_ms); its frames over it are refused", loaded.id, frames, cpu_ms,
                    loaded.budget_ms)
    return ResourceExhausted(f"adapter {loaded.id!r} took {cpu_ms:.1f} ms for this frame's run ({frames} frame(s)), "
                             f"over the adapter budget of {loaded.budget_ms:g} ms (adapter_budget_ms); the frame was "
                             "not rendered", field="adapter")


def resolve_frames(jobs: list) -> dict[int, BaseException]:
    """Give every job that waits for an adapter (``job.drive``, no ``job.frame``) its frame: the jobs of one
    adapter are mapped in one onnxruntime call. Returns {position in ``jobs``: error} for the frames refused (a
    non-finite adapter output, a failing run, or a run over the adapter budget): those are not rendered. Runs on
    the render thread."""
    failed: dict[int, BaseException] = {}
    groups: dict[int, list[int]] = {}
    for i, job in enumerate(jobs):
        drive = getattr(job, "drive", None)
        if job.frame is None and drive is not None:
            groups.setdefault(id(drive.adapter.loaded), []).append(i)
    for positions in groups.values():
        first = jobs[positions[0]].drive.adapter
        sources = np.stack([jobs[i].drive.source for i in positions])
        if first.loaded is None:  # smoothing only: the (smoothed) coefficients are the avatar's
            for i, row in zip(positions, sources, strict=True):
                frame = jobs[i].drive.base
                frame.expression[0] = torch.from_numpy(row).to(frame.expression.dtype)
                jobs[i].frame = frame
            continue
        try:
            cpu = time.thread_time()  # onnxruntime computes on this thread (one intra-op thread)
            expression, joints, errors = first.loaded.runtime.run(sources)
            cpu_ms = (time.thread_time() - cpu) * 1e3
        except Exception as e:  # noqa: BLE001 - the adapter failed for these frames only
            log.warning("adapter %s failed: %s", first.adapter_id, e)
            for i in positions:
                failed[i] = InvalidArgument(f"adapter {first.adapter_id!r} failed on this frame "
                                            f"({type(e).__name__})", field="adapter")
            continue
        if cpu_ms > first.loaded.budget_ms:
            for i in positions:
                failed[i] = _over_budget(first.loaded, cpu_ms, len(positions))
            continue
        for row, i in enumerate(positions):
            if errors[row] is not None:
                failed[i] = InvalidArgument(errors[row].detail, field="adapter")
                continue
            adapter = jobs[i].drive.adapter
            frame = jobs[i].drive.base
            frame.expression[0, adapter.expression_slots] = torch.from_numpy(expression[row]).to(
                frame.expression.dtype)
            if adapter.joint_slots:
                frame.joint_rotations[0, adapter.joint_slots] = axis_angle_to_matrix(
                    torch.from_numpy(joints[row]).to(frame.joint_rotations.dtype))
            jobs[i].frame = frame
    return failed

