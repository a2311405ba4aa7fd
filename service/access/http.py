"""API keys on the HTTP transport: the ``Authorization: Bearer`` dependency every protected route declares, and the
WebSocket's key (a ``bearer.<key>`` subprotocol) and Origin check. The rules are :mod:`service.access.auth`'s.

A route declares what it needs as a parameter, ``principal: Caller("render")``; the OpenAPI document then lists
the bearer scheme on it. ``tests/test_auth.py`` walks the app's routes: one without a key is refused unless it is
in :data:`OPEN_PATHS`.
"""

from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING, Annotated, Any
from urllib.parse import urlsplit

from fastapi import Depends, Request, WebSocket
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from .auth import WS_PROTOCOL, PermissionDenied, Principal, ws_key

if TYPE_CHECKING:
    from ..engine import Engine

# Routes that need no key: probes, metrics, the API description and the static pages (they ask for a key), and
# the Swagger UI assets (/static/swagger: a mount, and its gzipped script served by a route).
OPEN_PATHS = frozenset({"/healthz", "/readyz", "/metrics", "/openapi.json", "/docs", "/docs/oauth2-redirect",
                        "/demo", "/jobs", "/favicon.ico", "/static/swagger/swagger-ui-bundle.js"})

_scheme = HTTPBearer(auto_error=False, scheme_name="apiKey",
                     description="An API key (`blendsplat keys create`, or the admin key in <data_dir>/admin.key), "
                                 "sent as `Authorization: Bearer bsk_...`.")


def _engine(request: Request | WebSocket) -> Engine:
    return request.app.state.engine


def need(scope: str):
    """The dependency of a route that needs ``scope``: the caller, authenticated (401) and allowed (403)."""
    async def caller(request: Request,
                     credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_scheme)]) -> Principal:
        token = credentials.credentials if credentials is not None else None  # None: absent, or not "Bearer"
        principal = await asyncio.to_thread(_engine(request).access.authenticate, token)
        request.state.principal = principal
        return principal.require(scope)
    caller.__name__ = f"needs_{scope.replace(':', '_')}"
    return caller


def Caller(scope: str) -> Any:  # noqa: N802 - used as a type: principal: Caller("render")
    """``Annotated[Principal, Depends(need(scope))]``."""
    return Annotated[Principal, Depends(need(scope))]


def same_origin(origin: str, host: str | None) -> bool:
    parts = urlsplit(origin)
    return bool(host) and parts.netloc.lower() == host.lower()


async def websocket_caller(ws: WebSocket, scope: str) -> Principal:
    """The caller of a WebSocket (before it is accepted): the Origin must be this server or an allowed one
    (PermissionDenied), the key comes from the ``bearer.<key>`` subprotocol."""
    engine = _engine(ws)
    origin = ws.headers.get("origin")
    if origin and not (same_origin(origin, ws.headers.get("host")) or origin in engine.settings.allowed_origins):
        raise PermissionDenied(f"the origin {origin[:100]!r} is not allowed (setting allowed_origins)",
                               field="origin")
    token = ws_key(ws.scope.get("subprotocols") or [])
    principal = await asyncio.to_thread(engine.access.authenticate, token)
    return principal.require(scope)


def websocket_subprotocol(ws: WebSocket) -> str | None:
    """The subprotocol to answer with: ``blendsplat.v1`` when offered (never the key's)."""
    return WS_PROTOCOL if WS_PROTOCOL in (ws.scope.get("subprotocols") or []) else None
