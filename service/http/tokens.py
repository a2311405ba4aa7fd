"""``POST /v1/tokens``: a backend mints a short-lived, render-only session token with its key for a browser (a secret
key never belongs in a page). The format and the checks are :mod:`service.access.tokens`'s."""

from __future__ import annotations

from fastapi import APIRouter

from ..errors import InvalidArgument, PermissionDenied
from ..openapi import ErrorBody
from .dependencies import Caller, RenderEngine
from .schemas import TokenOut, TokenRequest

router = APIRouter(tags=["tokens"])


@router.post("/v1/tokens", status_code=201, response_model=TokenOut,
             summary="Mint a short-lived, render-only session token for a browser",
             description="Needs a key with the render scope (or admin). The token reads and streams the tenant's "
                         "avatars (only `avatar` when set) until `expires_at`, or until the minting key is revoked "
                         "(then its open streams end too). Use it as `Authorization: Bearer <token>` or as the "
                         "WebSocket subprotocol `bearer.<token>`. A token cannot mint tokens.",
             responses={422: {"model": ErrorBody, "description": "expires_in over token_max_seconds, or an "
                                                                 "avatar id that is not valid"}})
async def mint_token(body: TokenRequest, engine: RenderEngine, principal: Caller("render")) -> TokenOut:
    if principal.token:
        raise PermissionDenied("a session token cannot mint tokens: mint them with an API key", field="authorization")
    limit = engine.settings.token_max_seconds
    if body.expires_in > limit:
        raise InvalidArgument(f"expires_in is at most {limit} seconds (the setting token_max_seconds); got "
                              f"{body.expires_in}", field="expires_in")
    if body.avatar is not None:
        engine.avatar_info(body.avatar, principal)  # NotFound, or PermissionDenied: another tenant's
    if principal.key_id is None or principal.tenant is None:  # auth off: no key to mint with
        raise InvalidArgument("session tokens need authentication (auth=keys)", field="authorization")
    token, expires_at = engine.access.tokens.mint(principal.key_id, principal.tenant, body.avatar, body.expires_in)
    return TokenOut(token=token, expires_at=expires_at, scope="render", avatar=body.avatar, tenant=principal.tenant)
