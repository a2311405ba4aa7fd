"""A WebRTC session (:class:`Peer`): one RTCPeerConnection, one engine session, one video track, one data channel;
and the process's sessions (:class:`Peers`).

- The engine session is opened like a WebSocket's (the key's stream limit, the server's session limit, the
  avatar's read rule); its frames go, as 4:2:0 planes, to the :class:`~.track.FrameTrack`, whose
  encoder is aiortc's sender's (the classes of :mod:`.encoder`: H.264 at a fast libx264 preset). Frames come from
  the one scheduler and render thread as every other stream's.
- The data channel carries the WebSocket stream's messages: the client sends ``StreamRequest`` as protobuf JSON
  (text) or protobuf (binary), ``frame`` and ``end`` (the session is open already: ``open`` is refused), validated
  by the same session code; the server sends JSON: the session's ``header`` once the channel is open, an ``error``
  per refused message, the final ``status``, and per frame sent on the video track a ``frame`` (a
  ``RenderedFrame`` without data: index, client time, timings, where ``encode_ms`` is the video encoder's call
  for this frame (the codec and RTP packetisation of the track's 4:2:0 frame; wall time) and ``total_ms`` runs
  from the pose's receipt to its RTP packets) with ``video``: ``{"pts", "codec", "waitMs"`` (rendered to handed
  to the encoder), ``"sendMs"`` (handed to the encoder to its RTP packets sent: the executor's queue, the encode,
  the sending), ``"encodeCpuMs"}`` (the encoder call's CPU time: the encode cost).
- Flow: the engine hands each rendered frame to the track as it is delivered (the session's ``frame_sink``: the
  pixels as the render thread made them, no protobuf copy, no queue); the track acknowledges a frame to the engine
  when it hands it to the encoder or drops it for a newer one, so the engine renders as fast as the peer takes
  frames, and newest wins at both ends.
- Closing (:meth:`Peer.close`, once): the peer connection's failure or close (ICE, DTLS, the client's close), no
  connection within ``webrtc_connect_seconds``, nothing heard from the peer (RTCP receiver reports, data-channel
  messages) for ``webrtc_peer_timeout_seconds``, ``DELETE``, the data channel closed by the client, and the end of
  the engine session (a drain, a revoked key, the stream's maximum duration, the client's ``end``: the final status
  is sent on the data channel first), and the server's shutdown (:meth:`Peers.drain`: what the drain left open).
  Each frees the engine session and the ``blendsplat_webrtc_sessions`` slot.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time

from aiortc import RTCPeerConnection, RTCRtpSender, RTCSessionDescription
from google.protobuf import json_format
from google.protobuf.message import DecodeError

from blendsplat.v1 import render_pb2 as pb

from ..access.auth import Principal
from ..engine import Engine, Session
from ..errors import InvalidArgument, NotFound, to_status
from . import encoder, ice, messages
from .sdp import check_offer, parse_codecs
from .track import FrameTrack, Pending

log = logging.getLogger(__name__)
MAX_OUTBOX = 64  # replies waiting for the data channel to open
FLUSH_SECONDS = 0.5  # a final status gets this long to leave before the connection closes


def _json(message) -> str:
    return json_format.MessageToJson(message, indent=None)


class Peer:
    """One WebRTC session; built by :meth:`Peers.open`."""

    def __init__(self, peers: Peers, session: Session, pc: RTCPeerConnection, codecs: list[str]):
        self.peers, self.session, self.pc = peers, session, pc
        self.id = session.id
        self.key_id = session.principal.key_id
        out = session.out
        self.track = FrameTrack(out.width, out.height, self._sent, self._done)
        session.sink_frames(self._frame, yuv420=True)  # rendered frames straight to the track, in 4:2:0
        self.codecs = codecs
        self.codec = ""  # negotiated
        self.transceiver = None
        self.channel = None
        self.outbox: list[str] = []
        self.created = self.heard = time.monotonic()
        self.connected = False
        self.closed = False
        self._remote_report = None
        self._tasks: list[asyncio.Task] = []

    # ---------------------------------------------------------------------------------------------- set-up
    async def negotiate(self, offer: str) -> str:
        pc = self.pc
        transceiver = self.transceiver = pc.addTransceiver(self.track, direction="sendonly")
        capabilities = RTCRtpSender.getCapabilities("video").codecs
        preferred = [c for name in self.codecs for c in capabilities if c.mimeType.lower() == f"video/{name.lower()}"]
        transceiver.setCodecPreferences(preferred + [c for c in capabilities if c.mimeType.lower() == "video/rtx"])
        pc.on("datachannel", self._channel)
        pc.on("connectionstatechange", self._state)
        try:
            await pc.setRemoteDescription(RTCSessionDescription(sdp=offer, type="offer"))
        except Exception as e:  # noqa: BLE001 - aiortc's parse and validation errors: a bad offer
            raise InvalidArgument(f"SDP offer: {type(e).__name__}: {str(e)[:300]}", field="sdp") from None
        await pc.setLocalDescription(await pc.createAnswer())  # gathers the host (and STUN) candidates
        self.codec = next((c.mimeType.split("/")[1] for c in transceiver._codecs  # the one aiortc sends with
                           if not c.mimeType.lower().endswith("/rtx")), "")
        encoder.install(transceiver.sender, self.codec)  # H.264: libx264 set for several streams (encoder.py)
        self._tasks = [asyncio.create_task(self._pump(), name=f"webrtc-pump-{self.id}"),
                       asyncio.create_task(self._watch(), name=f"webrtc-watch-{self.id}")]
        return pc.localDescription.sdp

    async def add_candidates(self, candidates: list[tuple[str | None, str]], end: bool) -> None:
        from aiortc.sdp import candidate_from_sdp

        for mid, text in candidates:
            try:
                candidate = candidate_from_sdp(text.split(":", 1)[1])
            except (ValueError, IndexError):
                raise InvalidArgument(f"SDP fragment: not an ICE candidate: {text[:100]!r}", field="sdp") from None
            candidate.sdpMid = mid
            candidate.sdpMLineIndex = 0 if mid is None else None
            await self.pc.addIceCandidate(candidate)
        if end:
            await self.pc.addIceCandidate(None)

    # ------------------------------------------------------------------------------------------ the channel
    def _channel(self, channel) -> None:
        if self.channel is not None:
            return
        self.channel = channel
        channel.on("message", self._message)
        channel.on("close", lambda: self._schedule_close("ended", "the client closed the data channel"))
        if channel.readyState == "open":
            self._opened()
        else:
            channel.on("open", self._opened)

    def _opened(self) -> None:
        self.send(_json(self.session.header()))
        pending, self.outbox = self.outbox, []
        for text in pending:
            self.send(text)

    def send(self, text: str) -> None:
        channel = self.channel
        if channel is None or channel.readyState != "open":
            if len(self.outbox) < MAX_OUTBOX:
                self.outbox.append(text)
            return
        with contextlib.suppress(Exception):  # a channel closing meanwhile: the close handler frees the session
            channel.send(text)

    def _message(self, data: str | bytes) -> None:
        self.heard = time.monotonic()
        if len(data) > self.peers.engine.settings.max_message_bytes:
            return self.session.error(to_status(InvalidArgument(
                f"the message is {len(data)} bytes; the limit is {self.peers.engine.settings.max_message_bytes}",
                field="message")))
        try:
            request = messages.parse(data)  # a plain pose without json_format's walk
        except (json_format.ParseError, DecodeError, RecursionError, ValueError, TypeError) as e:
            return self.session.error(to_status(InvalidArgument(
                f"not a blendsplat.v1.StreamRequest: {str(e)[:300]}", field="message")))
        self.session.handle(request)

    # ------------------------------------------------------------------------------------- frames out
    def _done(self, index: int) -> None:
        if not self.session.closed:
            self.session.handle(pb.StreamRequest(ack=pb.Ack(index=index)))

    def _sent(self, frame: Pending, now: float) -> None:
        cost = encoder.cost_of(self.transceiver.sender, frame.pts) if self.transceiver else None
        t = pb.StageTimings()
        t.CopyFrom(frame.timings)
        t.encode_ms = cost.wall_ms if cost else (now - frame.handed) * 1e3
        t.total_ms = frame.timings.total_ms + (now - frame.arrived) * 1e3
        reply = pb.StreamResponse(frame=pb.RenderedFrame(
            index=frame.index, client_time_us=frame.client_time_us, width=self.track.width,
            height=self.track.height, timings=t, dropped=frame.dropped,
            codec=pb.CODEC_H264 if self.codec.upper() == "H264" else pb.CODEC_UNSPECIFIED))
        body = json_format.MessageToDict(reply)
        body["video"] = {"pts": frame.pts, "codec": self.codec,
                         "waitMs": round((frame.handed - frame.arrived) * 1e3, 3),
                         "sendMs": round((now - frame.handed) * 1e3, 3)}
        if cost:
            body["video"]["encodeCpuMs"] = round(cost.cpu_ms, 3)
        self.send(json.dumps(body, separators=(",", ":")))

    def _frame(self, f: pb.RenderedFrame, data: bytes) -> None:
        """The engine's frame sink (on the loop, as the frame is delivered): to the track, newest wins."""
        self.track.put(Pending(f.index, f.client_time_us, data, f.timings, f.dropped))

    async def _pump(self) -> None:
        """The session's other replies (errors, the final status) to the data channel; then the close."""
        final = None
        async for reply in self.session.responses():
            self.send(_json(reply))
            if reply.WhichOneof("msg") == "status":
                final = reply.status
        if self.closed:
            return
        if final is not None and self.channel is not None:
            deadline = time.monotonic() + FLUSH_SECONDS
            while self.channel.bufferedAmount and time.monotonic() < deadline:
                await asyncio.sleep(0.02)
            await asyncio.sleep(0.05)  # the SCTP association sends what it was given
        reason = "ended" if final is None or final.code in (pb.OK, pb.CANCELLED) else (
            "drain" if final.code == pb.UNAVAILABLE else "ended")
        await self.close(reason)

    # --------------------------------------------------------------------------------------- liveness
    def _state(self) -> None:
        state = self.pc.connectionState
        if state == "connected":
            self.connected = True
            self.heard = time.monotonic()
        elif state in ("failed", "closed"):
            self._schedule_close("failed", f"the peer connection is {state}")

    async def _watch(self) -> None:
        s = self.peers.engine.settings
        while not self.closed:
            await asyncio.sleep(min(0.5, s.webrtc_peer_timeout_seconds / 4))
            now = time.monotonic()
            if not self.connected:
                if now - self.created > s.webrtc_connect_seconds:
                    return self._schedule_close("timeout", "the peer did not connect within "
                                                           f"{s.webrtc_connect_seconds:g} s")
                continue
            await self._heard_rtcp()
            if now - self.heard > s.webrtc_peer_timeout_seconds:
                return self._schedule_close("vanished", f"nothing heard from the peer for "
                                                        f"{s.webrtc_peer_timeout_seconds:g} s")

    async def _heard_rtcp(self) -> None:
        """A new RTCP receiver report from the peer counts as a sign of life."""
        for sender in self.pc.getSenders():
            with contextlib.suppress(Exception):
                for stats in (await sender.getStats()).values():
                    if stats.type == "remote-inbound-rtp" and stats.timestamp != self._remote_report:
                        self._remote_report = stats.timestamp
                        self.heard = time.monotonic()

    def _schedule_close(self, reason: str, why: str) -> None:
        if not self.closed:
            log.info("webrtc session %s: %s", self.id, why)
            asyncio.ensure_future(self.close(reason))

    async def close(self, reason: str) -> None:
        """Close the connection and free the engine session (once)."""
        if self.closed:
            return
        self.closed = True
        log.info("webrtc session %s closed (%s): %d frames sent, %d replaced by a newer one before encoding",
                 self.id, reason, self.track.sent, self.track.replaced)
        self.peers.forget(self, reason)
        self.peers.engine.close_session(self.session)  # no-op when it has ended
        self.track.stop()
        current = asyncio.current_task()
        for task in self._tasks:
            if task is not current:
                task.cancel()
        with contextlib.suppress(Exception):
            await self.pc.close()


class Peers:
    """The process's WebRTC sessions, by id."""

    def __init__(self, engine: Engine):
        s = engine.settings
        self.engine = engine
        self.peers: dict[str, Peer] = {}
        for name in ("aioice", "aiortc"):  # a line per ICE check and state change: not the service's log
            logging.getLogger(name).setLevel(max(logging.WARNING, logging.getLogger(name).level))
        if s.webrtc_host_addresses:
            ice.use_host_addresses(s.webrtc_host_addresses)
        _cap_bitrate(s.webrtc_max_bitrate)

    async def open(self, principal: Principal, avatar_id: str, size: int, codecs: str, offer: bytes
                   ) -> tuple[Peer, str]:
        """A new session from an SDP offer: (the peer, the SDP answer). The offer is checked before the engine
        session opens (a bad one costs no stream slot)."""
        names = parse_codecs(codecs)
        sdp = check_offer(offer, names)
        session = await self.engine.open(pb.SessionConfig(avatar_id=avatar_id, width=size, height=size,
                                                          codec=pb.CODEC_RAW_RGBA), "webrtc", principal)
        pc = RTCPeerConnection(ice.server_configuration(self.engine.settings.webrtc_stun_urls))
        peer = Peer(self, session, pc, names)
        self.peers[peer.id] = peer
        self.engine.metrics.webrtc_sessions.set(len(self.peers))
        try:
            answer = await peer.negotiate(sdp)
        except BaseException:
            await peer.close("failed")
            raise
        return peer, answer

    def get(self, peer_id: str, principal: Principal) -> Peer:
        """The caller's session (another key's is NotFound, as is a closed one; admin keys: any)."""
        peer = self.peers.get(peer_id)
        if peer is None or peer.closed or not (principal.admin or principal.key_id == peer.key_id):
            raise NotFound(f"no WebRTC session {peer_id[:64]!r}", field="session_id")
        return peer

    def forget(self, peer: Peer, reason: str) -> None:
        if self.peers.pop(peer.id, None) is not None:
            self.engine.metrics.webrtc_sessions.set(len(self.peers))
            self.engine.metrics.webrtc_closed.labels(reason).inc()

    async def close_all(self, reason: str = "drain") -> None:
        await asyncio.gather(*(p.close(reason) for p in list(self.peers.values())), return_exceptions=True)

    async def drain(self, timeout: float) -> None:
        """The end of a server's drain, once the engine has ended every session: each peer sends its final status
        and closes itself (within :data:`FLUSH_SECONDS`); whatever is still open after that, or after ``timeout``
        if sooner, is closed here, so no peer connection outlives the server."""
        deadline = time.monotonic() + min(timeout, FLUSH_SECONDS + 0.25)
        while self.peers and time.monotonic() < deadline:
            await asyncio.sleep(0.02)
        await self.close_all("drain")


def _cap_bitrate(max_bps: int) -> None:
    """aiortc's encoders follow the receiver's REMB estimate between their own bounds (H.264 0.5 to 3 Mbit/s,
    starting at 1; VP8 0.25 to 1.5, starting at 0.5); the highest becomes this process's ``webrtc_max_bitrate``
    (aiortc reads the module's bounds whenever the estimate changes; the start is lowered to it when above)."""
    for module, (start, _) in _AIORTC_BITRATES.items():
        module.MAX_BITRATE = max(module.MIN_BITRATE, max_bps)
        module.DEFAULT_BITRATE = min(start, module.MAX_BITRATE)


def _aiortc_bitrates() -> dict:
    from aiortc.codecs import h264, vpx

    return {m: (m.DEFAULT_BITRATE, m.MAX_BITRATE) for m in (h264, vpx)}


_AIORTC_BITRATES = _aiortc_bitrates()  # aiortc's own (start, highest)
