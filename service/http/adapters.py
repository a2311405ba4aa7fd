"""``/v1/adapters``: retargeting adapters (ONNX models mapping a tracker's coefficients to a face model's). Who may
read, replace or delete one, and the audit, are the engine's (:meth:`~service.engine.Engine.put_adapter`...)."""

from __future__ import annotations

import asyncio
from typing import Annotated

from fastapi import APIRouter, Request
from fastapi import Path as PathParam

from ..adapters import MAX_ADAPTER_BYTES, MAX_MANIFEST_BYTES
from ..engine import AVATAR_ID_PATTERN
from ..errors import InvalidArgument
from ..intake import declared_length
from .dependencies import Caller, RenderEngine
from .schemas import AdapterList, AdapterOut

router = APIRouter(prefix="/v1/adapters", tags=["adapters"])
AdapterId = Annotated[str, PathParam(pattern=AVATAR_ID_PATTERN.pattern, max_length=128,
                                     description="an adapter id (the same rule as avatar ids)")]
_ADAPTER_UPLOAD = MAX_ADAPTER_BYTES + MAX_MANIFEST_BYTES + (1 << 20)  # the two parts' limits, plus framing
ADAPTER_UPLOAD_BODY = {"required": True, "description": "the adapter: its manifest and its ONNX model", "content": {
    "multipart/form-data": {
        "schema": {"type": "object", "required": ["manifest", "model"], "properties": {
            "manifest": {"type": "string", "format": "binary",
                         "description": "the manifest, JSON (docs/method.md section 12)"},
            "model": {"type": "string", "format": "binary", "maxLength": MAX_ADAPTER_BYTES,
                      "description": "the ONNX model (opset 13-21, the allowed operators, no external data)"}}},
        "encoding": {"manifest": {"contentType": "application/json"},
                     "model": {"contentType": "application/octet-stream"}}}}}


@router.get("", response_model=AdapterList,
            summary="Retargeting adapters in the store (ONNX models mapping a tracker's coefficients to a face "
                    "model's)")
async def list_adapters(engine: RenderEngine, principal: Caller("render")) -> dict:
    return {"adapters": engine.list_adapters(principal)}


@router.get("/{adapter_id}", response_model=AdapterOut,
            summary="One adapter: its manifest (source and target names), owner, size, digest")
async def get_adapter(adapter_id: AdapterId, engine: RenderEngine, principal: Caller("render")) -> dict:
    return engine.adapter_info(adapter_id, principal)


@router.put("/{adapter_id}", status_code=201, response_model=AdapterOut,
            summary="Upload (create or replace) a retargeting adapter",
            description="multipart/form-data with two parts: `manifest` (the JSON manifest, docs/method.md "
                        "section 12; its id may be left out) and `model` (the .onnx file), e.g. curl -X PUT -F "
                        "manifest=@m.json -F model=@a.onnx. Both are validated (size, opsets, operators, no "
                        "external data, shapes against the manifest, loads in onnxruntime) before anything is "
                        "stored; a refusal is 422 naming the reason's field.")
async def put_adapter(adapter_id: AdapterId, request: Request, engine: RenderEngine,
                      principal: Caller("avatars:write")) -> dict:
    return await engine.put_adapter(adapter_id, lambda: _adapter_parts(request, engine, principal), principal)


async def _adapter_parts(request: Request, engine, principal) -> tuple[bytes, bytes]:
    """The upload's (model, manifest) parts: the body through the upload intake (bounded, spooled off the event
    loop, admitted and counted against the quota), then parsed as a form from that file."""
    declared = declared_length(request.headers)
    spooled = await engine.receive_upload(principal, request.stream(), limit=_ADAPTER_UPLOAD, field="body",
                                          declared=declared)
    try:
        with open(spooled.path, "rb") as f:  # noqa: ASYNC230 - a local file of at most _ADAPTER_UPLOAD bytes
            async def replay() -> dict:
                chunk = await asyncio.to_thread(f.read, 1 << 16)
                return {"type": "http.request", "body": chunk, "more_body": bool(chunk)}

            try:
                form = await Request(request.scope, replay).form(max_files=2, max_fields=2,
                                                                 max_part_size=_ADAPTER_UPLOAD)
            except Exception as e:  # noqa: BLE001 - python-multipart's and starlette's parse errors
                raise InvalidArgument(f"not a multipart/form-data body with manifest and model parts "
                                      f"({type(e).__name__})", field="body") from None
            parts = {}
            for name in ("manifest", "model"):
                part = form.get(name)
                if part is None:
                    raise InvalidArgument(f"the {name} part is missing", field=name)
                parts[name] = part.encode() if isinstance(part, str) else await part.read()
    finally:
        spooled.path.unlink(missing_ok=True)
    return parts["model"], parts["manifest"]


@router.delete("/{adapter_id}", response_model=AdapterOut,
               summary="Delete an adapter (sessions using it keep their loaded copy); answers what was deleted")
async def delete_adapter(adapter_id: AdapterId, engine: RenderEngine, principal: Caller("avatars:write")) -> dict:
    return engine.delete_adapter(adapter_id, principal)
