"""``/v1/avatars``: list, describe, upload, delete, load and unload avatars (the engine applies who may)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Request, Response
from fastapi import Path as PathParam

from ..engine import AVATAR_ID_PATTERN
from ..intake import declared_length
from ..openapi import ErrorBody
from .dependencies import Caller, RenderEngine
from .schemas import AvatarList, AvatarOut

router = APIRouter(prefix="/v1/avatars", tags=["avatars"])
AvatarId = Annotated[str, PathParam(pattern=AVATAR_ID_PATTERN.pattern, max_length=128, examples=["demo"],
                                    description="an avatar id: letters, digits, '.', '_', '-' (at most 128, "
                                                "starting with a letter or digit)")]
BUNDLE_BODY = {"required": True, "content": {"application/octet-stream": {"schema": {"type": "string",
                                                                                     "format": "binary"}}},
               "description": "the bundle file (safetensors, schema 2)"}  # any bytes: the server validates it


@router.get("", response_model=AvatarList,
            summary="Avatars in the bundle store (and whether this replica has them loaded)")
async def list_avatars(engine: RenderEngine, principal: Caller("render")) -> AvatarList:
    return AvatarList(avatars=[AvatarOut.of(a) for a in engine.list_avatars(principal)])


@router.get("/{avatar_id}", response_model=AvatarOut,
            summary="Describe one avatar: counts, expression and joint names, precision")
async def get_avatar(avatar_id: AvatarId, engine: RenderEngine, principal: Caller("render")) -> AvatarOut:
    return AvatarOut.of(engine.avatar_info(avatar_id, principal))


@router.put("/{avatar_id}", status_code=201, response_model=AvatarOut,
            summary="Upload (create or replace) an avatar bundle",
            description="The body is the bundle file (any Content-Type). It is fully validated before it "
                        "replaces anything; an invalid, oversize or over-quota upload leaves the store unchanged.",
            responses={413: {"model": ErrorBody, "description": "larger than BLENDSPLAT_MAX_UPLOAD_BYTES"},
                       429: {"model": ErrorBody, "description": "the key's uploads per hour, or the tenant's "
                                                                "storage quota with this upload"}})
async def put_avatar(avatar_id: AvatarId, request: Request, engine: RenderEngine,
                     principal: Caller("avatars:write")) -> AvatarOut:
    declared = declared_length(request.headers)  # else (chunked) the stream's size decides
    return AvatarOut.of(await engine.replace(avatar_id, request.stream(), declared, principal))


@router.delete("/{avatar_id}", status_code=204, response_class=Response,
               summary="Delete an avatar: its bundle, the files beside it, and this replica's cached copy",
               description="Streams already open on it keep their copy until they end; new ones get NOT_FOUND.")
async def delete_avatar(avatar_id: AvatarId, engine: RenderEngine, principal: Caller("avatars:write")) -> Response:
    await engine.delete(avatar_id, principal)
    return Response(status_code=204)


@router.post("/{avatar_id}/load", response_model=AvatarOut, summary="Load an avatar into this replica's cache")
async def load_avatar(avatar_id: AvatarId, engine: RenderEngine, principal: Caller("render")) -> AvatarOut:
    return AvatarOut.of(await engine.load(avatar_id, principal))


@router.post("/{avatar_id}/unload", response_model=AvatarOut,
             summary="Drop an avatar from this replica's cache (the bundle stays)")
async def unload_avatar(avatar_id: AvatarId, engine: RenderEngine, principal: Caller("avatars:write")) -> AvatarOut:
    return AvatarOut.of(engine.unload(avatar_id, principal))
