"""Adapters on disk: ``<folder>/<id>.onnx`` (the model) and ``<folder>/<id>.json`` (its record: the manifest, the
owner ``tenant`` (None: the deployment's own), the model's size and SHA-256). The model is published first and
the record second, each atomically, so a record always names a complete model; the folder is the service's
``<data_dir>/adapters`` (what ``blendsplat adapter fit`` writes and the service lists)."""

from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path
from typing import Any

from ..atomic import atomic_path
from .manifest import AdapterError, AdapterManifest

ID_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")
MODEL_SUFFIX = ".onnx"
RECORD_SUFFIX = ".json"


def check_adapter_id(adapter_id: str, field: str = "adapter") -> str:
    if not isinstance(adapter_id, str) or not ID_PATTERN.match(adapter_id):
        raise AdapterError(f"{str(adapter_id)[:60]!r} is not an adapter id (letters, digits, '.', '_', '-'; at most "
                           "128, starting with a letter or digit)", field=field)
    return adapter_id


def paths(folder: str | os.PathLike, adapter_id: str) -> tuple[Path, Path]:
    check_adapter_id(adapter_id)
    folder = Path(folder)
    return folder / f"{adapter_id}{MODEL_SUFFIX}", folder / f"{adapter_id}{RECORD_SUFFIX}"


def write_adapter(folder: str | os.PathLike, model: bytes, manifest: AdapterManifest, tenant: str | None = None
                  ) -> dict[str, Any]:
    """Publish a (validated) model and its record as ``manifest.id``; returns the record."""
    model_path, record_path = paths(folder, manifest.id)
    model_path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(model_path) as tmp:
        tmp.write_bytes(model)
    record = {"manifest": manifest.to_dict(), "tenant": tenant, "model_bytes": len(model),
              "model_sha256": hashlib.sha256(model).hexdigest()}
    with atomic_path(record_path) as tmp:
        tmp.write_text(json.dumps(record, indent=1), encoding="utf-8")
    return record


def adapter_ids(folder: str | os.PathLike) -> list[str]:
    folder = Path(folder)
    if not folder.is_dir():
        return []
    return sorted(p.name[: -len(RECORD_SUFFIX)] for p in folder.iterdir()
                  if p.name.endswith(RECORD_SUFFIX) and ID_PATTERN.match(p.name[: -len(RECORD_SUFFIX)])
                  and (folder / (p.name[: -len(RECORD_SUFFIX)] + MODEL_SUFFIX)).is_file())


def read_record(folder: str | os.PathLike, adapter_id: str) -> tuple[dict[str, Any], AdapterManifest]:
    """(record, parsed manifest); AdapterError (field ``adapter``) when there is no such adapter."""
    model_path, record_path = paths(folder, adapter_id)
    try:
        record = json.loads(record_path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise AdapterError(f"no adapter {adapter_id!r}", field="adapter") from None
    except (OSError, ValueError) as e:
        raise AdapterError(f"adapter {adapter_id!r} has an unreadable record ({e})", field="adapter") from None
    if not isinstance(record, dict) or not model_path.is_file():
        raise AdapterError(f"adapter {adapter_id!r} is incomplete", field="adapter")
    return record, AdapterManifest.from_dict(record.get("manifest"))


def read_adapter(folder: str | os.PathLike, adapter_id: str) -> tuple[bytes, AdapterManifest, dict[str, Any]]:
    """(model bytes, manifest, record) of a stored adapter; the bytes are checked against the record's SHA-256."""
    record, manifest = read_record(folder, adapter_id)
    model = paths(folder, adapter_id)[0].read_bytes()
    if hashlib.sha256(model).hexdigest() != record.get("model_sha256"):
        raise AdapterError(f"adapter {adapter_id!r}: the model file does not match its record", field="adapter")
    return model, manifest, record


def delete_adapter(folder: str | os.PathLike, adapter_id: str) -> bool:
    """Remove an adapter (record first, so it is never listed half-deleted); whether it existed."""
    model_path, record_path = paths(folder, adapter_id)
    existed = record_path.is_file()
    record_path.unlink(missing_ok=True)
    model_path.unlink(missing_ok=True)
    return existed
