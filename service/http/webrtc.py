"""WebRTC signalling in the WHEP style (the egress counterpart of WHIP, RFC 9725): a thin adapter over
:class:`service.webrtc.peer.Peers`, which opens the engine session.

- ``POST /v1/webrtc?avatar=ID&size=N&codecs=h264,vp8`` with an ``application/sdp`` offer (at most
  ``webrtc_max_offer_bytes``; it must have a recvonly video section and a data channel) answers 201 with the SDP
  answer (all the server's candidates in it), ``Location: /v1/webrtc/{session_id}`` and the ICE servers as
  ``Link: <URL>; rel="ice-server"`` headers (TURN with short-lived credentials). A bad offer: 422 naming the SDP
  problem (field ``sdp``).
- ``PATCH /v1/webrtc/{session_id}`` with an ``application/trickle-ice-sdpfrag`` fragment adds the client's
  trickled candidates (``a=end-of-candidates`` ends them): 204. ICE restarts are not supported.
- ``DELETE /v1/webrtc/{session_id}`` closes the session: 204.

The key's ``render`` scope is needed as for every stream; a session is its key's (another key gets 404; admin
keys may close any).
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Path, Query, Request, Response
from starlette.requests import HTTPConnection

from ..engine import AVATAR_ID_PATTERN
from ..errors import InvalidArgument
from ..webrtc.ice import link_headers
from ..webrtc.peer import Peers
from .dependencies import Caller, RenderEngine, bounded_body

router = APIRouter(tags=["webrtc"])
SDP = "application/sdp"
FRAGMENT = "application/trickle-ice-sdpfrag"
SESSION_ID = Annotated[str, Path(pattern=r"^[0-9a-f]{32}$", description="the session id (the Location's last part)")]
CODECS_PATTERN = r"^\s*(h264|vp8)\s*(,\s*(h264|vp8)\s*)*$"


def peers_of(connection: HTTPConnection) -> Peers:
    return connection.app.state.webrtc


WebRTCPeers = Annotated[Peers, Depends(peers_of)]


def _text_body(media_type: str, limit: int, description: str) -> dict:
    schema = {"type": "string", "maxLength": limit}
    return {"required": True, "description": description + f" ({media_type}; text/plain is taken too)",
            "content": {media_type: {"schema": schema}, "text/plain": {"schema": schema}}}


def offer_body(limit: int) -> dict:
    """The OpenAPI request body of the POST: SDP text up to ``limit`` bytes."""
    return _text_body(SDP, limit, "the client's SDP offer (RFC 8866): a recvonly video section and a data channel "
                                  "(m=application ... webrtc-datachannel)")


def fragment_body(limit: int) -> dict:
    return _text_body(FRAGMENT, limit, "trickled ICE candidates (RFC 8840): a=mid, a=candidate lines, "
                                       "a=end-of-candidates")


ANSWER_RESPONSE = {"description": "the SDP answer", "content": {SDP: {"schema": {"type": "string"}}}, "headers": {
    "Location": {"description": "the session's URL (PATCH trickled candidates, DELETE to close)",
                 "schema": {"type": "string"}},
    "Link": {"description": 'an ICE server: <stun:...> or <turn:...>; rel="ice-server" (TURN with username and '
                            'credential, coturn\'s use-auth-secret scheme); one header per server',
             "schema": {"type": "string"}}}}


def _media_type(request: Request, wanted: str) -> None:
    """The body's media type must be ``wanted`` (or text/plain: a client that cannot name it; the same text)."""
    given = request.headers.get("content-type", "").split(";", 1)[0].strip().lower()
    if given not in (wanted, "text/plain"):
        raise InvalidArgument(f"the body must be SDP sent as Content-Type: {wanted} (got {given or 'none'!r})",
                              field="content-type")


@router.post("/v1/webrtc", status_code=201, response_class=Response, responses={201: ANSWER_RESPONSE},
             summary="Open a WebRTC session (WHEP): an SDP offer in, the SDP answer out",
             description="The avatar comes as a video track (H.264 constrained baseline or VP8, as codecs lists them "
                         "by preference); the client drives it on its data channel with the WebSocket stream's "
                         "messages (StreamRequest as protobuf JSON: frame, end) and gets per-frame timing, errors "
                         "and the final status on it. Counts against the key's streams.")
async def open_session(request: Request, engine: RenderEngine, peers: WebRTCPeers, principal: Caller("render"),
                       avatar: Annotated[str, Query(pattern=AVATAR_ID_PATTERN.pattern, max_length=128,
                                                    description="avatar id")],
                       size: Annotated[int, Query(ge=16, le=8192, description="width and height in pixels")] = 512,
                       codecs: Annotated[str, Query(pattern=CODECS_PATTERN, max_length=64,
                                                    description="video codecs by preference")] = "h264,vp8",
                       ) -> Response:
    _media_type(request, SDP)
    s = engine.settings
    offer = await bounded_body(request, s.webrtc_max_offer_bytes)
    peer, answer = await peers.open(principal, avatar, size, codecs, offer)
    response = Response(answer, status_code=201, media_type=SDP, headers={"Location": f"/v1/webrtc/{peer.id}"})
    for link in link_headers(s.webrtc_stun_urls, s.webrtc_turn_urls, s.webrtc_turn_secret,
                             s.webrtc_turn_ttl_seconds):
        response.headers.append("Link", link)
    return response


@router.patch("/v1/webrtc/{session_id}", status_code=204, response_class=Response,
              summary="Trickle ICE candidates to a WebRTC session",
              responses={204: {"description": "the candidates were added"}})
async def trickle(request: Request, session_id: SESSION_ID, engine: RenderEngine, peers: WebRTCPeers,
                  principal: Caller("render")) -> Response:
    from ..webrtc.sdp import parse_fragment

    peer = peers.get(session_id, principal)
    _media_type(request, FRAGMENT)
    candidates, end = parse_fragment(await bounded_body(request, engine.settings.webrtc_max_offer_bytes))
    await peer.add_candidates(candidates, end)
    return Response(status_code=204)


@router.delete("/v1/webrtc/{session_id}", status_code=204, response_class=Response,
               summary="Close a WebRTC session", responses={204: {"description": "closed"}})
async def close_session(session_id: SESSION_ID, peers: WebRTCPeers, principal: Caller("render")) -> Response:
    await peers.get(session_id, principal).close("deleted")
    return Response(status_code=204)
