"""Session tokens: short-lived, render-only credentials a backend mints with its key (``POST /v1/tokens``) for a
browser, so that a secret key never has to be in a page.

A token is ``bst.<payload>.<sig>``: ``payload`` is the URL-safe base64 (no padding) of compact JSON
``{"k": minting key id, "t": tenant, "a": avatar id or null, "s": "render", "e": expiry, unix seconds}`` and
``sig`` the URL-safe base64 of HMAC-SHA256(secret, ``"bst." + payload``). Every character is valid in a WebSocket
subprotocol (``bearer.<token>``) and in an ``Authorization: Bearer`` header.

Nothing is stored: :class:`Tokens` signs and verifies, and :meth:`service.access.auth.Access.authenticate` turns a
valid token into a :class:`~service.access.auth.Principal` with the ``render`` scope, the minting key's id and
tenant, and the token's avatar (the only one it may read or stream, when set). The minting key must still be
active: revoking it refuses the tokens it minted (within the key cache's seconds) and ends their open streams
(the streams' periodic key check asks after the minting key).

The secret: the ``token_secret`` setting (replicas must share one), else ``<data_dir>/token.secret`` (32 random
bytes, hex, mode 0600), created on first use.
"""

from __future__ import annotations

import base64
import binascii
import dataclasses
import hashlib
import hmac
import json
import secrets
import threading
import time
from pathlib import Path

from render_core.atomic import create_once

from ..settings import Settings

PREFIX = "bst"
SCOPE = "render"
SECRET_FILE = "token.secret"
MAX_LENGTH = 2048  # a token longer than this is not one of ours


class TokenInvalid(ValueError):
    """A token that is malformed, badly signed or expired (the message says which; never the secret)."""


@dataclasses.dataclass(frozen=True)
class Claims:
    """What a verified token says: the minting key, its tenant, the avatar (None: any the tenant may read) and the
    expiry (unix seconds)."""

    key_id: str
    tenant: str
    avatar: str | None
    expires_at: int


def is_token(text: str | None) -> bool:
    """Whether ``text`` has the form of a session token (then it is never checked as an API key)."""
    return bool(text) and text.startswith(PREFIX + ".")


def _b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode("ascii")


def _unb64(text: str) -> bytes:
    return base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))


class Tokens:
    """Mints and verifies session tokens with the process's secret (read or created on first use)."""

    def __init__(self, settings: Settings):
        self.settings = settings
        self._secret: bytes | None = None
        self._lock = threading.Lock()

    def secret(self) -> bytes:
        with self._lock:
            if self._secret is None:
                configured = self.settings.token_secret
                self._secret = configured.encode("utf-8") if configured else _file_secret(
                    Path(self.settings.data_dir) / SECRET_FILE)
            return self._secret

    def _sign(self, payload: str) -> str:
        return _b64(hmac.new(self.secret(), f"{PREFIX}.{payload}".encode("ascii"), hashlib.sha256).digest())

    def mint(self, key_id: str, tenant: str, avatar: str | None, seconds: int) -> tuple[str, int]:
        """A token for the key ``key_id`` of ``tenant`` valid ``seconds`` from now (the caller bounds them), and
        its expiry in unix seconds."""
        expires_at = int(time.time()) + int(seconds)
        claims = {"k": key_id, "t": tenant, "a": avatar, "s": SCOPE, "e": expires_at}
        payload = _b64(json.dumps(claims, separators=(",", ":")).encode("utf-8"))
        return f"{PREFIX}.{payload}.{self._sign(payload)}", expires_at

    def verify(self, token: str) -> Claims:
        """The claims of a well-formed, correctly signed, unexpired token; TokenInvalid naming what is wrong. The
        signature is compared in constant time, before the payload is read."""
        parts = token.split(".") if len(token) <= MAX_LENGTH else []
        if len(parts) != 3 or parts[0] != PREFIX or not parts[1] or not parts[2]:
            raise TokenInvalid("the session token is malformed (bst.<payload>.<signature>)")
        if not hmac.compare_digest(self._sign(parts[1]).encode("ascii"), parts[2].encode("ascii", "replace")):
            raise TokenInvalid("the session token's signature is not valid")
        try:
            raw = json.loads(_unb64(parts[1]))
            claims = Claims(raw["k"], raw["t"], raw["a"], raw["e"])
            ok = raw["s"] == SCOPE and isinstance(claims.key_id, str) and isinstance(claims.tenant, str) \
                and isinstance(claims.expires_at, int) and (claims.avatar is None or isinstance(claims.avatar, str))
        except (binascii.Error, ValueError, TypeError, KeyError):
            ok = False
        if not ok:
            raise TokenInvalid("the session token's payload is not valid")
        if claims.expires_at <= time.time():
            raise TokenInvalid(f"the session token expired (its expiry was {claims.expires_at}, unix seconds; mint a "
                               "new one)")
        return claims


def _file_secret(path: Path) -> bytes:
    """The secret in ``path``, created (32 random bytes as hex, mode 0600, published atomically so that processes
    starting together agree) when there is none."""
    existing = _read(path)
    if existing is not None:
        return existing
    create_once(path, secrets.token_hex(32) + "\n")  # another process may have got there first: its secret wins
    secret = _read(path)
    if secret is None:
        raise ValueError(f"token secret: {path} is empty")
    return secret


def _read(path: Path) -> bytes | None:
    try:
        text = path.read_text(encoding="ascii").strip()
    except FileNotFoundError:
        return None
    return text.encode("ascii") if text else None
