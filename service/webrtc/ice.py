"""ICE for the WebRTC transport: local addresses, remote candidates, STUN and TURN.

aioice (aiortc's ICE) gathers a host candidate on every interface address except 127.0.0.1 and ::1, and binds
each to an ephemeral port (it has no port range: a deployment that cannot open the ephemeral UDP range puts TURN
in front, see the README's WebRTC section). :func:`use_host_addresses` replaces that gathering for the whole
process: with a list set, those addresses and no others are gathered and offered (an empty list restores aioice's
own). A server whose addresses are all loopback also ignores every remote candidate that is not a loopback address
(:func:`remote_allowed`): on a test machine no other address is ever a target.

TURN credentials follow coturn's ``use-auth-secret`` (the TURN REST API draft): the username is
``EXPIRY:LABEL`` (a Unix time), the credential ``base64(HMAC-SHA1(secret, username))``; coturn checks both and
refuses an expired username. Clients get the ICE servers as WHEP's ``Link: <URL>; rel="ice-server"`` headers.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import ipaddress
import threading
import time

import aioice.ice
from aiortc import RTCConfiguration, RTCIceServer

_original_get_host_addresses = aioice.ice.get_host_addresses
_lock = threading.Lock()
_host_addresses: tuple[str, ...] = ()


def _configured_host_addresses(use_ipv4: bool, use_ipv6: bool) -> list[str]:
    """aioice's ``get_host_addresses`` with the process's list set: exactly those addresses (of the families
    asked for), nothing gathered from the interfaces."""
    chosen = _host_addresses
    if not chosen:
        return _original_get_host_addresses(use_ipv4=use_ipv4, use_ipv6=use_ipv6)
    return [a for a in chosen if (ipaddress.ip_address(a).version == 4 and use_ipv4)
            or (ipaddress.ip_address(a).version == 6 and use_ipv6)]


def use_host_addresses(addresses: list[str] | tuple[str, ...]) -> None:
    """Gather host candidates on ``addresses`` only, in this process (empty: aioice's own gathering)."""
    global _host_addresses
    for address in addresses:
        ipaddress.ip_address(address)  # ValueError for anything else
    with _lock:
        _host_addresses = tuple(addresses)
        aioice.ice.get_host_addresses = _configured_host_addresses


def host_addresses() -> tuple[str, ...]:
    """The process's host addresses (empty: aioice's own gathering)."""
    return _host_addresses


def loopback_only() -> bool:
    return bool(_host_addresses) and all(ipaddress.ip_address(a).is_loopback for a in _host_addresses)


def remote_allowed(host: str) -> bool:
    """Whether a remote candidate's address may be a target: any, unless this process gathers on loopback
    addresses only; then loopback addresses only (an mDNS name is never resolved then)."""
    if not loopback_only():
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def server_configuration(stun_urls: list[str]) -> RTCConfiguration:
    """The server's own peer configuration: the first STUN server for its server-reflexive candidate (the server
    never relays through TURN: clients do)."""
    stun = [u for u in stun_urls if u.startswith("stun:")][:1]
    return RTCConfiguration(iceServers=[RTCIceServer(urls=stun)] if stun else [])


def turn_credentials(secret: str, ttl_seconds: float, label: str = "blendsplat",
                     now: float | None = None) -> tuple[str, str]:
    """(username, credential) valid for ``ttl_seconds`` in coturn's use-auth-secret scheme."""
    expiry = int((time.time() if now is None else now) + ttl_seconds)
    username = f"{expiry}:{label}"
    digest = hmac.new(secret.encode(), username.encode(), hashlib.sha1).digest()
    return username, base64.b64encode(digest).decode()


def _quoted(value: str) -> str:
    return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'


def link_headers(stun_urls: list[str], turn_urls: list[str], turn_secret: str | None,
                 ttl_seconds: float) -> list[str]:
    """The ICE servers as WHEP ``Link`` header values: STUN as they are, TURN with fresh credentials."""
    links = [f'<{url}>; rel="ice-server"' for url in stun_urls]
    if turn_urls and turn_secret:
        username, credential = turn_credentials(turn_secret, ttl_seconds)
        links += [f'<{url}>; rel="ice-server"; username={_quoted(username)}; credential={_quoted(credential)}; '
                  'credential-type="password"' for url in turn_urls]
    return links
